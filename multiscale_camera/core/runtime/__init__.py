"""One worker runtime for the whole extension: work spread over worker processes that
start without copying this process, stay for the next run, and write results into
shared memory.

The field's trace and the renderer's casts are Python loops over numpy arrays and
``BVHTree.ray_cast`` calls: they hold the interpreter lock, so threads cannot share
them, but processes can. Workers are fresh interpreters (``launch``): a plain Python
that imports the core alone for field work, a background Blender (or a Python that
imports bpy) where tasks need mathutils. Nothing of this process is copied into them,
so they are as safe to start from Blender's window as from ``blender -b``: a forked
copy of a threaded Blender could hang on a lock another thread held at the fork.

A task names a function by module and name (pickle's way) and carries its data: large
arrays travel as shared-memory handles, and arrays made with ``Runtime.shared_array``
are written in place by the workers (``shared``, ``wire``). A run streams each item's
result as it finishes and ends with an ``Outcome``: which process ran each item, which
workers were given up and why (``pool``); the items of a worker that died, stalled or
failed run in this process instead. ``Runtime.journal`` collects the outcomes of the
runs made inside a block, so that work that must tell the user (a build, a frame) can
say that it went on in Blender's process.

The loops make no BLAS calls (``@`` or ``np.dot`` on large arrays): numpy's OpenBLAS
starts threads for them that spin on the other cores for a while after each call, and
those cores are the workers' (or, in-process, took the second core from the render's
tile loop: 19.9 CPU seconds in 10.6 s of wall time, against 6.3 in 6.1 without).
Row-wise products go through ``family.dot3`` (``einsum``), sums of products through
``einsum`` (tests/unit/test_blas_threads.py); workers also start with one BLAS thread.

The process's one ``Runtime`` is made on first use (``runtime``) and ended by
``shutdown`` (the add-on's unregister, or the interpreter's exit). Pure Python and
numpy: no bpy.
"""

import atexit
import os
import threading

from .heap import release_free_memory
from .launch import Launcher, python_launcher
from .outcome import GivenUp, Mapped, Outcome, Reason
from .pool import STALL_SECONDS, Run, Runtime
from .worker import Context

__all__ = [
    "STALL_SECONDS",
    "Context",
    "GivenUp",
    "Launcher",
    "Mapped",
    "Outcome",
    "Reason",
    "Run",
    "Runtime",
    "cores",
    "gave_up",
    "python_launcher",
    "release_free_memory",
    "runtime",
    "shutdown",
    "worker_count",
]

# The process's Runtime, made on first use: the one owner of worker processes.
_OWNER = []
_OWNER_LOCK = threading.Lock()


def runtime():
    """The process's Runtime (made now if there is none)."""
    with _OWNER_LOCK:
        if not _OWNER:
            _OWNER.append(Runtime())
            atexit.register(shutdown)
        return _OWNER[0]


def shutdown():
    """End the process's Runtime, if any: its workers end, its shared-memory names go.
    The next ``runtime`` makes a new one."""
    with _OWNER_LOCK:
        owner = _OWNER.pop() if _OWNER else None
    atexit.unregister(shutdown)
    if owner is not None:
        owner.shutdown()


def gave_up(outcomes):
    """bool, whether any of ``outcomes`` (Outcome) gave a worker up."""
    return any(outcome.given_up for outcome in outcomes)


def cores():
    """int, the cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def worker_count(requested=0):
    """int, processes to use: ``requested`` if positive, else one per core (``cores``);
    1 keeps the work in this process."""
    if requested and requested > 0:
        return int(requested)
    return cores()
