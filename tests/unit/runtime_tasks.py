"""Tasks for the worker runtime's tests: module-level (workers find them by name) and
importing nothing but numpy and the core, so that a worker that runs them imports no
bpy."""

import os
import sys
import time

import numpy as np

from multiscale_camera.core.errors import Cancelled


def square(item, context):
    return item * item


def where(item, context):
    """(item, pid, in_worker)."""
    return item, os.getpid(), context.in_worker


def sleep(seconds, item, context):
    """Sleeps without a beat."""
    time.sleep(seconds)
    return item


def nap(item, context):
    """``item`` is (value, seconds): beats for that long, then gives the value."""
    value, seconds = item
    beating(seconds, None, context)
    return value


def beating(seconds, item, context):
    """Takes ``seconds`` and beats every 0.05 s."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(0.05)
        context()
    return item


def until_stopped(item, context):
    """Beats until the run is cancelled (at most a minute); item 0 at once."""
    end = time.monotonic() + (0 if item == 0 else 60)
    while time.monotonic() < end:
        if context():
            raise Cancelled()
        time.sleep(0.01)
    return item


def die(item, context):
    os._exit(3)


def die_in_workers(item, context):
    """Kills its worker; in the parent, the item squared."""
    if context.in_worker:
        os._exit(3)
    return item * item


def hang_in_workers(item, context):
    """Hangs without a beat in a worker; in the parent, the item squared."""
    if context.in_worker:
        time.sleep(60)
    return item * item


def fail_in_workers(item, context):
    if context.in_worker:
        raise MemoryError("no room in the worker")
    return item * item


def fill(out, item, context):
    """Writes rows ``item`` of the shared array ``out``."""
    a, b = item
    out[a:b] = np.arange(a, b)[:, None] * 10 + np.arange(out.shape[1])
    return b - a


def total(array, item, context):
    """The sum of ``array`` (as float64), and whether it lies in shared memory here."""
    base = array
    while isinstance(base, np.ndarray):
        base = base.base
    return float(array.sum(dtype=np.float64)), type(base).__name__


def modules(item, context):
    """The top-level names of the modules the process has imported."""
    return sorted({name.split(".")[0] for name in sys.modules})


class InWorkers:
    """``real`` in the parent; in a worker, first ``how`` ("hang": a minute without a
    beat, "die": the process ends). Pickled by the real function's module and name, so
    that a test can put it where the real one was (monkeypatch) and the worker still
    finds the real one."""

    def __init__(self, real, how, parent=None):
        self.real, self.how = real, how
        self.parent = os.getpid() if parent is None else parent

    def __call__(self, *args, **kwargs):
        if os.getpid() != self.parent:
            if self.how == "die":
                os._exit(3)
            time.sleep(60)
        return self.real(*args, **kwargs)

    def __reduce__(self):
        return _in_workers, (self.real.__module__, self.real.__qualname__, self.how, self.parent)


def _in_workers(module, qualname, how, parent):
    import importlib

    real = importlib.import_module(module)
    for part in qualname.split("."):
        real = getattr(real, part)
    return InWorkers(real, how, parent)
