"""Grid choice and the membership constraint M of the paper's ray field (section 4.4,
eq. 4).

1. Grid: an axis-aligned box around camera 1's near plane and every curved ray R_i up to
   just past the last camera's near plane; the cell follows from the smallest camera's
   near-plane width and the accuracy target.
2. Fill (eq. 4): M = i on every voxel that a preserved ray of camera i passes near
   (forward splatting of R_i over camera i's mask, dilated by one voxel so that every
   trilinear lookup along a preserved ray reads only that camera's constraint).
   Voxels that two cameras claim are left free and counted.

The solve (eq. 5) that makes N of M is ``solvers.solve_membership``; the tracer of the
blended field is ``tracer``.
"""

from dataclasses import dataclass

import numpy as np

from ..diagnostics import check_stop
from ..geometry import DEFAULT_SEGMENTS, build_guides, curved_rays
from .grid import Grid

# Cells across the smallest camera's near plane, per pixel of accuracy asked for: the
# bundle is narrowest there, and its transitions need a few cells to be smooth.
CELLS_ACROSS_NEAR_PER_PX = 8.0
MIN_CELLS_ACROSS_NEAR = 8


@dataclass(frozen=True)
class GridChoice:
    """The grid and why it has that size.

    grid : Grid. wanted_cell : float, world units, the cell the accuracy target asks
    for. capped : bool, whether the voxel budget forced a coarser cell.
    """

    grid: Grid
    wanted_cell: float
    capped: bool


def near_plane_width(cam):
    """Width of a camera's near plane (the image rectangle at clip_start), world units."""
    xmin, xmax, _ymin, _ymax = cam.view_plane()
    return (xmax - xmin) * cam.clip_start


def choose_grid(rig, accuracy_px, max_voxels, lattice=17):
    """The box of the bending stretch and a cell size from the rig and the accuracy target.

    Parameters
    ----------
    rig : Rig. accuracy_px : float, target preserved error in pixels.
    max_voxels : int, the voxel budget. lattice : int, pixels per side sampled for the box.

    Returns
    -------
    GridChoice
    """
    cams = rig.cameras
    w, h = rig.size
    px, py = np.meshgrid(np.linspace(0, w, lattice), np.linspace(0, h, lattice))
    g = build_guides(cams, px.ravel(), py.ravel(), rig.beta)
    n = len(cams)
    smallest = min(near_plane_width(c) for c in cams[1:]) if n > 1 else near_plane_width(cams[0])
    across = max(MIN_CELLS_ACROSS_NEAR, CELLS_ACROSS_NEAR_PER_PX / accuracy_px)
    cell = smallest / across
    if n > 1:
        rays = curved_rays(g, DEFAULT_SEGMENTS)[:, :, : 1 + (n - 1) * DEFAULT_SEGMENTS]
        pts = rays.reshape(-1, 3)
        # run on past the last near plane far enough for its rays to settle
        tail = (
            g.points[-1]
            + g.directions[-1]
            * (0.25 * np.linalg.norm(g.points[-1] - g.points[-2], axis=-1))[:, None]
        )
        pts = np.concatenate([pts, tail])
    else:
        pts = g.points[0]
    lo, hi = pts.min(0), pts.max(0)
    span = hi - lo
    capped = False
    wanted = cell
    while np.prod(np.ceil(span / cell) + 3) > max_voxels:
        cell *= 1.1
        capped = True
    return GridChoice(Grid.from_bounds(lo, hi, cell), wanted, capped)


def _dilate(a):
    """Binary dilation of a 3D bool array by one voxel (3x3x3 cube), separable."""
    out = a.copy()
    for axis in range(3):
        src = out.copy()
        lead = [slice(None)] * 3
        trail = [slice(None)] * 3
        lead[axis], trail[axis] = slice(1, None), slice(None, -1)
        out[tuple(lead)] |= src[tuple(trail)]
        out[tuple(trail)] |= src[tuple(lead)]
    return out


