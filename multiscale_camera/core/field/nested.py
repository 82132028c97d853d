"""Nested grids: boxes that refine toward the smaller cameras along their bundle.

The rays of a multiscale image converge from camera 1's near plane to the last
camera's: the bundle's width w(tau) falls by the rig's scale ratio, up to 1000x on the
paper's galleon. A uniform grid fine enough for the narrow end would need the ratio
squared times more cells across camera 1's near plane than it has. Here level L has
cells of c_0 / 2**L and covers the bundle from where it has narrowed enough to need them
on (``choose_levels``): every level holds about the same number of cells across the
bundle, so the cost grows with the logarithm of the ratio, not its square.

Membership (eq. 5) is solved level by level, coarsest first (``solve_levels``): level L
holds its boundary voxels at level L-1's values (its centres are also level L-1's, the
grids are aligned) and its own fill (eq. 4) inside. N(x) is read from the finest level
whose box holds x, blended into its parent across a band of ``BAND_CELLS`` cells inside
the box's faces (``NestedDomain.sample``): continuous everywhere, so streamlines cross
levels without kinks.

Where cells are needed, and how long the trace's steps are, both follow one smooth
scale: ``ScaleField``, the width of the nearest camera's frustum at a point. The step
must vary smoothly in space: neighbouring rays interpolated vertex by vertex need their
k-th vertices at corresponding places, and a step that jumped at a box's face would
put them out of step wherever one ray crosses the face and its neighbour does not.
"""

from dataclasses import dataclass
from functools import partial

import numpy as np

from ..diagnostics import check_stop
from ..geometry import DEFAULT_SEGMENTS, build_guides, curved_rays
from ..runtime import runtime
from .grid import FieldSampler, Grid
from .solvers import solve_membership

# Level L starts where the cell the bundle asks for falls below this many times level
# L-1's cell: before level L-1 becomes too coarse, so the hand-over band lies where the
# parent still resolves the bundle.
START_RATIO = 1.4
# Width, in a level's cells, of the band inside its faces where its membership and step
# blend into its parent's.
BAND_CELLS = 3.0
# Cells of a level kept between its box and the bundle, and parent cells between a box
# and its parent's faces (beyond the parent's own band).
MARGIN_CELLS = 2
# The cell the trace's step is measured in: the scale field over the cells wanted
# across it, over this (1.0 halves the steps: on the 1000x rig at 240x135 the worst
# camera's p95 went from 0.19 to 0.36 px).
STEP_SCALE = 2.0
# Samples per guide stage for the bundle's width profile.
PROFILE_SEGMENTS = 4 * DEFAULT_SEGMENTS


@dataclass(frozen=True)
class Levels:
    """The nested grids of a rig.

    grids : tuple of Grid, coarsest first; grids[L + 1] lies inside grids[L], its cell
        half as large, its centres a superset of grids[L]'s within its box.
    wanted_cell : float, world units: the finest cell the accuracy target asks for.
    capped : bool, whether the voxel budget forced coarser cells.
    """

    grids: tuple
    wanted_cell: float
    capped: bool

    @property
    def voxels(self):
        return sum(g.size for g in self.grids)


class ScaleField:
    """The scale of the multiscale image at a point: the width of the view of the
    camera whose eye is nearest, as seen at that distance (never nearer than its near
    plane). On camera i's near plane it is camera i's near-plane width; along the
    bundle it shrinks toward the smaller cameras as the bundle does; it is continuous,
    with kinks only where two cameras are equally near.

    Parameters
    ----------
    cameras : sequence of PinholeCamera.
    """

    def __init__(self, cameras):
        self.eyes = np.array([c.eye for c in cameras], dtype=np.float64)
        self.spread = np.array([c.view_plane()[1] - c.view_plane()[0] for c in cameras])
        self.near = np.array([c.clip_start for c in cameras], dtype=np.float64)

    def __call__(self, points):
        """(P,) float64, world units, at ``points`` (P, 3) world units."""
        p = np.asarray(points, dtype=np.float64)
        out = np.full(len(p), np.inf)
        for eye, spread, near in zip(self.eyes, self.spread, self.near):
            d = p - eye
            dist = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)
            np.minimum(out, spread * np.maximum(dist, near), out=out)
        return out


