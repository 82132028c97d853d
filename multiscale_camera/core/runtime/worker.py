"""A worker process's side: read tasks from standard input, run them, write results to a
private copy of standard output (what tasks print goes to standard error).

Messages from the parent: ``("job", job, payload)`` (the function of a run, pickled by
``wire.dump_payload``), ``("item", job, index, item)``, ``("release",)`` (forget the
job: its shared memory is unmapped). Replies: ``("ready", pid)`` once,
``("done", job, index, result)``, ``("failed", job, index, traceback)``,
``("cancelled", job, index)``. The worker ends at the end of its input.

Also ``Context``, what a task gets besides its item, in a worker or in the parent.
"""

import os
import signal
import sys
import traceback

import numpy as np

from ..errors import Cancelled
from .shared import Segment
from .wire import MARKER, encode, load_payload, read_message, write_frame, write_message

# The control segment's words (int64): beats counted by the worker, the job the parent
# cancelled.
BEAT, CANCEL = 0, 1
CONTROL_WORDS = 2


class Context:
    """What a task gets besides its item: ``task(item, context)``.

    Calling it is the task's ``should_stop``: in a worker it counts a beat (the parent
    then knows the worker is making progress, however long the item takes) and says
    whether the parent cancelled the run; in the parent it asks the run's own
    ``should_stop``. ``memo`` is a dict kept for the life of the process that runs the
    task (a worker keeps it across runs: a BVH tree rebuilt once, say);
    ``in_worker`` says where the task runs.
    """

    def __init__(self, should_stop=None, control=None, memo=None):
        self._should_stop = should_stop
        self._control = control
        self.memo = {} if memo is None else memo
        self.job = 0

    @property
    def in_worker(self):
        return self._control is not None

    def __call__(self):
        control = self._control
        if control is not None:
            control[BEAT] += 1
            return int(control[CANCEL]) == self.job
        return self._should_stop is not None and bool(self._should_stop())


def probe(item, context):
    """A task that only says where it ran: (item, pid, in_worker, the names of the
    extension's modules imported there, whether bpy is)."""
    package = __name__.rsplit(".", 3)[0]
    mine = sorted(name for name in sys.modules if name.startswith(package + "."))
    return item, os.getpid(), context.in_worker, mine, "bpy" in sys.modules


def touch(arrays, item, context):
    """A task that reads every element of ``arrays`` (tuple of ndarrays): their float64
    sums. What data costs to reach a worker (bench/workers.py)."""
    return tuple(float(a.sum(dtype=np.float64)) for a in arrays)


def serve(control_name):
    """The worker's loop (the bootstrap's last call); returns at the end of its input."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl+C in a terminal is the parent's
    if hasattr(signal, "SIGTERM"):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # whatever the host installed
    sys.stdout.flush()
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # what tasks and the host print goes to standard error from now on
    source = os.fdopen(os.dup(0), "rb")
    control_segment = Segment.attach(control_name, CONTROL_WORDS * 8)
    control = control_segment.array((CONTROL_WORDS,), np.int64)
    context = Context(control=control)
    out.write(MARKER)
    write_message(out, ("ready", os.getpid()))
    function = failure = None
    segments = {}
    while True:
        message = read_message(source)
        if message is None:
            return
        kind = message[0]
        if kind == "job":
            function = failure = None
            segments = {}
            context.job = message[1]
            try:
                function = load_payload(message[2], segments)
            except BaseException:  # e.g. a module the parent has and this process lacks
                failure = traceback.format_exc()
        elif kind == "release":
            function = failure = None
            segments = {}
        elif kind == "item":
            _, job, index, item = message
            write_frame(out, _run(function, failure, job, index, item, context))


def _run(function, failure, job, index, item, context):
    """The reply to an item, encoded."""
    if failure is not None:
        return encode(("failed", job, index, failure))
    try:
        result = function(item, context)
    except Cancelled:
        return encode(("cancelled", job, index))
    except BaseException:
        return encode(("failed", job, index, traceback.format_exc()))
    try:
        return encode(("done", job, index, result))
    except BaseException:  # a result that cannot be pickled
        return encode(("failed", job, index, traceback.format_exc()))
