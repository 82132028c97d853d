"""Ray-generation methods.

Each method is one function ``prepare_<method>(rig, settings, should_stop=None)`` that
builds a ``RayField`` once; the field then hands out ray bundles for any set of pixels,
so the renderer works tile by tile with bounded memory.

- IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights.
- LINEAR: the paper's strawman, a transition pixel's ray interpolates linearly between
  the rays of the nearest preserved pixels of two cameras.
- VECTOR_FIELD: eq. 3, the tangents of preserved rays smoothed directly into a field.
- SCALAR_FIELD: eq. 4 to 6, a smoothed membership blends exact tangent fields.
"""

import abc
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from .errors import Cancelled, RigError, SolverDidNotConverge
from .field import (
    CELLS_ACROSS_NEAR_PER_PX,
    MIN_CELLS_ACROSS_NEAR,
    FieldTracer,
    NestedDomain,
    ScaleField,
    StopReason,
    Traced,
    choose_grid,
    choose_levels,
    fill_membership,
    mask_weights,
    merge,
    near_plane_width,
    run_on,
    solve_levels,
    solve_membership,
    step_cells,
)
from .geometry import DEFAULT_SEGMENTS, Family, RayBundle, build_guides, curved_rays
from .parallel import worker_count
from .quality import check_rig, conflict_messages, guard_messages


@dataclass(frozen=True)
class Settings:
    """What a build is asked for.

    accuracy_px : float, target preserved error in pixels.
    max_voxels : int, the grid's voxel budget.
    cubic : bool, monotone cubic blending weights (SCALAR_FIELD).
    nested : bool or None, SCALAR_FIELD on nested grids that refine toward the smaller
        cameras (``nested``); False: one uniform grid, as the paper; None (default):
        nested only where one uniform grid within the budget cannot have the cells the
        accuracy target asks for (scale ratios beyond about 10x).
    processes : int, worker processes that share the trace and the nested levels'
        fills (0: one per core; 1: in Blender's process). Not part of the field's
        identity: every count traces the same rays (to about float32 rounding).
    """

    accuracy_px: float = 0.5
    max_voxels: int = 160**3
    cubic: bool = False
    nested: bool = None
    processes: int = field(default=0, repr=False, compare=False)


# Quality presets: accuracy target in pixels and voxel budget (about 0.1, 0.4 and
# 1.3 GB of build memory), DESIGN.md's `quality` enum.
QUALITY = {
    "PREVIEW": Settings(2.0, 96**3),
    "STANDARD": Settings(0.5, 160**3),
    "HIGH": Settings(0.25, 256**3),
}


def settings_for(quality, accuracy_px=0.5):
    """The Settings of a quality preset; CUSTOM uses ``accuracy_px`` and a budget that
    grows as the target tightens (the STANDARD budget at 0.5 px)."""
    if quality in QUALITY:
        return QUALITY[quality]
    budget = int(np.clip(160**3 * (0.5 / accuracy_px) ** 1.5, 64**3, 320**3))
    return Settings(float(accuracy_px), budget)


@dataclass
class RayField(abc.ABC):
    """A prepared ray generator (base of every method's field).

    Attributes
    ----------
    rig : Rig. method : str, the method's enum name.
    seconds : dict stage -> float seconds ("fill", "solve", "tangents", "trace").
    solver : dict with "iterations", "residual", "converged".
    warnings : list of str, for the report and the user.
    grids : list of [nx, ny, nz].
    stats : dict of counts ("conflicts", "stalled", ...).
    notices : list of str, what the scene adapters adjusted (resampled masks, ...).
    """

    rig: object
    method: str
    seconds: dict = field(default_factory=dict)
    solver: dict = field(
        default_factory=lambda: {"iterations": 0, "residual": 0.0, "converged": True}
    )
    warnings: list = field(default_factory=list)
    grids: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    notices: list = field(default_factory=list)

    @abc.abstractmethod
    def rays(self, ix, iy):
        """Rays for pixels ``(ix, iy)`` ((P,) int arrays, row 0 at the top): a RayBundle."""

    def exit_index(self, ix, iy):
        """(P,) int: the vertex where each pixel's ray leaves the modelled volume (the
        end of its bending stretch); the last vertex unless a method knows better."""
        return None

    def _bundle(self, ix, iy, verts, membership):
        cams = self.rig.cameras
        p1 = cams[0].near_points(cams[0].directions(ix + 0.5, iy + 0.5))
        return RayBundle(
            vertices=verts.astype(np.float32, copy=False),
            membership=membership.astype(np.float32, copy=False),
            pixels=np.stack([ix, iy], axis=1).astype(np.int32),
            start_depth=np.linalg.norm(p1 - cams[0].eye, axis=-1).astype(np.float32),
            reach=np.full(len(ix), max(c.clip_end for c in cams), dtype=np.float32),
        )