def bundle_profile(rig, lattice=17):
    """Where the image's rays run, and how wide their bundle is, along the chain.

    The last camera's family bends through every near plane: its curves span the bundle
    of the final image (other families leave it straight, into their own frusta).

    Returns
    -------
    taus : (T,) float64, curve parameter (stage j is [j, j + 1]; past the last near
        plane, n - 1 + the fraction of the tail's length run straight on, up to n).
    points : (T, P, 3) float64, world units: the curves of a lattice x lattice pixel grid.
    width : (T,) float64, world units: the bundle's scale there (the smallest
        ``ScaleField`` value of its points). It falls along the chain and grows again
        past the last near plane, where the last camera's frustum widens.
    """
    cams = rig.cameras
    w, h = rig.size
    px, py = np.meshgrid(np.linspace(0, w, lattice), np.linspace(0, h, lattice))
    g = build_guides(cams, px.ravel(), py.ravel(), rig.beta)
    n = len(cams)
    rays = curved_rays(g, PROFILE_SEGMENTS)[-1]  # (P, K, 3)
    # the tail: up to a quarter of the last stage's chord past the last near plane (the
    # uniform grid's box), sampled geometrically from a hundredth of the last camera's
    # near distance, so the levels can follow the frustum as it widens again
    length = 0.25 * np.linalg.norm(g.points[-1] - g.points[-2], axis=-1)
    near = cams[-1].clip_start
    frac = np.geomspace(0.01 * near / max(length.max(), 0.02 * near), 1.0, 48)
    tail = g.points[-1][:, None] + g.directions[-1][:, None] * (length[:, None] * frac)[..., None]
    pts = np.concatenate([rays[:, : 1 + (n - 1) * PROFILE_SEGMENTS], tail], axis=1)
    pts = pts.transpose(1, 0, 2)
    taus = np.concatenate([np.linspace(0, n - 1, 1 + (n - 1) * PROFILE_SEGMENTS), n - 1 + frac])
    width = ScaleField(cams)(pts.reshape(-1, 3)).reshape(pts.shape[:2]).min(axis=1)
    return taus, pts, width


def _aligned_child(parent, lo, hi):
    """The grid of half the parent's cell covering [lo, hi], its centres on the parent's
    half-cell lattice (so every parent centre inside it is one of its centres) and its
    box inside the parent's, MARGIN_CELLS + band parent cells from its faces."""
    cell = parent.cell / 2.0
    p_lo, p_hi = parent.bounds
    keep = (MARGIN_CELLS + BAND_CELLS) * parent.cell
    lo = np.maximum(lo, p_lo + keep)
    hi = np.minimum(hi, p_hi - keep)
    hi = np.maximum(hi, lo)
    # round outwards to parent centres
    first = np.floor((lo - parent.origin) / parent.cell)
    last = np.ceil((hi - parent.origin) / parent.cell)
    first = np.maximum(first, 0)
    last = np.minimum(last, np.array(parent.shape) - 1)
    last = np.maximum(last, first + 1)
    origin = parent.origin + first * parent.cell
    shape = tuple(int(n) for n in (2 * (last - first) + 1))
    return Grid(origin, cell, shape)


