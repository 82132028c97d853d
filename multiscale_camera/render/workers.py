"""Tiles rendered in worker processes: ``BVHTree.ray_cast`` holds the interpreter lock, so
threads cannot share the casting, but forked processes can, each casting on its own copy
of the frame's tree (fork copies the parent's memory, tree included, page by page as it
is written).

Only ``fork`` is used: a spawned worker would start a fresh interpreter and import the
package, and with it ``bpy``, which must not happen inside Blender. Where fork is not
available (Windows, or a Python that forbids it) the tiles render in-process. Workers
never call bpy: ``render_rows`` works on the frame's numpy arrays and the tree. They
write their tiles into passes in shared memory (``shared_passes``) and send back only
the rows and their cast counts.
"""

from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from ..core.errors import Cancelled
from ..core.parallel import (
    STALL_SECONDS,
    Stalled,
    fork_context,
    shared_array,
    stop,
    wait_for,
    worker_count,  # noqa: F401 (the engine's and the bench's name for it)
    worker_init,
)
from . import pipeline

# A frame with fewer rays than this renders in-process: starting workers costs more.
MIN_RAYS = 200_000

# The frame the forked workers render, and the passes they write (set in the parent
# just before forking).
_FRAME = None
_SHARED = None


def _render_tile(rows):
    """In a worker: render ``rows`` into the shared passes; (rows, counts) go back."""
    frame = _FRAME
    before = frame.casts, frame.shadow_casts, frame.rays
    passes = pipeline.render_rows(frame, rows[0], rows[1])
    for name, data in passes.items():
        _SHARED[name][rows[0] : rows[1]] = data
    counts = (frame.casts - before[0], frame.shadow_casts - before[1], frame.rays - before[2])
    return rows, counts


def shared_passes(width, height):
    """dict pass name -> (height, width, channels) float32 array in memory shared with
    the processes forked after it (``parallel.shared_array``): the workers write their
    tiles there, so no image data is pickled through the pool's pipes."""
    return {
        name: shared_array((height, width, channels), np.float32)
        for name, channels, _i, _k in pipeline.PASSES
    }


def render_tiles(frame, tiles, processes, should_stop=None):
    """Yield ``((row0, row1), passes)`` for every tile, in order.

    Parameters
    ----------
    frame : pipeline.Frame. tiles : list of (row0, row1). processes : int; 1 (or no fork,
        or a small frame) renders in-process. should_stop : callable, consulted between
        tiles (and, in-process, every few thousand casts); True stops the workers.

    Raises
    ------
    Cancelled when ``should_stop`` says so.
    """
    global _FRAME, _SHARED
    width, height = frame.size
    ctx = fork_context()
    pool = shared = None
    if processes > 1 and ctx is not None and width * height * frame.samples >= MIN_RAYS:
        _FRAME = frame
        try:
            _SHARED = shared = shared_passes(width, height)
            pool = ProcessPoolExecutor(processes, mp_context=ctx, initializer=worker_init)
        except OSError:  # no memory or processes to be had (limits, sandbox): render here
            _FRAME = _SHARED = None
    done = 0
    if pool is not None:
        try:
            futures = [pool.submit(_render_tile, rows) for rows in tiles]
            for future in futures:
                # asked while waiting too, so that Esc ends a tile loop whose workers are
                # slow; workers that do no tile for STALL_SECONDS are taken for stuck (a
                # forked copy of a threaded host can hang on a lock)
                rows, counts = wait_for(future, should_stop, STALL_SECONDS)
                frame.casts += counts[0]
                frame.shadow_casts += counts[1]
                frame.rays += counts[2]
                done += 1
                yield rows, {name: data[rows[0] : rows[1]] for name, data in shared.items()}
        except BrokenProcessPool:
            # a worker died (killed, or a forked copy of a threaded host that could not
            # run): the tiles it left render here, rather than waiting on it forever
            frame.diag.warn(WORKER_DIED)
        except Stalled:
            frame.diag.warn(WORKER_STALLED)
        finally:
            stop(pool)
            _FRAME = _SHARED = None
    for row0, row1 in tiles[done:]:
        if should_stop is not None and should_stop():
            raise Cancelled()
        yield (row0, row1), pipeline.render_rows(frame, row0, row1, should_stop)


WORKER_DIED = "A render worker process died; the remaining tiles rendered in Blender's process"
WORKER_STALLED = (
    "The render worker processes stopped making progress (a forked copy of Blender can "
    "hang on a lock another thread held); the remaining tiles rendered in Blender's "
    "process. Render > Performance > Threads: Fixed at 1 renders there from the start"
)