@dataclass
class CurveBlendField(RayField):
    """Rays that blend each pixel's own curves R_i by per-pixel camera weights.

    weights : (N, H, W) float32, summing to one per pixel.
    """

    weights: np.ndarray = None
    segments: int = DEFAULT_SEGMENTS

    def rays(self, ix, iy):
        ix, iy = np.asarray(ix), np.asarray(iy)
        cams = self.rig.cameras
        g = build_guides(cams, ix + 0.5, iy + 0.5, beta=self.rig.beta)
        curves = curved_rays(g, self.segments)
        w = self.weights[:, iy, ix].astype(np.float64)
        verts = np.einsum("np,npkc->pkc", w, curves)
        m = np.arange(1, len(cams) + 1, dtype=np.float64) @ w
        return self._bundle(ix, iy, verts, np.repeat(m[:, None], verts.shape[1], axis=1))


def prepare_image_blend(rig, settings=None, should_stop=None):
    """IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights.

    Exact where it matters: a pixel inside camera i's mask gets R_i itself, so beyond
    camera i's near plane it is camera i's own pinhole ray. Neighbouring rays can cross
    in the transitions (folds), since nothing ties them together.
    """
    warnings = check_rig(rig)
    t0 = time.perf_counter()
    solve = mask_weights(rig.masks)
    fld = CurveBlendField(rig=rig, method="IMAGE_BLEND", weights=solve.x, warnings=warnings)
    fld.seconds.update(fill=0.0, solve=time.perf_counter() - t0, tangents=0.0, trace=0.0)
    fld.solver.update(
        iterations=solve.iterations,
        residual=solve.residuals[-1] if solve.residuals else 0.0,
        converged=solve.converged,
    )
    fld.warnings += guard_warnings(rig)
    return fld


def guard_warnings(rig):
    """Warnings for camera pairs whose guides the guard shortened (see ``guides``)."""
    return guard_messages(rig)


@dataclass
class TracedField(RayField):
    """Rays traced on an adaptive pixel lattice; every other pixel's ray is interpolated
    bilinearly, vertex by vertex (vertex k of every ray lies at the same arc length),
    from the four corners of the lattice cell (a quadtree leaf) that holds it.

    traced : field.Traced, all traced rays. index : (H, W) int32, the traced ray of a
    pixel or -1. leaves : (L, 4) int32 cells (x0, y0, x1, y1) in pixels, corners
    included. leaf_of : (H, W) int32, the leaf holding each pixel. grid : Grid (with
    nested grids, the coarsest). membership : (nx, ny, nz) float32 on ``grid``.
    domain : nested.NestedDomain or None, the membership of every level.
    step : float, world units, or a callable (P, 3) points -> (P,) lengths: the trace's
    step (``rk4_streamlines``), so rays can be traced again as the field traced them.
    """

    traced: object = None
    index: np.ndarray = None
    leaves: np.ndarray = None
    leaf_of: np.ndarray = None
    grid: object = None
    membership: np.ndarray = None
    domain: object = None
    step: object = None

    def tracer(self, cubic=False):
        """A FieldTracer of this field's membership (for tracing further rays)."""
        return FieldTracer(self.rig, self.grid, self.membership, cubic=cubic, domain=self.domain)

    def _corners(self, ix, iy):
        x0, y0, x1, y1 = self.leaves[self.leaf_of[iy, ix]].T
        fx = np.where(x1 > x0, (ix - x0) / np.maximum(x1 - x0, 1), 0.0).astype(np.float32)[:, None]
        fy = np.where(y1 > y0, (iy - y0) / np.maximum(y1 - y0, 1), 0.0).astype(np.float32)[:, None]
        idx = self.index
        return (
            (idx[y0, x0], (1 - fy) * (1 - fx)),
            (idx[y0, x1], (1 - fy) * fx),
            (idx[y1, x0], fy * (1 - fx)),
            (idx[y1, x1], fy * fx),
        )

    def rays(self, ix, iy):
        ix, iy = np.asarray(ix), np.asarray(iy)
        corners = self._corners(ix, iy)
        # past the last traced vertex every ray runs straight: one more vertex holds it
        k = min(
            self.traced.vertices.shape[1],
            max(int(self.traced.counts[r].max()) for r, _w in corners) + 1,
        )
        k = max(k, 2)
        verts = mem = None
        for row, w in corners:  # in place: a (P, K, 3) temporary less per corner
            v = self.traced.vertices[row, :k]
            v *= w[:, :, None]
            m = self.traced.membership[row, :k]
            m *= w
            if verts is None:
                verts, mem = v, m
            else:
                verts += v
                mem += m
        return self._bundle(ix, iy, verts, mem)

    def exit_index(self, ix, iy):
        """(P,) int: for each pixel, the vertex where its ray leaves the grid (the
        smallest traced count among the rays it is interpolated from)."""
        counts = self.traced.counts
        rows = [row for row, _w in self._corners(np.asarray(ix), np.asarray(iy))]
        return np.minimum.reduce([counts[r] for r in rows]) - 1


