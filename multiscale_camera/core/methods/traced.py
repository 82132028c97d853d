"""Rays traced through a field on an adaptive pixel lattice (``TracedField``), the
base of SCALAR_FIELD and VECTOR_FIELD: the lattice traces rays where interpolating
them would err, and every other pixel's ray is interpolated from the traced ones.
"""

from dataclasses import dataclass
from functools import partial

import numpy as np

from ..field import (
    FieldTracer,
    NearPlaneStep,
    StopReason,
    choose_grid,
    merge,
    near_plane_width,
    run_on,
    steady_grid,
    step_cells,
)
from ..field.plane_step import plane_gain, schedule_of
from ..quality import along_ray, conflict_messages, substitution_messages
from ..runtime import release_free_memory, worker_count
from .base import RayField, guard_warnings


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
            max(int(self.traced.counts[r].max(initial=0)) for r, _w in corners) + 1,
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
        last = np.maximum.reduce([self.traced.counts[r] for r, _w in corners])
        straight_on(verts, last)
        return self._bundle(ix, iy, verts, mem)

    def ray_vertices(self):
        """Every traced ray's vertex count (an interpolated ray has at most as many)."""
        return int(self.traced.vertices.shape[1])

    def exit_index(self, ix, iy):
        """(P,) int: for each pixel, the vertex where its ray leaves the grid (the
        smallest traced count among the rays it is interpolated from)."""
        counts = self.traced.counts
        rows = [row for row, _w in self._corners(np.asarray(ix), np.asarray(iy))]
        return np.minimum.reduce([counts[r] for r in rows]) - 1


def straight_on(verts, last):
    """Run interpolated rays straight on past their corners' last traced vertex, in place: ray
    p's vertices after ``last[p]`` continue its segment from ``last[p] - 1`` to
    ``last[p]`` (the first vertex past every corner's trace, where all four run
    straight) at that segment's length, as the renderer's leaf schedules end there and
    keep every vertex from the first corner's last on (``sampling``). The corners' own
    run-ons need not keep step with one another (their step follows the point: nested
    cells, the bands at near planes); mixed vertex by vertex up to the longest ray of
    the request, they bent a ray further out by as much as the other pixels asked for
    had run on: camera 2's rays on the nested 1000x rig at 120x68 PREVIEW strayed up to
    0.045 px more among their mask's rays than alone.

    verts : (P, K, 3) float32, K >= 2. last : (P,) int, clipped to 1 .. K - 1."""
    k = verts.shape[1]
    last = np.clip(np.asarray(last, dtype=np.int64), 1, k - 1)
    rows = np.flatnonzero(last < k - 1)
    if not len(rows):
        return
    rows = rows[np.argsort(last[rows], kind="stable")]
    ends, starts = np.unique(last[rows], return_index=True)
    ahead = np.arange(1, k, dtype=verts.dtype)[None, :, None]  # 1, 2, ... past the last
    for n, (at, first) in enumerate(zip(ends.tolist(), starts.tolist())):
        r = rows[first : starts[n + 1] if n + 1 < len(starts) else len(rows)]
        end = verts[r, at]
        seg = end - verts[r, at - 1]
        verts[r, at + 1 :] = end[:, None] + ahead[:, : k - 1 - at] * seg[:, None]


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


# Accuracy target of a lattice cell whose pixels all belong to one camera's preserved
# region, as a fraction of the build's: its rays are laid out exactly (no trace), and
# interpolating them is the only error left on that camera's pixels: what it adds,
# measured where the picture shows it (``_AdaptiveLattice._pure_error``).
PRESERVED_TOL_FRACTION = 0.25


def preserved_labels(rig):
    """(H, W) int8: 1 + the camera whose preserved ray a pixel gets (a rig's masks do
    not overlap), 0 for transition pixels."""
    w, h = rig.size
    label = np.zeros((h, w), dtype=np.int8)
    for i, mask in enumerate(rig.masks):
        label[np.asarray(mask, dtype=bool)] = i + 1
    return label


