"""Work spread over forked worker processes.

The field's trace and the renderer's casts are Python loops over numpy arrays and
``BVHTree.ray_cast`` calls: they hold the interpreter lock, so threads cannot share them,
but forked processes can, each working on its own copy of the parent's memory (page by
page as it is written: the grids, the tree and the rig are not copied up front).

Only ``fork`` is used: a spawned worker would start a fresh interpreter and import the
package, and with it ``bpy``, which must not happen inside Blender. Where fork is not
available (Windows, or a Python that forbids it) the work runs in-process. Workers never
call bpy.

The loops make no BLAS calls (``@`` or ``np.dot`` on large arrays): numpy's OpenBLAS
starts threads for them that spin on the other cores for a while after each call, and
those cores are the workers' (or, in-process, took the second core from the render's
tile loop: 19.9 CPU seconds in 10.6 s of wall time, against 6.3 in 6.1 without).
Row-wise products go through ``family.dot3`` (``einsum``), sums of products through
``einsum`` (tests/unit/test_blas_threads.py).
"""

import mmap
import multiprocessing
import os
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from .errors import Cancelled

# What forked workers run: the callable is set in the parent just before forking, so
# the children find it (and everything it holds) in their copy of the parent's memory;
# and the counter in shared memory that they count up as they make progress (``beat``).
_TASK = None
_BEATS = None
# How often the parent asks ``should_stop`` while it waits for workers, seconds.
POLL_SECONDS = 0.1
# Seconds with no item done after which workers on short items (a tile, a part of a
# simplification: well under a second each) are taken for stuck.
STALL_SECONDS = 20.0
# How many times ``forked_map`` has given up its workers in this process (one died, or
# all stalled): work that must tell the user compares ``given_up()`` before and after.
_GIVEN_UP = [0]


def given_up():
    """int, how many times ``forked_map`` has given up its workers in this process (the
    caller then did the work in-process: the same result, only slower)."""
    return _GIVEN_UP[0]


def fork_context():
    """The ``fork`` multiprocessing context, or None where it is unavailable."""
    if sys.platform == "win32":
        return None
    try:
        return multiprocessing.get_context("fork")
    except ValueError:
        return None


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


def worker_init():
    """A worker ends when its pool terminates it, whatever handlers the host installed,
    and leaves Ctrl+C to the parent."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def stop(pool):
    """Shut a pool down without waiting for work still queued; end its workers."""
    processes = list(getattr(pool, "_processes", {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in processes:
        if proc.is_alive():
            proc.terminate()
    for proc in processes:
        proc.join(timeout=5)


def shared_array(shape, dtype):
    """A zeroed array in memory shared with the processes forked after it (an anonymous
    shared mapping), so that forked workers can write their part of a result in place
    instead of pickling it back.

    Parameters
    ----------
    shape : tuple of int. dtype : numpy dtype.

    Returns
    -------
    ndarray of ``shape`` and ``dtype``; its buffer lives as long as the array does.
    """
    dtype = np.dtype(dtype)
    count = int(np.prod(shape, dtype=np.int64))
    buffer = mmap.mmap(-1, max(count * dtype.itemsize, 1))
    return np.frombuffer(buffer, dtype, count).reshape(shape)


class Stalled(Exception):
    """Forked workers have done nothing for longer than they may."""


def wait_for(future, should_stop=None, stall_seconds=None, beats=None):
    """The result of a pool's ``future``, asking ``should_stop`` every POLL_SECONDS.

    Parameters
    ----------
    beats : (1,) int64 shared array the workers count up (``beat``), or None: while it
        changes, the workers count as busy however long the item takes.

    Raises
    ------
    Cancelled when ``should_stop`` says so; Stalled when ``stall_seconds`` (None: no
    limit) pass first with no beat. A forked copy of a process that runs other threads
    can hang for ever on a lock another thread held at the fork (Blender's memory
    allocator's, seen in Blender 5.2's window), without dying: only the time tells.
    """
    start = time.monotonic()
    seen = None if beats is None else int(beats[0])
    while True:
        if should_stop is not None and should_stop():
            raise Cancelled()
        try:
            return future.result(timeout=POLL_SECONDS)
        except TimeoutError:
            if beats is not None and int(beats[0]) != seen:
                seen, start = int(beats[0]), time.monotonic()
            if stall_seconds is not None and time.monotonic() - start > stall_seconds:
                raise Stalled() from None


def beat():
    """In a worker of ``forked_map``: tell the parent that it is making progress. Returns
    False, so that it can be passed where a ``should_stop`` is polled."""
    if _BEATS is not None:
        _BEATS[0] += 1
    return False


def _run(item):
    return _TASK(item)


def forked_map(task, items, processes, should_stop=None, stall_seconds=None):
    """``[task(item) for item in items]``, the items shared among forked workers.

    Parameters
    ----------
    task : callable, item -> picklable result. It runs in the workers on their copy of
        the parent's memory; what it changes there does not come back.
    items : sequence of picklable items. processes : int, workers (at most one an item);
        1, or no fork, runs in-process.
    should_stop : callable () -> bool, asked while waiting: True ends the workers.
    stall_seconds : float or None: when no item has been done, and no worker has called
        ``beat``, for this long, the workers are taken for stuck and ended; None waits
        as long as it takes.

    Returns
    -------
    list of results, in the order of ``items``; or None when the work could not be
    shared (no fork, no processes to be had, a worker died or stalled): the caller then
    runs it in-process.

    Raises
    ------
    Cancelled when ``should_stop`` says so.
    """
    global _TASK, _BEATS
    processes = min(int(processes), len(items))
    ctx = fork_context()
    if processes < 2 or ctx is None:
        return None
    _TASK = task
    _BEATS = beats = shared_array((1,), np.int64)
    try:
        pool = ProcessPoolExecutor(processes, mp_context=ctx, initializer=worker_init)
    except OSError:  # no processes to be had (limits, sandbox)
        _TASK = _BEATS = None
        return None
    try:
        futures = [pool.submit(_run, item) for item in items]
        results = []
        for future in futures:
            results.append(wait_for(future, should_stop, stall_seconds, beats))
        return results
    except (BrokenProcessPool, Stalled):
        # a worker died (killed, or a forked copy of a threaded host that could not
        # run) or hangs: the caller does the work in-process rather than wait for ever
        _GIVEN_UP[0] += 1
        return None
    finally:
        stop(pool)
        _TASK = _BEATS = None
