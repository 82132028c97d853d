"""What the user reads when work fails: one message per error, never a traceback.

The engine, the operators and the viewport turn every exception of their work into a
message here (``failure_message``). The errors the renderer raises on purpose
(``RigError``, ``SolverDidNotConverge``, ``ExrError``) already say what to change and are
passed on as they are; a file that cannot be read or written names the file; anything
else is a defect of the extension: its traceback goes to the system console and the user
reads what failed, that nothing was written, and where the details are
(docs/failures.md lists each case).
"""

import traceback

from ..core.errors import RigError, SolverDidNotConverge
from ..io.exr import ExrError

# Errors whose text is written for the user.
SAID = (RigError, SolverDidNotConverge, ExrError)
DETAILS = "the details are in the system console (Window > Toggle System Console)"


def failure_message(err: BaseException, action: str = "The render") -> str:
    """The one message the user reads for ``err``, raised while doing ``action`` (a
    capitalised noun phrase: "The render", "Compute Field"). Prints the traceback of an
    unexpected error to the console."""
    if isinstance(err, SAID):
        return str(err)
    if isinstance(err, OSError):
        if not err.filename:  # raised by the extension with its own words
            return str(err)
        return (
            f"{action} could not use the file '{err.filename}': {err.strerror or err}; "
            "nothing was written (check the path and its folder's permissions)"
        )
    traceback.print_exception(err)
    return f"{action} failed ({type(err).__name__}: {err}); nothing was written; {DETAILS}"