class _CellLabels:
    """Which lattice cells (closed pixel rectangles x0..x1, y0..y1) hold pixels of one
    preserved region only, or a mix, from one summed-area table per camera."""

    def __init__(self, label, count):
        self.tables = []
        for i in range(count):
            t = np.zeros((label.shape[0] + 1, label.shape[1] + 1), dtype=np.int64)
            t[1:, 1:] = np.cumsum(np.cumsum(label == i + 1, axis=0), axis=1)
            self.tables.append(t)

    def kinds(self, cells):
        """For (n, 4) cells: pure (n,) bool, every pixel preserved by one camera; mixed
        (n,) bool, some pixel preserved but not all by the same camera."""
        x0, y0, x1, y1 = (np.asarray(c, dtype=np.int64) for c in np.asarray(cells).T)
        area = (x1 - x0 + 1) * (y1 - y0 + 1)
        pure = np.zeros(len(x0), dtype=bool)
        some = np.zeros(len(x0), dtype=bool)
        for t in self.tables:
            n = t[y1 + 1, x1 + 1] - t[y0, x1 + 1] - t[y1 + 1, x0] + t[y0, x0]
            pure |= n == area
            some |= n > 0
        return pure, some & ~pure


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

    Where the tracer lays preserved rays out exactly (``exact_preserved``), a cell that
    mixes one camera's preserved pixels with other pixels is split down to single
    pixels whatever its error (interpolating across a mask's edge would bend preserved
    rays towards their neighbours), and a cell of one camera's preserved pixels only is
    checked against that camera's own rays instead of the estimate: what interpolating
    its rays adds to the camera's error along the whole ray, at its centre and the
    middles of its edges, is held to ``PRESERVED_TOL_FRACTION`` of the tolerance
    (``_pure_error``). The estimate, on an edge of odd length, compares the ray one
    pixel before the middle with the mean half a pixel further on and never falls
    below 0.5 px there: held to a quarter of the tolerance it split every such cell to
    single pixels (docs/architecture.md).
    """

    def __init__(self, tracer, rig, step, max_steps, tol_px, diag):
        self.tracer, self.rig, self.step = tracer, rig, step
        # run-ons follow the step's band around near planes (``field.run_on``)
        self.schedule = schedule_of(step)
        self.max_steps, self.tol, self.diag = max_steps, tol_px, diag
        w, h = rig.size
        self.index = np.full((h, w), -1, dtype=np.int32)
        self.parts, self.order, self.count = [], [], 0
        # each traced ray's pixel, in the order traced
        self.pixel_x = self.pixel_y = np.zeros(0, dtype=np.int64)
        self.labels = self.label = None
        if getattr(tracer, "exact_preserved", False):
            self.label = preserved_labels(rig)
            self.labels = _CellLabels(self.label, len(rig.cameras))
            self.own_error = np.zeros(0)  # along_ray of each traced ray, nan: not yet

    def _fine(self, cells, err):
        """(n,) bool: cells whose interpolation error estimate ``err`` (n,) meets the
        target, preserved regions' edges and interiors as the class says."""
        if self.labels is None:
            return err <= self.tol
        pure, mixed = self.labels.kinds(cells)
        fine = (err <= self.tol) & ~mixed & ~pure
        check = np.flatnonzero(pure)
        k = self.width()
        block = max(1, DEVIATION_BLOCK_VERTICES // (5 * k))  # five rays a cell
        for s in range(0, len(check), block):
            sel = check[s : s + block]
            fine[sel] = self._pure_error(cells[sel]) <= self.tol * PRESERVED_TOL_FRACTION
        return fine

    def _pure_error(self, cells):
        """(n,) float64: what interpolating the rays of ``cells`` (n, 4), each inside one
        camera's preserved region, adds to that camera's error, in its pixels, measured
        as the report measures it (``quality.along_ray``: the whole ray from the
        camera's near plane out to its clip end, against the pixel centre's pinhole ray)
        at the cell's centre and the middles of its edges: the worst there less the
        worst of its four traced corners (inf where a ray never reaches the stretch)."""
        x0, y0, x1, y1 = (np.tile(np.asarray(c, dtype=np.int64), 5) for c in cells.T)
        n = len(cells)
        xm, ym = (x0 + x1) // 2, (y0 + y1) // 2
        # the centre, then the middles of the edges y0, y1, x0 and x1
        sx = np.concatenate([xm[:n], xm[:n], xm[:n], x0[:n], x1[:n]])
        sy = np.concatenate([ym[:n], y0[:n], y1[:n], ym[:n], ym[:n]])
        cam = self.label[y0, x0].astype(np.int64) - 1
        fx = np.where(x1 > x0, (sx - x0) / np.maximum(x1 - x0, 1), 0.0)
        fy = np.where(y1 > y0, (sy - y0) / np.maximum(y1 - y0, 1), 0.0)
        corners = [
            (self.index[y0, x0], (1 - fy) * (1 - fx)),
            (self.index[y0, x1], (1 - fy) * fx),
            (self.index[y1, x0], fy * (1 - fx)),
            (self.index[y1, x1], fy * fx),
        ]
        verts, last = None, 0
        for row, weight in corners:  # as ``TracedField.rays`` interpolates them
            v, counts = self.rows(row)
            v = v.astype(np.float64) * weight[:, None, None]
            verts = v if verts is None else verts + v
            last = np.maximum(last, counts)
        straight_on(verts, last)
        own = np.max([self._own_error(row) for row, _weight in corners], axis=0)
        got = np.zeros(len(sx))
        cams = self.rig.cameras
        for c in np.unique(cam):
            sel = np.flatnonzero(cam == c)
            got[sel] = along_ray(verts[sel], cams[c], sx[sel] + 0.5, sy[sel] + 0.5, cams[:c])[0]
        added = np.where(np.isfinite(got) & np.isfinite(own), got - own, np.inf)
        return added.reshape(5, n).max(axis=0)

    def _own_error(self, ids):
        """(n,) float64: ``along_ray`` of traced rays ``ids`` (n,), each against the
        camera that keeps its pixel, at that pixel: computed once per ray."""
        if len(self.own_error) < self.count:
            grown = np.full(self.count, np.nan)
            grown[: len(self.own_error)] = self.own_error
            self.own_error = grown
        todo = np.unique(ids[np.isnan(self.own_error[ids])])
        if len(todo):
            px, py = self.pixel_x[todo], self.pixel_y[todo]
            c_of = self.label[py, px].astype(np.int64) - 1
            cams = self.rig.cameras
            k = self.width()
            block = max(1, DEVIATION_BLOCK_VERTICES // k)
            for s in range(0, len(todo), block):
                verts = self.rows(todo[s : s + block])[0]
                for c in np.unique(c_of[s : s + block]):
                    sel = s + np.flatnonzero(c_of[s : s + block] == c)
                    self.own_error[todo[sel]] = along_ray(
                        verts[sel - s], cams[c], px[sel] + 0.5, py[sel] + 0.5, cams[:c]
                    )[0]
        return self.own_error[ids]

    def trace(self, px, py):
        """Trace the pixels not traced yet (duplicates allowed)."""
        key = np.unique(np.asarray(py, dtype=np.int64) * self.index.shape[1] + np.asarray(px))
        py, px = np.divmod(key, self.index.shape[1])
        new = self.index[py, px] < 0
        px, py = px[new], py[new]
        if len(px) == 0:
            return
        self.diag.check()
        # the workers' shares stay apart, each numbered as one run of rays: merging them
        # here would hold the round twice, and ``run``'s merge would then hold the
        # round's copy beside the result (the build's peak on large images)
        shares = self.tracer.trace_pixels(
            px, py, self.step, self.max_steps, self.diag.should_stop, parts=True
        )
        rows = np.concatenate([r for _traced, r in shares])
        for traced, r in shares:
            self.parts.append(traced)
            self.order.append(np.arange(self.count, self.count + len(r)))
            self.count += len(r)
        start = self.count - len(rows)
        self.pixel_x = np.concatenate([self.pixel_x, px[rows]])
        self.pixel_y = np.concatenate([self.pixel_y, py[rows]])
        self.index[py[rows], px[rows]] = np.arange(start, self.count)

    def width(self):
        """int: the most vertices any traced ray is laid out with."""
        return max(p.width for p in self.parts)

    def rows(self, ids):
        """Vertices (n, K, 3) float32 and counts (n,) of traced rays ``ids`` (n,),
        K the most any part has (shorter rays run straight on, as ``merge`` lays
        them out). The parts stay apart until ``run`` ends: merging after every round
        would hold two copies of every ray."""
        k = self.width()
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
            verts[sel] = run_on(p.rows(r), k, self.schedule).vertices
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
        k = self.width()
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
        flagged = ~self._fine(cells, rough / CHILD_ERROR_RATIO)
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
            children = np.concatenate(
                [
                    np.stack([x0, y0, xm, ym], 1),
                    np.stack([xm, y0, x1, ym], 1),
                    np.stack([x0, ym, xm, y1], 1),
                    np.stack([xm, ym, x1, y1], 1),
                ]
            )
            keep = self._fine(children, np.tile(err / CHILD_ERROR_RATIO, 4))
            leaves.append(children[keep])
            cells = children[~keep]
        leaves = np.concatenate(leaves).astype(np.int32)
        leaf_of = np.zeros((h, w), dtype=np.int32)
        for n, (a, b, c, d) in enumerate(leaves.tolist()):
            leaf_of[b : d + 1, a : c + 1] = n
        parts, order = self.parts, self.order
        self.parts, self.order = [], []
        # in shared memory where workers will be handed the field (its fold count, the
        # render's tables): they map its rays then rather than a copy of them
        shared = worker_count(getattr(self.tracer, "processes", 1)) >= 2
        # the rounds' temporaries freed between the kept rays: their pages go back
        # before the merge lays every ray out (the merge hands back each part's itself)
        release_free_memory()
        traced = merge(parts, order, self.count, self.schedule, shared=shared)
        return traced, self.index, leaves, leaf_of


def lattice_stride(rig, grid):
    """Pixels between traced rays: half the smallest camera's pixels per cell, so every
    cell the rays cross is seen by two lattice rays, clamped to 1 .. MAX_STRIDE."""
    cams = rig.cameras
    w = rig.size[0]
    px = min(near_plane_width(c) / w for c in cams)
    return int(np.clip(grid.cell / px / 2, 1, MAX_STRIDE))


def field_grid(fld, settings):
    """The grid of a field method (``choose_grid``): the shot's (``settings.layout``,
    uniform) where it holds the frame's, else laid on the world lattice within the
    budget when ``settings.steady``; with a warning on ``fld`` when the voxel budget
    caps the cell the accuracy target asks for."""
    choice = choose_grid(fld.rig, settings.accuracy_px, settings.max_voxels)
    if choice.capped:
        fld.warnings.append(capped_message(settings, choice.wanted_cell, choice.grid.cell))
    layout = settings.layout
    if layout is not None and not layout.nested and layout.covers((choice.grid,)):
        fld.stats["layout"] = "shot"
        return layout.grids[0]
    if settings.steady:
        fld.stats["layout"] = "frame"
        return steady_grid(choice.grid, settings.max_voxels)
    return choice.grid


def capped_message(settings, wanted, cell):
    """The warning for a voxel budget that forced cells coarser than the target asks."""
    return (
        f"The accuracy target of {settings.accuracy_px:g} px wants {wanted:.3g}-unit cells; "
        f"the voxel budget allows {cell:.3g}: transitions near the smallest camera may be "
        "coarser than asked (raise the quality, or move that camera's near plane farther "
        "from its eye)"
    )


def _nested_step(cells, domain, x):
    """The trace's step at points ``x`` ((..., 3)): ``cells`` of the local cell of the
    nested grids (``NestedDomain.cell_at``), world units."""
    return cells * domain.cell_at(x)


def trace_field(fld, tracer, fill, settings, diag, levels=None):
    """Trace a field method's rays on the adaptive lattice into ``fld`` (a TracedField
    whose ``grid`` and ``membership`` are set) and record the stats and warnings;
    ``diag`` (core.diagnostics.Diagnostics) is asked whether to stop.

    ``levels``: the tuple of nested grids (coarsest first) when ``tracer`` reads N from
    them; the step then follows the local cell (``NestedDomain.cell_at``)."""
    rig, grid = fld.rig, fld.grid
    grids = levels or (grid,)
    stride = lattice_stride(rig, grids[-1])
    cells = step_cells(settings.accuracy_px, rig.size[0])
    max_steps = int(sum(np.ceil(np.linalg.norm(np.array(g.shape)) / cells * 2) for g in grids)) + 8
    if levels:
        # a partial, not a lambda: the step goes to worker processes with the tracer
        step = partial(_nested_step, cells, tracer.domain)
    else:
        step = cells * grid.cell
    # VECTOR_FIELD lays out no preserved ray (its Y only approximates R_i): no band
    exact = getattr(tracer, "exact_preserved", False)
    gains = plane_gains(tracer, rig, step, settings.accuracy_px) if exact else []
    if max(gains, default=1.0) > 1.0:
        step = NearPlaneStep(step, rig.cameras[1:], gains)
        max_steps += step.extra_steps()
    fld.step = step
    lattice = _AdaptiveLattice(tracer, rig, step, max_steps, settings.accuracy_px, diag)
    traced, fld.index, fld.leaves, fld.leaf_of = lattice.run(stride)
    fld.traced = traced
    fld.grids.extend(list(g.shape) for g in grids)
    fld.stats.update(
        plane_gains=[round(g, 3) for g in gains],
        conflicts=fill.conflicts,
        stalled=int((traced.reason == StopReason.STALLED).sum()),
        unfinished=int((traced.reason == StopReason.REACHED_LIMIT).sum()),
        stride=stride,
        traced=int(len(traced.counts)),
        cell=grids[-1].cell,
        levels=len(grids),
        newton_lost=int(getattr(tracer, "missed", 0)),
    )
    fld.warnings += substitution_messages(rig, traced, fld.index, tracer.lost)
    fld.warnings += conflict_messages([c.name for c in rig.cameras], fill.overlaps)
    fld.warnings += guard_warnings(rig)


# Preserved pixels per camera whose rays ``plane_gains`` weighs at its near plane.
PLANE_SAMPLE = 256


def plane_gains(tracer, rig, step, accuracy_px):
    """How many times to shorten the trace's step at each near plane of cameras 2..N
    (``field.NearPlaneStep``), from the sag of the segment that straddles it.

    Up to ``PLANE_SAMPLE`` of camera i's preserved pixels, spread over its mask, have
    their segment across the plane weighed at every phase (``field.plane_step.
    plane_gain``): a preserved ray is R_i at every vertex, so past the plane that chord
    is its only error, and it falls as the step squared. 1 for a camera without
    preserved pixels.

    Parameters
    ----------
    tracer : FieldTracer (its families). rig : Rig. step : float (world units) or
        callable, the trace's unshortened step. accuracy_px : float.

    Returns
    -------
    list of float, one per camera 2..N, each in [1, MAX_GAIN].
    """
    cams = rig.cameras
    gains = []
    for i in range(1, len(cams)):
        ys, xs = np.nonzero(rig.masks[i])
        if not len(xs):
            gains.append(1.0)
            continue
        pick = np.unique(np.linspace(0, len(xs) - 1, min(len(xs), PLANE_SAMPLE)).astype(np.int64))
        u, v = xs[pick] + 0.5, ys[pick] + 0.5
        if callable(step):
            base = np.asarray(step(cams[i].near_points(cams[i].directions(u, v))), dtype=np.float64)
        else:
            base = np.full(len(u), float(step))
        gains.append(plane_gain(tracer.families[i], u, v, base, accuracy_px))
    return gains