def choose_levels(rig, accuracy_px, max_voxels, cells_across, outer_box):
    """Nested grids for ``rig`` from its accuracy target.

    Parameters
    ----------
    rig : Rig. accuracy_px : float, target preserved error in pixels (recorded only;
        ``cells_across`` carries it). max_voxels : int, budget for all levels together.
    cells_across : float, cells wanted across the bundle's width at every depth.
    outer_box : (lo, hi) two (3,) float arrays, world units: the region level 0 covers.

    Returns
    -------
    Levels
    """
    taus, pts, width = bundle_profile(rig)
    wanted = width / cells_across  # the cell each part of the bundle asks for
    finest = wanted.min()
    lo, hi = outer_box
    most = int(max(0, np.ceil(np.log2(wanted[0] / finest) - 1e-9)))
    # coarsen every level until the budget holds them; where even that cannot (each
    # level keeps a few cells of margin), give up the finest level and try again
    for levels in range(most, -1, -1):
        for attempt in range(MAX_COARSENINGS + 1):
            scale = 1.1**attempt
            grids = _layout(pts, wanted, lo, hi, scale, levels)
            if sum(g.size for g in grids) <= max_voxels:
                capped = attempt > 0 or levels < most
                return Levels(tuple(grids), float(finest), capped)
    return Levels(tuple(grids[:1]), float(finest), True)


# Times the cells may grow by 10% to fit the voxel budget before a level is given up.
MAX_COARSENINGS = 40


def _layout(pts, wanted, lo, hi, scale, levels):
    """The aligned nested grids for cells ``scale`` times those wanted, with ``levels``
    levels under the coarsest (see ``choose_levels``)."""
    c0 = wanted[0] * scale
    boxes = []
    for lev in range(1, levels + 1):
        parent_cell = c0 / 2 ** (lev - 1)
        need = wanted * scale < START_RATIO * parent_cell
        # one sample either side of where the level is needed
        need[:-1] |= need[1:].copy()
        need[1:] |= need[:-1].copy()
        sel = pts[need].reshape(-1, 3)
        pad = MARGIN_CELLS * parent_cell / 2 + BAND_CELLS * parent_cell / 2
        boxes.append((sel.min(0) - pad, sel.max(0) + pad))
    # a child box must sit inside its parent: grow parents around their children,
    # finest first, before laying out the aligned grids coarsest first
    boxes.insert(0, (np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)))
    for lev in range(len(boxes) - 2, -1, -1):
        child_lo, child_hi = boxes[lev + 1]
        keep = (MARGIN_CELLS + BAND_CELLS + 1) * c0 / 2**lev
        b_lo, b_hi = boxes[lev]
        boxes[lev] = (np.minimum(b_lo, child_lo - keep), np.maximum(b_hi, child_hi + keep))
    grids = [Grid.from_bounds(*boxes[0], c0)]
    for box_lo, box_hi in boxes[1:]:
        grids.append(_aligned_child(grids[-1], box_lo, box_hi))
    return grids