def _lattice_axis(n, stride):
    """Lattice pixel indices 0, stride, ..., always including the last pixel n - 1."""
    return np.unique(np.append(np.arange(0, n, stride), n - 1))


def _across(d, t):
    """Length of the part of vectors ``d`` (..., 3) across unit directions ``t``: the
    arc-length layout lets neighbouring vertices slide along their rays, which moves
    nothing in the image."""
    return np.linalg.norm(d - (d * t).sum(-1, keepdims=True) * t, axis=-1)


# Lattice stride bounds in pixels: one traced ray per stride x stride block, the others
# interpolated (rays bend on the scale of a cell, many pixels wide).
MAX_STRIDE = 16


# Ray vertices weighed together by ``_AdaptiveLattice.deviation`` (about 24 bytes each
# in each of its ten or so temporaries).
DEVIATION_BLOCK_VERTICES = 1 << 20


# A cell's interpolation error over its parent's midpoint deviation: 1/4 for smooth rays,
# 1/2 where N's trilinear kinks make them only once differentiable (the bound used).
CHILD_ERROR_RATIO = 2.0


class _AdaptiveLattice:
    """Traces rays on a pixel lattice and refines it where interpolation would err.

    A cell's interpolation error is estimated from the second differences of its
    rays (a child cell's bilinear interpolation errs by at most about half its parent's
    midpoint deviation), in pixels of the multiscale image at each vertex (the spacing
    of neighbouring rays there), both measured across the rays; cells above the
    tolerance are split in four and their midpoints traced, down to single pixels.
    """

    def __init__(self, tracer, rig, step, max_steps, tol_px, should_stop):
        self.tracer, self.rig, self.step = tracer, rig, step
        self.max_steps, self.tol, self.should_stop = max_steps, tol_px, should_stop
        w, h = rig.size
        self.index = np.full((h, w), -1, dtype=np.int32)
        self.parts, self.order, self.count = [], [], 0

    def trace(self, px, py):
        """Trace the pixels not traced yet (duplicates allowed)."""
        key = np.unique(np.asarray(py, dtype=np.int64) * self.index.shape[1] + np.asarray(px))
        py, px = np.divmod(key, self.index.shape[1])
        new = self.index[py, px] < 0
        px, py = px[new], py[new]
        if len(px) == 0:
            return
        if self.should_stop is not None and self.should_stop():
            raise Cancelled()
        self.parts.append(
            self.tracer.trace_pixels(px, py, self.step, self.max_steps, self.should_stop)
        )
        self.order.append(np.arange(self.count, self.count + len(px)))
        self.index[py, px] = np.arange(self.count, self.count + len(px))
        self.count += len(px)

    def rows(self, ids):
        """Vertices (n, K, 3) float32 and counts (n,) of traced rays ``ids`` (n,),
        K the most any part has (shorter rays run straight on, as ``merge`` lays
        them out). The parts stay apart until ``run`` ends: merging after every round
        would hold two copies of every ray."""
        k = max(p.vertices.shape[1] for p in self.parts)
        ids = np.asarray(ids)
        verts = np.empty((len(ids), k, 3), dtype=np.float32)
        counts = np.empty(len(ids), dtype=np.int32)
        starts = np.array([o[0] for o in self.order])
        part = np.searchsorted(starts, ids, side="right") - 1
        for j, p in enumerate(self.parts):
            sel = np.flatnonzero(part == j)
            if not len(sel):
                continue
            r = ids[sel] - starts[j]
            sub = Traced(p.vertices[r], p.membership[r], p.counts[r], p.reason[r], p.step)
            verts[sel] = run_on(sub, k).vertices
            counts[sel] = p.counts[r]
        return verts, counts

    def deviation(self, mid, a, b, pixels):
        """How far ray(mid) strays from the mean of rays a and b, in pixels.

        Max over the vertices inside the grid of |ray(mid) - (ray(a) + ray(b)) / 2|
        across the ray, over the spacing of the neighbouring rays there (|ray(b) -
        ray(a)| / pixels): pixels of the multiscale image. Beyond the grid the rays run
        straight and may cross far off, where that spacing vanishes; that stretch is not
        weighed. (P,) arrays of flat pixel keys and pixel distances."""
        ia, ib, im = (self.index.ravel()[k] for k in (a, b, mid))
        pixels = np.asarray(pixels)
        out = np.zeros(len(ia))
        k = max(p.vertices.shape[1] for p in self.parts)
        # in blocks: three float64 copies of every ray's vertices would take gigabytes
        block = max(1, DEVIATION_BLOCK_VERTICES // max(k, 1))
        for s in range(0, len(ia), block):
            sl = slice(s, s + block)
            (va, ca), (vb, cb), (vm, cm) = (self.rows(i[sl]) for i in (ia, ib, im))
            va, vb, vm = (x.astype(np.float64) for x in (va, vb, vm))
            t = np.diff(vm, axis=1, append=2 * vm[:, -1:] - vm[:, -2:-1])
            t /= np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-30)
            d = _across(vm - 0.5 * (va + vb), t)
            spacing = _across(vb - va, t) / np.maximum(pixels[sl], 1)[:, None]
            traced = np.arange(k)[None, :] < np.minimum.reduce([ca, cb, cm])[:, None]
            out[sl] = np.where(traced, d / np.maximum(spacing, 1e-12), 0.0).max(axis=1)
        return out

    def _lattice_roughness(self, xs, ys):
        """(cells,) float: for each base cell, the largest deviation of a corner ray from
        the mean of its two lattice neighbours (a span of two cells), row-major cells."""
        w = self.index.shape[1]
        gy, gx = np.meshgrid(ys, xs, indexing="ij")
        key = gy * w + gx
        dev = np.zeros(key.shape)
        if len(xs) > 2:
            d = self.deviation(
                key[:, 1:-1].ravel(),
                key[:, :-2].ravel(),
                key[:, 2:].ravel(),
                (gx[:, 2:] - gx[:, :-2]).ravel(),
            )
            dev[:, 1:-1] = np.maximum(dev[:, 1:-1], d.reshape(len(ys), -1))
        if len(ys) > 2:
            d = self.deviation(
                key[1:-1].ravel(), key[:-2].ravel(), key[2:].ravel(), (gy[2:] - gy[:-2]).ravel()
            )
            dev[1:-1] = np.maximum(dev[1:-1], d.reshape(-1, len(xs)))
        corners = np.maximum.reduce([dev[:-1, :-1], dev[:-1, 1:], dev[1:, :-1], dev[1:, 1:]])
        return corners.ravel()

    def run(self, stride):
        w, h = self.rig.size
        xs, ys = _lattice_axis(w, stride), _lattice_axis(h, stride)
        gy, gx = np.meshgrid(ys, xs, indexing="ij")
        self.trace(gx.ravel(), gy.ravel())
        x0, y0 = np.meshgrid(xs[:-1], ys[:-1]) if len(xs) > 1 and len(ys) > 1 else (gx, gy)
        x1, y1 = np.meshgrid(xs[1:], ys[1:]) if len(xs) > 1 and len(ys) > 1 else (gx, gy)
        cells = np.stack([x0.ravel(), y0.ravel(), x1.ravel(), y1.ravel()], axis=1)
        # the base lattice's own second differences estimate its cells' error, so only
        # the cells that need it get their midpoints traced
        rough = self._lattice_roughness(xs, ys)
        flagged = rough / CHILD_ERROR_RATIO > self.tol
        leaves = [cells[~flagged]]
        cells = cells[flagged]
        while len(cells):
            x0, y0, x1, y1 = cells.T
            xm, ym = (x0 + x1) // 2, (y0 + y1) // 2
            split = (x1 - x0 > 1) | (y1 - y0 > 1)
            leaves.append(cells[~split])
            cells, x0, y0, x1, y1, xm, ym = (a[split] for a in (cells, x0, y0, x1, y1, xm, ym))
            if not len(cells):
                break
            self.trace(np.concatenate([xm, xm, x0, x1, xm]), np.concatenate([y0, y1, ym, ym, ym]))
            key = lambda x, y: y * w + x  # noqa: E731
            err = np.maximum.reduce(
                [
                    self.deviation(key(xm, y0), key(x0, y0), key(x1, y0), x1 - x0),
                    self.deviation(key(xm, y1), key(x0, y1), key(x1, y1), x1 - x0),
                    self.deviation(key(x0, ym), key(x0, y0), key(x0, y1), y1 - y0),
                    self.deviation(key(x1, ym), key(x1, y0), key(x1, y1), y1 - y0),
                ]
            )
            # bilinear error falls as the cell size squared where the rays are smooth, but
            # only linearly across the kinks of N at voxel faces: assume the slower rate
            fine = err / CHILD_ERROR_RATIO <= self.tol
            children = np.concatenate(
                [
                    np.stack([x0, y0, xm, ym], 1),
                    np.stack([xm, y0, x1, ym], 1),
                    np.stack([x0, ym, xm, y1], 1),
                    np.stack([xm, ym, x1, y1], 1),
                ]
            )
            keep = np.tile(fine, 4)
            leaves.append(children[keep])
            cells = children[~keep]
        leaves = np.concatenate(leaves).astype(np.int32)
        leaf_of = np.zeros((h, w), dtype=np.int32)
        for n, (a, b, c, d) in enumerate(leaves.tolist()):
            leaf_of[b : d + 1, a : c + 1] = n
        parts, order = self.parts, self.order
        self.parts, self.order = [], []
        return merge(parts, order, self.count), self.index, leaves, leaf_of


