"""IMAGE_BLEND: each pixel's ray is its curves R_i blended by eased harmonic mask weights."""

import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..diagnostics import diagnostics_of
from ..field import mask_weights, solve_workers
from ..geometry import DEFAULT_SEGMENTS, Guides, blended_planes, build_guides, curve_planes
from ..quality import check_rig, fold_workers
from ..runtime import runtime, worker_count
from .base import RayField, Settings, guard_warnings, record_seconds


@dataclass
class CurveBlendField(RayField):
    """Rays that blend each pixel's own curves R_i by per-pixel camera weights.

    weights : (N, H, W) float32, summing to one per pixel.

    Kept rays are exact (``exact_kept``): inside camera i's mask the weights are one-hot
    (1 for i, 0 for the others, exactly: ``harmonic.mask_weights`` fixes them there and
    ``eased`` keeps 0 and 1), so the blend ``1 * R_i + 0 * R_j`` is R_i bit for bit.
    """

    weights: np.ndarray = None
    segments: int = DEFAULT_SEGMENTS
    exact_kept: ClassVar[bool] = True

    def near_vertex(self, i):
        """R_i's vertex i * segments is p_i on camera i's near plane (the end of guide
        B_{i-1}: the cubic at t = 1 is its last control point, exactly); the vertices
        after it run straight along v_i (``geometry.curved_rays``)."""
        return i * self.segments

    def rays(self, ix, iy):
        """The blend of each pixel's curves; a pixel whose weights are one-hot (kept by
        camera i) gets R_i alone, the bits the blend ``1 R_i + 0 R_j`` has."""
        ix, iy = np.asarray(ix), np.asarray(iy)
        planes, w = self._planes(ix, iy)
        verts = np.empty((len(ix), planes.shape[1], 3))
        verts[...] = planes.transpose(2, 1, 0)
        # einsum's own loop: a matrix product would wake BLAS's threads, which spin on
        # the cores the fold count's workers need
        n = len(w)
        m = np.einsum("n,np->p", np.arange(1, n + 1, dtype=np.float64), w)
        return self._bundle(ix, iy, verts, np.repeat(m[:, None], verts.shape[1], axis=1))

    def vertex_planes(self, ix, iy):
        """``rays(ix, iy)``' vertices, float32 as the renderer gets them, as float64
        coordinate planes (3, P, K), made without the bundle's other arrays."""
        planes, _w = self._planes(np.asarray(ix), np.asarray(iy))
        out = np.empty((3, planes.shape[2], planes.shape[1]))
        out[...] = planes.astype(np.float32).transpose(0, 2, 1)
        return out

    def _planes(self, ix, iy):
        """Each pixel's ray as coordinate planes (3, K, P) float64, and its weights (N,
        P) float64: the blend of its curves (``geometry.blended_planes``), or, where the
        weights are one-hot (kept by camera i), R_i alone (``geometry.curve_planes``)."""
        cams = self.rig.cameras
        n = len(cams)
        g = build_guides(cams, ix + 0.5, iy + 0.5, beta=self.rig.beta)
        w = self.weights[:, iy, ix].astype(np.float64)
        one = (w == 1.0).any(axis=0) & ((w == 0.0).sum(axis=0) == n - 1)
        planes = np.empty((3, 1 + (n - 1) * self.segments + 1, len(ix)))
        blend = np.flatnonzero(~one)
        if len(blend):
            planes[:, :, blend] = blended_planes(_subset(g, blend), w[:, blend], self.segments)
        owner = w.argmax(axis=0)
        for i in range(n):
            mine = np.flatnonzero(one & (owner == i))
            if len(mine):
                planes[:, :, mine] = curve_planes(_subset(g, mine), self.segments, [i])[0]
        return planes, w