class NestedDomain:
    """Membership on nested grids, read as one continuous field.

    Parameters
    ----------
    grids : sequence of Grid, coarsest first (``Levels.grids``).
    fields : sequence of (nx, ny, nz) float arrays, the membership on each grid.
    scale : ScaleField or None, what the trace's step follows (``cell_at``).
    cells_across : float, cells wanted across the scale (``choose_levels``).
    """

    def __init__(self, grids, fields, scale=None, cells_across=1.0):
        self.grids = tuple(grids)
        self.scale = scale
        self.cells_across = float(cells_across)
        self.bands = np.array([BAND_CELLS * g.cell for g in self.grids])
        # every level's values in one flat float32 array, read by one gather per
        # corner whatever level each point reads (``_read``)
        shapes = np.array([g.shape for g in self.grids], dtype=np.intp)
        sizes = shapes.prod(axis=1)
        self.values = np.concatenate(
            [np.ascontiguousarray(f, dtype=np.float32).ravel() for f in fields]
        )
        self.offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)
        self.origins = np.array([g.origin for g in self.grids], dtype=np.float64)
        self.inv_cells = np.array([1.0 / g.cell for g in self.grids])
        self.tops = (shapes - 1).astype(np.float64)
        self.lasts = np.maximum(shapes - 2, 0)
        strides = np.stack([shapes[:, 1] * shapes[:, 2], shapes[:, 2], np.ones_like(sizes)], 1)
        self.strides = strides
        self.steps = strides * (shapes > 1)
        bounds = [g.bounds for g in self.grids]
        self.lo = np.array([b[0] for b in bounds])
        self.hi = np.array([b[1] for b in bounds])

    @property
    def finest_cell(self):
        return self.grids[-1].cell

    def contains(self, points):
        """(P,) bool: inside the outermost box (the modelled volume)."""
        return self.grids[0].contains(points)

    def _depth(self, points):
        """The finest level whose ramp is positive at each point, and that ramp.

        Boxes nest with a level's box at least its parent's band inside the parent's
        faces (``_aligned_child``), so where a level's ramp is positive its parent's is
        1: N there is that level's value blended into its parent's alone.

        Returns
        -------
        level : (P,) int64, 0 where no finer box holds the point (NaN points too).
        ramp : (P,) float64 in (0, 1], that level's ramp (1 on level 0).
        """
        n = len(points)
        level = np.zeros(n, dtype=np.int64)
        inside = np.zeros(n)
        # the boxes nest: only points inside a level's box can be inside its child's
        cand, pts = np.arange(n), points
        for lev in range(1, len(self.grids)):
            lo, hi = self.lo[lev], self.hi[lev]
            d = None
            for a in range(3):  # per column: a reduction over a length-3 axis is slow
                c = pts[:, a]
                e = np.minimum(c - lo[a], hi[a] - c)
                d = e if d is None else np.minimum(d, e, out=d)
            deeper = d > 0
            cand, pts = cand[deeper], pts[deeper]
            if not len(cand):
                break
            level[cand] = lev
            inside[cand] = d[deeper]
        s = np.clip(inside / self.bands[level], 0.0, 1.0)
        s[level == 0] = 1.0
        return level, s * s * (3.0 - 2.0 * s)

    def _read(self, points, level):
        """Trilinear N of level ``level[p]`` at each point ``points[p]``: (P,) float64.
        As ``grid.sample``: clamped to each level's box of centres."""
        idx = (points - self.origins[level]) * self.inv_cells[level][:, None]
        np.maximum(idx, 0.0, out=idx)
        np.minimum(idx, self.tops[level], out=idx)
        with np.errstate(invalid="ignore"):  # NaN points: corner 0, NaN weights
            corner = idx.astype(np.intp)
        np.minimum(corner, self.lasts[level], out=corner)
        np.maximum(corner, 0, out=corner)
        f = idx - corner
        strides, steps = self.strides[level], self.steps[level]
        base = self.offsets[level] + corner[:, 0] * strides[:, 0]
        base += corner[:, 1] * strides[:, 1]
        base += corner[:, 2]
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        sx, sy, sz = steps[:, 0], steps[:, 1], steps[:, 2]
        vals = self.values
        # lerp along z, then y, then x
        z00 = vals[base] + fz * (vals[base + sz] - vals[base])
        b = base + sy
        z01 = vals[b] + fz * (vals[b + sz] - vals[b])
        b = base + sx
        z10 = vals[b] + fz * (vals[b + sz] - vals[b])
        b += sy
        z11 = vals[b] + fz * (vals[b + sz] - vals[b])
        y0 = z00 + fy * (z01 - z00)
        y1 = z10 + fy * (z11 - z10)
        return y0 + fx * (y1 - y0)

    def sample(self, points):
        """Membership N at ``points`` ((P, 3) world units): (P,) float32.

        Each level's value is blended into its parent's by its ramp, coarsest first;
        with the boxes nested (``_depth``) that is at most two trilinear reads a point:
        the finest level holding it and, inside that level's band, its parent."""
        points = np.asarray(points, dtype=np.float64)
        level, ramp = self._depth(points)
        out = self._read(points, level)
        blend = np.flatnonzero(ramp < 1.0)
        if len(blend):
            parent = self._read(points[blend], level[blend] - 1)
            out[blend] = parent + ramp[blend] * (out[blend] - parent)
        return out.astype(np.float32)

    def cell_at(self, points):
        """The cell the accuracy target asks for at ``points`` ((P, 3) world units):
        (P,) float64, world units, the ``ScaleField`` over the cells wanted across it,
        halved (where a level takes over, its cells are between 1/1.4 and 1/2.8 of it:
        ``START_RATIO``); the coarsest level's cell where there is no scale field."""
        points = np.asarray(points, dtype=np.float64)
        if self.scale is None:
            return np.full(len(points), self.grids[0].cell)
        return self.scale(points) / (STEP_SCALE * self.cells_across)