def lattice_stride(rig, grid):
    """Pixels between traced rays: half the smallest camera's pixels per cell, so every
    cell the rays cross is seen by two lattice rays, clamped to 1 .. MAX_STRIDE."""
    cams = rig.cameras
    w = rig.size[0]
    px = min(near_plane_width(c) / w for c in cams)
    return int(np.clip(grid.cell / px / 2, 1, MAX_STRIDE))


def field_grid(fld, settings):
    """The grid of a field method (``choose_grid``), with a warning on ``fld`` when the
    voxel budget caps the cell the accuracy target asks for."""
    choice = choose_grid(fld.rig, settings.accuracy_px, settings.max_voxels)
    if choice.capped:
        fld.warnings.append(capped_message(settings, choice.wanted_cell, choice.grid.cell))
    return choice.grid


def capped_message(settings, wanted, cell):
    """The warning for a voxel budget that forced cells coarser than the target asks."""
    return (
        f"The accuracy target of {settings.accuracy_px:g} px wants {wanted:.3g}-unit cells; "
        f"the voxel budget allows {cell:.3g}: transitions near the smallest camera may be "
        "coarser than asked (raise the quality, or move that camera's near plane farther "
        "from its eye)"
    )


def trace_field(fld, tracer, fill, settings, should_stop, levels=None):
    """Trace a field method's rays on the adaptive lattice into ``fld`` (a TracedField
    whose ``grid`` and ``membership`` are set) and record the stats and warnings.

    ``levels``: the tuple of nested grids (coarsest first) when ``tracer`` reads N from
    them; the step then follows the local cell (``NestedDomain.cell_at``)."""
    rig, grid = fld.rig, fld.grid
    grids = levels or (grid,)
    stride = lattice_stride(rig, grids[-1])
    cells = step_cells(settings.accuracy_px, rig.size[0])
    max_steps = int(sum(np.ceil(np.linalg.norm(np.array(g.shape)) / cells * 2) for g in grids)) + 8
    if levels:
        domain = tracer.domain
        step = lambda x: cells * domain.cell_at(x)  # noqa: E731
    else:
        step = cells * grid.cell
    fld.step = step
    lattice = _AdaptiveLattice(tracer, rig, step, max_steps, settings.accuracy_px, should_stop)
    traced, fld.index, fld.leaves, fld.leaf_of = lattice.run(stride)
    fld.traced = traced
    fld.grids.extend(list(g.shape) for g in grids)
    fld.stats.update(
        conflicts=fill.conflicts,
        stalled=int((traced.reason == StopReason.STALLED).sum()),
        unfinished=int((traced.reason == StopReason.REACHED_LIMIT).sum()),
        stride=stride,
        traced=int(len(traced.counts)),
        cell=grids[-1].cell,
        levels=len(grids),
        newton_lost=int(getattr(tracer, "missed", 0)),
    )
    fld.warnings += conflict_messages([c.name for c in rig.cameras], fill.overlaps)
    fld.warnings += guard_warnings(rig)


