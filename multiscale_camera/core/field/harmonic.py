"""Harmonic interpolation of masks over the image (the IMAGE_BLEND weights).

Pixels inside camera i's mask have weight 1 for i and 0 for the others; pixels that no
mask owns get the harmonic interpolation (discrete Laplace equation, 4-neighbourhood,
zero-flux image borders). The weights of every pixel sum to one.

Each camera's weight is one Laplace solve on the image seen as a one-voxel-thick grid,
by the same multigrid-preconditioned conjugate gradients as the membership field, but
the last camera's: the weights' sum is harmonic, 1 on every mask, so it is 1 everywhere
(every free pixel is linked to a mask: ``solvers.isolated_voxels``), and the last weight
is 1 minus the others. Of N cameras N - 1 are solved (one of two on a two-camera rig);
the weights differ from N independent solves by the solves' tolerance (tested against a
direct sparse solve). Each solve starts from the same solve on every ``COARSE``-th
pixel in each direction, held on each pixel's COARSE x COARSE block: the full solve
then stops at the same relative residual, in fewer iterations (a start, not an answer).
The solves run on the box around the free pixels alone (``free_box``): outside it every
pixel is owned, and inside it the free pixels' equations are the whole image's.
"""

from functools import partial

import numpy as np

from ..errors import RigError, SolverDidNotConverge
from ..runtime import runtime, worker_count
from .solvers import SolveResult, solve_membership

# Relative residual of each solve: weights then err by ~1e-6, far below what moves a
# ray by a visible amount.
TOLERANCE = 1e-6
# The start of each solve: the solve on every COARSE-th pixel (images at least
# COARSE_MIN_PX pixels on each side), stopped at COARSE_TOLERANCE. At 1920x1080 it took
# PCG from 7 iterations to 5 (the bench's 4x rig) and 6 (the demo), 0.1 to 0.4 CPU s.
COARSE = 4
COARSE_MIN_PX = 8 * COARSE
COARSE_TOLERANCE = 1e-4
# Images of at least this many pixels solve their weights in worker processes, one
# solve each, when there are two or more solves and ``processes`` allows: a solve of
# 1920x1080 takes about 1 s, a worker's start about 0.4 s (and the fold count that
# follows finds the workers started).
SHARED_MIN_PIXELS = 1 << 20


def solve_workers(pixels, solves, available):
    """int, the worker processes that share ``solves`` weight solves of an image of
    ``pixels`` pixels with ``available`` processes (``runtime.worker_count``'s answer):
    one a solve, when there are two or more and the image has ``SHARED_MIN_PIXELS``;
    0 when they run in this process, one after the other."""
    n = min(int(available), int(solves))
    return n if n >= 2 and int(pixels) >= SHARED_MIN_PIXELS else 0