@dataclass(frozen=True)
class LevelSolve:
    """The membership of every level and how its solves went.

    fields : list of (nx, ny, nz) float32. fills : list of field.Fill.
    iterations : int, the most PCG iterations of a level. residual : float, the worst
    final relative residual. converged : bool, every level converged.
    """

    fields: list
    fills: list
    iterations: int
    residual: float
    converged: bool


def _fill_level(fill_membership, rig, families, item, context):
    """A worker's fill of one level (``solve_levels``): ``item`` is (grid, known)."""
    grid, known = item
    return fill_membership(rig, grid, families, should_stop=context, known=known)


def solve_levels(
    rig, grids, families, fill_membership, should_stop=None, processes=1, known=None, warm=None
):
    """Fill and solve every level, coarsest first; a finer level's boundary voxels hold
    its parent's membership (Dirichlet), its own constraints hold inside.

    The fills do not depend on one another: with ``processes`` > 1 they are shared
    among worker processes (``runtime``) before the solves run in order.

    Parameters
    ----------
    rig : Rig. grids : sequence of Grid, coarsest first. families : list of Family.
    fill_membership : callable (rig, grid, families, should_stop=) -> Fill
        (``fill.fill_membership``; module-level, so that workers find it by name).
    should_stop : optional callable, asked during each level's fill and solve.
    processes : int, worker processes for the fills (1: in-process).
    known : None, or per level the ``known`` claims of ``fill_membership`` (cameras
        already splatted on that level's grid). warm : None, or per level None or an
        (nx, ny, nz) membership to start the level's solve from (a previous frame's on
        the same grid) instead of the parent's values.

    Returns
    -------
    LevelSolve
    """

    known = list(known) if known is not None else [None] * len(grids)
    warm = list(warm) if warm is not None else [None] * len(grids)
    shared = None
    if processes > 1:
        task = partial(_fill_level, fill_membership, rig, families)
        items = list(zip(grids, known, strict=True))
        shared = runtime().map(task, items, processes, should_stop).results
    fields, fills, its, res, ok = [], [], 0, 0.0, True
    for lev, grid in enumerate(grids):
        check_stop(should_stop)
        if shared is not None:
            fill, shared[lev] = shared[lev], None
        else:
            fill = fill_membership(rig, grid, families, should_stop=should_stop, known=known[lev])
        check_stop(should_stop)
        values, constrained, x0 = fill.values, fill.constrained, None
        if lev:
            parent = FieldSampler(grids[lev - 1], fields[-1])
            x0 = parent(grid.centres(flat=True)).reshape(grid.shape)
            shell = np.ones(grid.shape, dtype=bool)
            shell[1:-1, 1:-1, 1:-1] = False
            values = np.where(shell, x0, values).astype(np.float32)
            constrained = constrained | shell
        if warm[lev] is not None:
            x0 = warm[lev]
        solve = solve_membership(values, constrained, x0=x0, should_stop=should_stop)
        fields.append(solve.x)
        fills.append(fill)
        its = max(its, solve.iterations)
        res = max(res, float(solve.residuals[-1]) if solve.residuals else 0.0)
        ok = ok and bool(solve.converged)
    return LevelSolve(fields, fills, its, res, ok)