def prepare_scalar_field(rig, settings=None, should_stop=None):
    """SCALAR_FIELD (paper eq. 4 to 6): a membership field solved on a grid blends
    exact per-camera tangent fields; rays are its RK4 streamlines."""
    settings = settings or Settings()
    nested = settings.nested
    if nested is None:
        nested = choose_grid(rig, settings.accuracy_px, settings.max_voxels).capped
    if nested and len(rig.cameras) > 1:
        return _prepare_nested(rig, settings, should_stop)
    fld = TracedField(rig=rig, method="SCALAR_FIELD")
    fld.warnings += check_rig(rig)
    t0 = time.perf_counter()
    fld.grid = field_grid(fld, settings)
    families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
    fill = fill_membership(rig, fld.grid, families, should_stop=should_stop)
    t1 = time.perf_counter()
    if should_stop is not None and should_stop():
        raise Cancelled()
    solve = solve_membership(fill.values, fill.constrained, should_stop=should_stop)
    t2 = time.perf_counter()
    if not solve.converged:
        raise SolverDidNotConverge(
            f"The membership solve stopped at relative residual {solve.residuals[-1]:.2e} after "
            f"{solve.iterations} iterations; simplify the masks or lower the quality"
        )
    fld.membership = solve.x
    tracer = FieldTracer(rig, fld.grid, solve.x, cubic=settings.cubic, processes=settings.processes)
    trace_field(fld, tracer, fill, settings, should_stop)
    t3 = time.perf_counter()
    fld.seconds.update(
        fill=t1 - t0,
        solve=t2 - t1,
        tangents=tracer.tangent_seconds,
        trace=t3 - t2 - tracer.tangent_seconds,
    )
    fld.solver.update(
        iterations=solve.iterations,
        residual=float(solve.residuals[-1]) if solve.residuals else 0.0,
        converged=bool(solve.converged),
    )
    return fld


