"""Tiles rendered in worker processes: ``BVHTree.ray_cast`` holds the interpreter lock, so
threads cannot share the casting, but processes can: render workers of the worker
runtime (background Blenders, ``processes``), each casting on its own copy of the
frame's tree, built there once per scene.

Workers never call bpy: ``render_rows`` works on the frame's numpy arrays and the tree.
They write their tiles into passes in shared memory (``shared_passes``) and send back
only their cast counts. A tile whose worker died, stalled or failed renders in
Blender's process, and the frame's notices say so.
"""

import copy
from functools import partial

import numpy as np

from ..core.errors import Cancelled
from ..core.runtime import (
    Reason,
    runtime,
    worker_count,  # noqa: F401 (the engine's and the bench's name for it)
)
from . import pipeline
from .processes import blender_launcher, frame_here, portable

# A frame with fewer rays than this renders in-process: sending it out costs more.
MIN_RAYS = 200_000


def _render_tile(frame, passes, rows, context):
    """In a render worker: ``_render_here`` with the frame's tree built there."""
    return _render_here(frame_here(frame, context), passes, rows, context)


def _render_here(frame, passes, rows, stop=None):
    """Render ``rows`` (row0, row1) of ``frame`` into ``passes``; (casts, shadow casts,
    rays) it made (``frame``'s own counts are left as they were)."""
    tile = copy.copy(frame)
    tile.casts = tile.shadow_casts = tile.rays = 0
    for name, data in pipeline.render_rows(tile, rows[0], rows[1], stop).items():
        passes[name][rows[0] : rows[1]] = data
    return tile.casts, tile.shadow_casts, tile.rays


def shared_passes(width, height):
    """dict pass name -> (height, width, channels) float32 array in shared memory
    (``Runtime.shared_array``): the workers write their tiles there, so no image data
    travels through the workers' pipes.

    Raises
    ------
    OSError when shared memory cannot be had.
    """
    kinds = [(name, channels) for name, channels, _i, _k in pipeline.PASSES]
    return {
        name: runtime().shared_array((height, width, channels), np.float32)
        for name, channels in kinds + [pipeline.HIT_PASS]
    }


def render_tiles(frame, tiles, processes, should_stop=None):
    """Yield ``((row0, row1), passes)`` for every tile, in order.

    Parameters
    ----------
    frame : pipeline.Frame. tiles : list of (row0, row1). processes : int; 1 (or a small
        frame) renders in-process. should_stop : callable, asked while waiting on
        workers (and, in-process, every few thousand casts); True stops the render.

    Raises
    ------
    Cancelled when ``should_stop`` says so.
    """
    width, height = frame.size
    passes = None
    if processes > 1 and width * height * frame.samples >= MIN_RAYS:
        try:
            passes = shared_passes(width, height)
        except OSError:  # no shared memory to be had: render here
            passes = None
    if passes is None:
        for row0, row1 in tiles:
            if should_stop is not None and should_stop():
                raise Cancelled()
            yield (row0, row1), pipeline.render_rows(frame, row0, row1, should_stop)
        return
    run = runtime().run(
        partial(_render_tile, portable(frame), passes),
        tiles,
        processes,
        should_stop,
        launcher=blender_launcher(),
        local=partial(_render_here, frame, passes),
    )
    done, told, following = set(), 0, 0
    try:
        for index, counts in run:
            frame.casts += counts[0]
            frame.shadow_casts += counts[1]
            frame.rays += counts[2]
            # what the run had to say (workers given up) is said at once
            given_up = run.given_up
            for g in given_up[told:]:
                frame.diag.warn(given_up_notice(g))
            told = len(given_up)
            done.add(index)
            while following in done:  # in order: the tiles before it are done too
                if should_stop is not None and should_stop():
                    raise Cancelled()
                row0, row1 = tiles[following]
                yield (row0, row1), {name: data[row0:row1] for name, data in passes.items()}
                following += 1
    finally:
        run.close()


def given_up_notice(given_up):
    """The notice for a render worker given up (``runtime.GivenUp``)."""
    if given_up.reason is Reason.STALLED:
        return WORKER_STALLED
    if given_up.reason is Reason.DIED:
        return WORKER_DIED
    return f"{WORKERS_UNUSED} ({given_up.detail})"


WORKER_DIED = "A render worker process died; the remaining tiles rendered in Blender's process"
WORKER_STALLED = (
    "A render worker process stopped making progress; it was ended and its tiles "
    "rendered in Blender's process"
)
WORKERS_UNUSED = (
    "Render worker processes could not be used; the tiles rendered in Blender's process"
)