def mask_weights(masks, tol=TOLERANCE, processes=1, should_stop=None):
    """Per-pixel camera weights: one-hot in the masks, harmonic in between.

    Parameters
    ----------
    masks : (N, H, W) bool array, at most one True per pixel, at least one True overall.
    tol : float, relative residual of each solve.
    processes : int, ``runtime.worker_count``'s request (0: one per core, 1: every solve
        in this process). With two or more solves on an image of ``SHARED_MIN_PIXELS``
        or more, they run at once in worker processes; each is the same function of the
        same arrays as here, so the weights are the same bits either way (a solve whose
        worker is given up runs here).
    should_stop : callable () -> bool or None: here, asked before each solve, its coarse
        start and each of its iterations (``solve_membership``: at most about 0.5 s
        apart at 1920x1080); shared, it cancels the workers' solves.

    Returns
    -------
    SolveResult whose ``x`` is (N, H, W) float32, each pixel's weights summing to one;
    ``iterations`` and ``residuals`` are those of the slowest solve.

    Raises
    ------
    RigError if every mask is empty; SolverDidNotConverge if a solve stalls; Cancelled
    when ``should_stop`` says so.
    """
    masks = np.asarray(masks, dtype=bool)
    n, h, w = masks.shape
    owned = masks.any(axis=0)
    if not owned.any():
        raise RigError("Every mask is empty: paint white where each camera's view should be kept")
    # a pixel a mask owns has its weights already: one-hot (the solves' constraints)
    x = masks.astype(np.float64)
    slowest = SolveResult(None, True, 0, ())
    kept = [i for i in range(n) if masks[i].any()]
    solves = kept[:-1]
    box = free_box(owned)
    if box is None:  # no pixel to solve for
        solves = []
    else:
        masks, owned = np.ascontiguousarray(masks[:, box[0], box[1]]), owned[box]
    workers = solve_workers(h * w, len(solves), worker_count(processes))
    if not workers:
        results = []
        for i in solves:
            results.append(_solve_weight(masks, owned, tol, i, should_stop=should_stop))
    else:
        task = partial(_solve_weight, masks, owned, tol)
        results = runtime().map(task, solves, workers, should_stop).results
    for i, result in zip(solves, results):
        if not result.converged:
            raise SolverDidNotConverge(
                f"Mask weights did not converge: relative residual {result.residuals[-1]:.2e} "
                f"after {result.iterations} iterations"
            )
        x[i][box] = result.x[..., 0]
        if result.iterations >= slowest.iterations:
            slowest = result
    # the sum of all weights is 1 exactly (module docstring): the last is what is left
    x[kept[-1]] = 1.0 - x[kept[:-1]].sum(axis=0)
    x = np.clip(x, 0.0, 1.0)
    x /= np.maximum(x.sum(axis=0, keepdims=True), 1e-12)
    return SolveResult(x.astype(np.float32), True, slowest.iterations, slowest.residuals)


def free_box(owned):
    """The pixels the weight solves need: (rows, columns) slices of the box around the
    pixels no mask owns, one pixel wider on each side where the image goes on; None
    when every pixel is owned. ``owned``: (H, W) bool.

    Outside the box every pixel is owned, so its weights are the masks'; inside, every
    free pixel has its four neighbours in the box (the ring around the free pixels is
    owned, fixed), so the Laplace equations of the free pixels, and their solution,
    are those of the whole image. Camera 1 keeps the frame's edges on most rigs: the
    box then leaves out what lies between its mask's inner edge and the frame (the 6x
    rig: 84% of 1920x1080 solved, the demo 59%)."""
    free = ~np.asarray(owned, dtype=bool)
    rows, cols = np.flatnonzero(free.any(axis=1)), np.flatnonzero(free.any(axis=0))
    if not len(rows):
        return None
    h, w = free.shape
    return (
        slice(max(int(rows[0]) - 1, 0), min(int(rows[-1]) + 2, h)),
        slice(max(int(cols[0]) - 1, 0), min(int(cols[-1]) + 2, w)),
    )


def _solve_weight(masks, owned, tol, i, context=None, should_stop=None):
    """The SolveResult of camera ``i``'s weight (``mask_weights``), here or in a worker
    (``context``: the worker's beat, unused: one solve is one item; the pool cancels
    it). ``should_stop``: the cancel check of a solve run here (``solve_membership``)."""
    return solve_membership(
        masks[i][..., None].astype(np.float32),
        owned[..., None],
        tol=tol,
        x0=coarse_start(masks[i], owned, should_stop),
        should_stop=should_stop,
    )


def coarse_start(mask, owned, should_stop=None):
    """A start for the weight of ``mask`` ((H, W) bool) among the ``owned`` pixels: the
    solve on every COARSE-th pixel, each value held on its COARSE x COARSE block;
    (H, W, 1) float32, or None for an image under COARSE_MIN_PX on a side.
    ``should_stop``: the solve's cancel check (``solve_membership``)."""
    h, w = mask.shape
    if min(h, w) < COARSE_MIN_PX:
        return None
    coarse = solve_membership(
        mask[::COARSE, ::COARSE, None].astype(np.float32),
        owned[::COARSE, ::COARSE, None],
        tol=COARSE_TOLERANCE,
        should_stop=should_stop,
    )
    x0 = np.repeat(np.repeat(coarse.x[..., 0], COARSE, axis=0), COARSE, axis=1)
    return x0[:h, :w, None]