def _prepare_nested(rig, settings, should_stop):
    """SCALAR_FIELD on nested grids (``nested``): the same equations, with cells that
    shrink with the bundle toward the smaller cameras."""
    fld = TracedField(rig=rig, method="SCALAR_FIELD")
    fld.warnings += check_rig(rig)
    t0 = time.perf_counter()
    outer = choose_grid(rig, settings.accuracy_px, 1 << 62).grid
    across = max(MIN_CELLS_ACROSS_NEAR, CELLS_ACROSS_NEAR_PER_PX / settings.accuracy_px)
    levels = choose_levels(rig, settings.accuracy_px, settings.max_voxels, across, outer.bounds)
    if levels.capped:
        fld.warnings.append(capped_message(settings, levels.wanted_cell, levels.grids[-1].cell))
    families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
    workers = worker_count(settings.processes)
    solved = solve_levels(rig, levels.grids, families, fill_membership, should_stop, workers)
    t1 = time.perf_counter()
    if not solved.converged:
        raise SolverDidNotConverge(
            f"The membership solve stopped at relative residual {solved.residual:.2e} after "
            f"{solved.iterations} iterations; simplify the masks or lower the quality"
        )
    fld.grid, fld.membership = levels.grids[0], solved.fields[0]
    domain = fld.domain = NestedDomain(levels.grids, solved.fields, ScaleField(rig.cameras), across)
    tracer = FieldTracer(
        rig,
        fld.grid,
        fld.membership,
        cubic=settings.cubic,
        domain=domain,
        processes=settings.processes,
    )
    fill = _composite_fill(levels.grids, solved.fills)
    trace_field(fld, tracer, fill, settings, should_stop, levels=levels.grids)
    t2 = time.perf_counter()
    fld.seconds.update(
        fill=t1 - t0,  # fill and solve interleave level by level; "solve" holds none
        solve=0.0,
        tangents=tracer.tangent_seconds,
        trace=t2 - t1 - tracer.tangent_seconds,
    )
    fld.solver.update(
        iterations=solved.iterations, residual=solved.residual, converged=solved.converged
    )
    return fld