def splat_camera(grid, family, mask, chunk=200_000, should_stop=None):
    """Voxels near camera i's preserved rays (eq. 4's support for one camera).

    The family R_i is sampled over the mask at a pixel spacing and a tau spacing small
    enough that consecutive samples are at most half a cell apart; each sample marks its
    nearest voxel (the core). The halo is the core dilated by one voxel: with it, every
    trilinear lookup along a preserved ray reads only this camera's constraint.

    Parameters
    ----------
    grid : Grid. family : Family of camera i. mask : (H, W) bool, camera i's mask.
    should_stop : callable () -> bool or None, asked between chunks of samples.

    Returns
    -------
    core, halo : (nx, ny, nz) bool, disjoint.

    Raises
    ------
    Cancelled when ``should_stop`` says so.
    """
    claimed = np.zeros(grid.shape, dtype=bool)
    if not mask.any():
        return claimed, claimed.copy()
    h, w = mask.shape
    cam = family.cameras[-1]
    # sample pixels in and one pixel around the mask, so its edge rays are covered
    grown = mask.copy()
    grown[1:] |= mask[:-1]
    grown[:-1] |= mask[1:]
    grown[:, 1:] |= grown[:, :-1].copy()
    grown[:, :-1] |= grown[:, 1:].copy()
    ys, xs = np.nonzero(grown)
    pick = np.linspace(0, len(xs) - 1, min(len(xs), 64)).astype(int)
    probe_u, probe_v = xs[pick] + 0.5, ys[pick] + 0.5
    for j in range(family.i):
        check_stop(should_stop)
        window = _stage_window(grid, family, j, w, h)
        if window is None:
            continue
        t0, t1 = window
        taus = np.linspace(t0, t1, 5)
        uu = np.repeat(probe_u, len(taus))
        vv = np.repeat(probe_v, len(taus))
        tt = np.tile(taus, len(pick))
        p, tangent = family.evaluate(uu, vv, tt)
        pu, _ = family.evaluate(uu + 1.0, vv, tt)
        pv, _ = family.evaluate(uu, vv + 1.0, tt)
        per_px = max(np.linalg.norm(pu - p, axis=-1).max(), np.linalg.norm(pv - p, axis=-1).max())
        per_tau = np.linalg.norm(tangent, axis=-1).max()
        du = float(np.clip(0.5 * grid.cell / max(per_px, 1e-30), 0.125, 4.0))
        n_tau = int(np.ceil((t1 - t0) * per_tau / (0.5 * grid.cell))) + 1
        taus = np.linspace(t0, t1, n_tau)
        lu, lv = np.meshgrid(np.arange(du / 2, w, du), np.arange(du / 2, h, du))
        inside = grown[lv.astype(int).clip(0, h - 1), lu.astype(int).clip(0, w - 1)]
        lu, lv = lu[inside], lv[inside]
        per_chunk = max(1, chunk // n_tau)
        for s in range(0, len(lu), per_chunk):
            check_stop(should_stop)
            cu = np.repeat(lu[s : s + per_chunk], n_tau)
            cv = np.repeat(lv[s : s + per_chunk], n_tau)
            ct = np.tile(taus, len(lu[s : s + per_chunk]))
            pts, _ = family.evaluate(cu, cv, ct)
            idx = np.rint(grid.to_index(pts)).astype(np.int64)
            ok = ((idx >= 0) & (idx < grid.shape)).all(axis=1)
            idx = idx[ok]
            claimed[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    near, around = straight_claims(grid, cam, mask, should_stop=should_stop)
    core = claimed | near
    return core, (_dilate(claimed) | around) & ~core


# Samples per side of the pixel lattice, and per guide stage, that locate the part of a
# stage inside a grid's box.
WINDOW_LATTICE = 17
WINDOW_TAUS = 65


def _stage_window(grid, family, j, w, h):
    """The tau interval of guide stage j (tau in [j, j + 1]) whose curves come within
    reach of ``grid``'s box, or None: the part of the stage worth splatting. A lattice of
    the whole image's curves is tested against the box grown by the lattice's own
    spacing, so no curve between lattice points is missed.

    Returns
    -------
    (t0, t1) floats or None.
    """
    lu, lv = np.meshgrid(np.linspace(0, w, WINDOW_LATTICE), np.linspace(0, h, WINDOW_LATTICE))
    taus = np.linspace(j, j + 1, WINDOW_TAUS)
    n = lu.size
    pts, _ = family.evaluate(
        np.repeat(lu.ravel(), len(taus)), np.repeat(lv.ravel(), len(taus)), np.tile(taus, n)
    )
    pts = pts.reshape(WINDOW_LATTICE, WINDOW_LATTICE, len(taus), 3)
    # the largest gap between neighbouring lattice points, at each tau
    across_u = np.linalg.norm(np.diff(pts, axis=1), axis=-1).max(axis=(0, 1))
    across_v = np.linalg.norm(np.diff(pts, axis=0), axis=-1).max(axis=(0, 1))
    along = np.linalg.norm(np.diff(pts, axis=2), axis=-1).max(axis=(0, 1))
    gap = np.maximum(across_u, across_v)
    gap[1:] = np.maximum(gap[1:], along)
    gap[:-1] = np.maximum(gap[:-1], along)
    lo, hi = grid.bounds
    reach = (gap + grid.cell)[None, None, :, None]
    near = ((pts >= lo - reach) & (pts <= hi + reach)).all(axis=-1).any(axis=(0, 1))
    if not near.any():
        return None
    hits = np.flatnonzero(near)
    first, last = max(hits[0] - 1, 0), min(hits[-1] + 1, len(taus) - 1)
    return float(taus[first]), float(taus[last])


def _square_dilations(mask, levels):
    """Masks dilated by squares of half-width 2**k pixels, k = 0 .. levels - 1.

    Returns
    -------
    (levels, H, W) bool.
    """
    out = [mask]
    for k in range(levels):
        r = 1 if k == 0 else 2 ** (k - 1)
        a = out[-1].copy()
        b = a.copy()
        b[:, r:] |= a[:, :-r]
        b[:, :-r] |= a[:, r:]
        c = b.copy()
        c[r:] |= b[:-r]
        c[:-r] |= b[r:]
        out.append(c)
    return np.stack(out[1:])


# Mask dilations go up to 2**(levels - 1) pixels; a voxel wider than that in the image
# is coarser than any mask detail anyway.
DILATION_LEVELS = 10


def straight_claims(grid, cam, mask, chunk=1 << 18, should_stop=None):
    """Voxels within a voxel's reach of camera i's preserved rays beyond its near plane.

    Each voxel centre is projected into camera i; beyond the near plane it is a core
    claim when the mask, dilated by half a voxel seen from the camera (in pixels), holds
    its pixel, and a halo claim when the mask dilated by the voxel's half-diagonal does.
    Exact for the straight part of the family, with no sampling.

    should_stop : callable () -> bool or None, asked between chunks of voxels.

    Returns
    -------
    core, halo : (nx, ny, nz) bool, disjoint.
    """
    h, w = mask.shape
    dil = _square_dilations(mask, DILATION_LEVELS)
    px_world = cam.image_affine[0]  # view-plane width of one pixel at unit distance
    core = np.zeros(grid.size, dtype=bool)
    halo = np.zeros(grid.size, dtype=bool)
    centres = grid.centres(flat=True)
    for s in range(0, grid.size, chunk):
        check_stop(should_stop)
        pts = centres[s : s + chunk]
        pix, depth = cam.project(pts)
        front = depth >= cam.clip_start
        radius = np.sqrt(3.0) * grid.cell / (np.maximum(depth, 1e-30) * px_world)
        level = np.clip(np.ceil(np.log2(np.maximum(radius, 1.0))), 0, DILATION_LEVELS - 1).astype(
            int
        )
        inner = np.clip(
            np.ceil(np.log2(np.maximum(radius / np.sqrt(12.0), 1.0))), 0, DILATION_LEVELS - 1
        )
        inner = inner.astype(int)
        reach = 2.0**level
        x, y = pix[:, 0], pix[:, 1]
        near = front & (x > -reach) & (x < w + reach) & (y > -reach) & (y < h + reach)
        xi = np.clip(x, 0, w - 1).astype(int)
        yi = np.clip(y, 0, h - 1).astype(int)
        sel = np.flatnonzero(near)
        in_core = np.zeros(len(pts), dtype=bool)
        in_halo = np.zeros(len(pts), dtype=bool)
        in_core[sel] = dil[inner[sel], yi[sel], xi[sel]]
        in_halo[sel] = dil[level[sel], yi[sel], xi[sel]] & ~in_core[sel]
        core[s : s + chunk] = in_core
        halo[s : s + chunk] = in_halo
    return core.reshape(grid.shape), halo.reshape(grid.shape)


@dataclass(frozen=True)
class Fill:
    """The constraint field M of eq. 4.

    values : (nx, ny, nz) float32, camera number (1-based) where constrained, else 0.
    constrained : (nx, ny, nz) bool. conflicts : int, voxels that preserved rays of two
    cameras pass through (left free). per_camera : tuple of int, core voxels each camera
    keeps. overlaps : (N, N) int64, voxels preserved rays of both i and j pass through.
    cores, halos : tuple of (nx, ny, nz) bool, each camera's core and halo voxels
    (``splat_camera``), which a later fill on the same grid may take (``known``).
    """

    values: np.ndarray
    constrained: np.ndarray
    conflicts: int
    per_camera: tuple
    overlaps: np.ndarray
    cores: tuple = ()
    halos: tuple = ()

    @property
    def conflict_mask(self):
        """(nx, ny, nz) bool: voxels two cameras' cores claim."""
        return np.sum(self.cores, axis=0) > 1 if self.cores else np.zeros_like(self.constrained)

    def overlaps_in(self, region):
        """(N, N) int64: ``overlaps`` counted inside ``region`` ((nx, ny, nz) bool) only."""
        n = len(self.cores)
        out = np.zeros((n, n), dtype=np.int64)
        for i in range(n):
            for j in range(i + 1, n):
                out[i, j] = out[j, i] = int((self.cores[i] & self.cores[j] & region).sum())
        return out


def fill_membership(rig, grid, families, should_stop=None, known=None):
    """Eq. 4: M = i along the preserved rays of camera i; shared voxels stay free.

    ``should_stop``: callable () -> bool or None, asked as each camera's rays are
    splatted (raises Cancelled). ``known``: None, or a sequence with, per camera, None
    or its (core, halo) already splatted on this grid (a camera whose family and mask
    are unchanged since an earlier fill: ``methods.reuse``), taken instead of splatting.

    Each camera claims the voxels its preserved rays pass through (core) and a
    one-voxel halo around them. A core claim outranks another camera's halo, so where
    two preserved tubes come within a voxel of each other both keep their own rays'
    voxels; only voxels that two cores claim, or two halos, are left free."""
    cores = np.zeros(grid.shape, dtype=np.uint8)
    halos = np.zeros(grid.shape, dtype=np.uint8)
    core_of = np.zeros(grid.shape, dtype=np.float32)
    halo_of = np.zeros(grid.shape, dtype=np.float32)
    per, around = [], []
    for i, fam in enumerate(families):
        claims = known[i] if known is not None else None
        if claims is None:
            claims = splat_camera(grid, fam, rig.masks[i], should_stop=should_stop)
            check_stop(should_stop)
        core, halo = claims
        around.append(halo)
        cores += core
        halos += halo
        core_of[core] = i + 1
        halo_of[halo] = i + 1
        per.append(core)
    # a preserved ray's own voxel outranks another camera's halo; two cores on one voxel
    # contradict each other and leave it free, as do two halos
    by_core = cores == 1
    by_halo = (cores == 0) & (halos == 1)
    constrained = by_core | by_halo
    values = np.where(by_core, core_of, np.where(by_halo, halo_of, 0.0)).astype(np.float32)
    n = len(per)
    overlaps = np.zeros((n, n), dtype=np.int64)
    for i in range(n):
        for j in range(i + 1, n):
            overlaps[i, j] = overlaps[j, i] = int((per[i] & per[j]).sum())
    return Fill(
        values,
        constrained,
        int((cores > 1).sum()),
        tuple(int((c & constrained).sum()) for c in per),
        overlaps,
        tuple(per),
        tuple(around),
    )
