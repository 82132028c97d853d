"""How worker processes start: a fresh interpreter (never a copy of this process), told by
a short bootstrap where this package lives and under which name.

The package is imported in the worker under the dotted name it has here
(``multiscale_camera``, or ``bl_ext.<repo>.multiscale_camera`` inside Blender), so that
the functions a task names by module and name (as pickle does) are found there. The
bootstrap loads the package from its folder by that name (``importlib``), after empty
stand-ins for the names above it (``bl_ext``, ``bl_ext.<repo>``) when the worker has
none: the package's ``__init__`` imports nothing (bpy is imported by ``register``), so
a worker that runs core tasks imports numpy and the core alone. The parent's
``sys.path`` is appended to the worker's, so that what the parent imports (numpy in
Blender's bundled site-packages, the modules tests name) the worker finds too.
"""

import os
import sys
from dataclasses import dataclass
from pathlib import Path

# The package: this module is <package>.core.runtime.launch.
PACKAGE = __name__.rsplit(".", 3)[0]
FOLDER = str(Path(__file__).resolve().parents[2])
# The worker's module, under the package.
WORKER = __name__.rsplit(".", 1)[0] + ".worker"

BOOTSTRAP = """
import importlib, importlib.util, sys, types
def _multiscale_worker(name, folder, path, worker, control):
    sys.path.extend(p for p in path if p not in sys.path)
    parts = name.split(".")
    for i in range(1, len(parts)):
        if ".".join(parts[:i]) not in sys.modules:
            stand_in = types.ModuleType(".".join(parts[:i]))
            stand_in.__path__ = []
            sys.modules[stand_in.__name__] = stand_in
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(
            name, folder + "/__init__.py", submodule_search_locations=[folder])
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    importlib.import_module(worker).serve(control)
_multiscale_worker({name!r}, {folder!r}, {path!r}, {worker!r}, {control!r})
"""

# Environment of every worker: one thread each for numpy's BLAS (the workers are one
# per core already; OpenBLAS threads would spin on the others' cores after each call).
ENVIRONMENT = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@dataclass(frozen=True)
class Launcher:
    """A kind of worker process: the command that starts one.

    name : str, the kind (one pool a kind). prefix : tuple of str, the command up to
    the Python code it runs (the bootstrap). preamble : str, Python run before the
    bootstrap (``import bpy`` where mathutils comes with bpy).
    """

    name: str
    prefix: tuple
    preamble: str = ""

    def command(self, control):
        """list of str: the command that starts a worker whose control segment is
        named ``control``."""
        code = BOOTSTRAP.format(
            name=PACKAGE, folder=FOLDER, path=list(sys.path), worker=WORKER, control=control
        )
        return [*self.prefix, self.preamble + "\n" + code]

    @staticmethod
    def environment():
        """dict: the workers' environment (this process's, BLAS threads at one)."""
        return {**os.environ, **ENVIRONMENT}


def python_launcher():
    """Workers in a plain Python: this interpreter's own executable (inside Blender, its
    bundled Python), isolated from PYTHON* variables and the user's site-packages (the
    parent's ``sys.path`` is passed on instead)."""
    return Launcher("python", (sys.executable, "-I", "-c"))