def _composite_fill(grids, fills):
    """The conflicts and overlaps of nested fills, each level counted only where no
    finer level's box takes over (a coarse level cannot separate what a finer one does)."""
    conflicts, overlaps = 0, None
    for lev, (grid, fill) in enumerate(zip(grids, fills)):
        own = np.ones(grid.shape, dtype=bool)
        if lev + 1 < len(grids):
            own &= ~grids[lev + 1].contains(grid.centres(flat=True)).reshape(grid.shape)
        conflicts += int((fill.conflict_mask & own).sum())
        o = fill.overlaps_in(own)
        overlaps = o if overlaps is None else overlaps + o
    return SimpleNamespace(conflicts=conflicts, overlaps=overlaps)


# --- serialisation (the field cache on disk) -------------------------------------------

# Version of the array layout below; a cache entry of another version is rebuilt.
ARRAYS_VERSION = 1
# Fields that belong to the base class or are rebuilt from the scene, not stored.
# Not stored: the rig (the key is its digest), and what only re-tracing needs (nested
# grids' membership and the step function): ``rays`` reads the traced rays alone.
_NOT_STORED = ("rig", "domain", "step")


def _field_classes():
    from .strawmen import LinearField

    return {cls.__name__: cls for cls in (TracedField, CurveBlendField, LinearField)}


def field_to_arrays(fld):
    """A prepared RayField as a flat dict of numpy arrays (for ``np.savez``).

    The rig is not stored: the cache key is a digest of it, so whoever loads the field
    already holds the same rig. A ``report`` attribute (the build report dict, set by
    whoever measured the field) is kept too. Arrays keep their dtype and shape; the ``Traced`` rays
    and the ``Grid`` are split into their arrays; everything else (method, timings,
    warnings, stats, ints) goes into a JSON string under ``"meta"``.

    Returns
    -------
    dict str -> np.ndarray.
    """
    import dataclasses
    import json

    from .field import Grid, Traced

    out = {}
    meta = {"version": ARRAYS_VERSION, "class": type(fld).__name__, "plain": {}}
    for f in dataclasses.fields(fld):
        if f.name in _NOT_STORED:
            continue
        value = getattr(fld, f.name)
        if isinstance(value, np.ndarray):
            out[f"array.{f.name}"] = value
        elif isinstance(value, Traced):
            for t in dataclasses.fields(value):
                part = getattr(value, t.name)
                if t.name == "step" and part is None:  # a step that followed the cells
                    part = np.nan
                out[f"traced.{f.name}.{t.name}"] = np.asarray(part)
        elif isinstance(value, Grid):
            out[f"grid.{f.name}"] = np.concatenate(
                [value.origin, [value.cell], np.asarray(value.shape, dtype=np.float64)]
            )
        else:
            meta["plain"][f.name] = value
    if getattr(fld, "report", None) is not None:  # the build report, when one was made
        meta["report"] = fld.report
    out["meta"] = np.frombuffer(
        json.dumps(
            meta, default=lambda o: o.item() if isinstance(o, np.generic) else str(o)
        ).encode(),
        dtype=np.uint8,
    )
    return out