def _start_fold_workers(rig, processes):
    """Start the fold count's workers (``quality.fold_workers``), not waiting for them,
    when the weight solves run in this process (``field.solve_workers``: one solve, a
    rig of two cameras, or a small image), so that their start overlaps the solve on the
    core it leaves idle: the report's fold count then finds them started, or starting
    (it hands them their bands as they come ready). Solves shared among workers start
    them themselves (``harmonic.mask_weights``)."""
    n = len(rig.cameras)
    solves = int(np.asarray(rig.masks).reshape(n, -1).any(axis=1).sum()) - 1
    available = worker_count(processes)
    if solve_workers(rig.size[0] * rig.size[1], solves, available):
        return
    count = fold_workers(rig.size, 1 + (n - 1) * DEFAULT_SEGMENTS + 1, processes)
    if count:
        runtime().warm(count, wait=False)


def _subset(guides, rows):
    """The guides of the pixels ``rows`` ((P',) int) of ``guides``."""
    return Guides(
        guides.points[:, rows],
        guides.directions[:, rows],
        guides.handles_out[:, rows],
        guides.handles_in[:, rows],
        guides.shortened,
    )


def eased(weights):
    """Harmonic mask weights eased at both ends, so that every weight leaves 0 and 1
    with zero slope.

    A harmonic weight leaves its mask with its steepest slope: one pixel out, a small
    camera's ray already takes a few hundredths of the next camera's curve, which
    beyond its near plane runs far from the small camera's own (a camera turned 10
    degrees, 2% of its curve: several of the small camera's pixels). The rays at a
    mask's edge crossed their neighbours inside it (4 to 396 quads at 1920x1080 on the
    bench rigs, none after easing: docs/performance.md). Smoothstep
    ``3 w^2 - 2 w^3`` keeps 0, 1 and the order of the weights, and the sum is restored
    by dividing by it.

    weights : (N, H, W) float array, each pixel's weights summing to one.
    Returns (N, H, W) float32, each pixel's summing to one.
    """
    w = np.asarray(weights, dtype=np.float64)
    s = w * w * (3.0 - 2.0 * w)
    s /= s.sum(axis=0, keepdims=True)
    return s.astype(np.float32)


def prepare_image_blend(rig, settings=None, diag=None, reuse=None):
    """IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights,
    eased at both ends (``eased``).

    Exact where it matters: a pixel inside camera i's mask gets R_i itself, so beyond
    camera i's near plane it is camera i's own pinhole ray. Neighbouring rays can cross
    in the transitions (folds), since nothing ties them together.

    ``reuse`` (``reuse.FrameReuse`` or None): the weights depend on the masks alone, so
    a build whose masks are those the store kept takes its weights as they were (no
    solve), and one whose masks changed solves and keeps them; what it did is in
    ``stats["reuse"]`` (``FrameReuse.record_weights``).

    ``diag`` (core.diagnostics.Diagnostics or None) steers the solve (its cancel check,
    asked before every iteration) and gets its seconds as stage "solve".
    """
    diag = diagnostics_of(diag)
    run = diag.child()
    warnings = check_rig(rig)
    start = time.perf_counter()
    kept = reuse.mask_weights(rig.masks) if reuse is not None else None
    if kept is not None:
        weights, solver = kept
    else:
        processes = (settings or Settings()).processes
        with run.stage("solve"):
            _start_fold_workers(rig, processes)
            solve = mask_weights(rig.masks, processes=processes, should_stop=run.should_stop)
        weights = eased(solve.x)
        solver = {
            "iterations": solve.iterations,
            "residual": solve.residuals[-1] if solve.residuals else 0.0,
            "converged": solve.converged,
        }
        if reuse is not None:
            reuse.keep_weights(rig.masks, weights, solver)
    fld = CurveBlendField(rig=rig, method="IMAGE_BLEND", weights=weights, warnings=warnings)
    record_seconds(fld, {"solve": time.perf_counter() - start})
    fld.solver.update(solver)
    fld.warnings += guard_warnings(rig)
    if reuse is not None:
        fld.stats["reuse"] = reuse.record_weights(kept is not None, fld.seconds)
    diag.merge(run)
    return fld