def field_from_arrays(arrays, rig):
    """The RayField ``field_to_arrays`` stored, for ``rig`` (the rig it was built for).

    Parameters
    ----------
    arrays : mapping str -> np.ndarray (a dict or an ``np.load`` result).
    rig : Rig.

    Raises
    ------
    ValueError when the arrays are of another layout version or an unknown class.
    """
    import json

    from .field import Grid, Traced

    meta = json.loads(bytes(np.asarray(arrays["meta"], dtype=np.uint8)).decode())
    if meta.get("version") != ARRAYS_VERSION:
        raise ValueError(f"field arrays of version {meta.get('version')}, not {ARRAYS_VERSION}")
    cls = _field_classes().get(meta.get("class"))
    if cls is None:
        raise ValueError(f"unknown field class {meta.get('class')!r}")
    kwargs = dict(meta["plain"])
    traced = {}
    for key in arrays.keys():
        kind, _, rest = key.partition(".")
        if kind == "array":
            kwargs[rest] = np.asarray(arrays[key])
        elif kind == "grid":
            g = np.asarray(arrays[key], dtype=np.float64)
            kwargs[rest] = Grid(g[:3], float(g[3]), tuple(int(n) for n in g[4:7]))
        elif kind == "traced":
            name, _, part = rest.partition(".")
            traced.setdefault(name, {})[part] = np.asarray(arrays[key])
    for name, parts in traced.items():
        step = float(parts["step"])
        parts["step"] = None if np.isnan(step) else step
        kwargs[name] = Traced(**parts)
    fld = cls(rig=rig, **kwargs)
    if "report" in meta:
        fld.report = meta["report"]
    return fld


def _strawman(name):
    """A builder of ``strawmen``, imported on first use (it builds on this module)."""

    def build(rig, settings=None, should_stop=None):
        from . import strawmen

        return getattr(strawmen, name)(rig, settings, should_stop)

    return build


METHODS = {
    "IMAGE_BLEND": prepare_image_blend,
    "LINEAR": _strawman("prepare_linear"),
    "VECTOR_FIELD": _strawman("prepare_vector_field"),
    "SCALAR_FIELD": prepare_scalar_field,
}


def prepare_auto(rig, settings=None, should_stop=None):
    """AUTO: the cheapest method that meets the accuracy target on this rig.

    IMAGE_BLEND is the cheapest (no 3D grid) and its preserved rays are exact by
    construction, so it meets any target unless its transition rays fold; its folds
    are counted on the rays it would render, and where there are any, SCALAR_FIELD is
    built (on nested grids where one uniform grid cannot hold the cells the target asks
    for). LINEAR folds wherever a transition has more than one nearest preserved pixel,
    and VECTOR_FIELD's preserved rays drift (docs/methods.md), so neither is a candidate.
    The choice and why are in ``stats["auto"]``.
    """
    from .quality import fold_map  # the report measures fields; it builds on this module

    fld = prepare_image_blend(rig, settings, should_stop)
    folds = int(fold_map(fld)[0].sum())
    if folds == 0:
        fld.stats["auto"] = "IMAGE_BLEND: its rays do not fold on this rig"
        return fld
    if should_stop is not None and should_stop():
        raise Cancelled()
    out = prepare_scalar_field(rig, settings, should_stop)
    out.stats["auto"] = f"SCALAR_FIELD: IMAGE_BLEND would fold {folds} quads on this rig"
    return out


METHODS["AUTO"] = prepare_auto


def prepare(rig, method, settings=None, should_stop=None):
    """Prepare the ray field of ``method`` (an enum name of DESIGN.md) for ``rig``."""
    try:
        builder = METHODS[method]
    except KeyError:
        raise RigError(
            f"Method '{method}' is not available in this version; use one of: " + ", ".join(METHODS)
        ) from None
    return builder(rig, settings or Settings(), should_stop)
