"""The paper's ray field (section 4.4, eq. 4 to 6) and its streamlines (section 4.5).

1. Grid: an axis-aligned box around camera 1's near plane and every curved ray R_i up to
   just past the last camera's near plane; the cell follows from the smallest camera's
   near-plane width and the accuracy target.
2. Fill (eq. 4): M = i on every voxel that a preserved ray of camera i passes near
   (forward splatting of R_i over camera i's mask, dilated by one voxel so that every
   trilinear lookup along a preserved ray reads only that camera's constraint).
   Voxels that two cameras claim are left free and counted.
3. Solve (eq. 5): N = the harmonic interpolation of M (``solvers.solve_membership``).
4. Tangents: X_i(x) is the unit tangent of R_i through x, found by inverting the family
   R_i(u, v, tau) with Newton's method, warm-started from the ray's previous position.
   It is exact at any point, so preserved rays do not depend on the grid resolution.
5. Blend (eq. 6): Y = sum_i w(N, i) X_i / sum_i w(N, i), w = 1 - |N - i| clipped at 0
   (or its monotone cubic smoothstep).
6. Trace: RK4 streamlines of Y from pixel seeds on camera 1's near plane, on a sparse
   pixel lattice; the rays of other pixels are interpolated from the lattice.
"""

import time
from dataclasses import dataclass

import numpy as np

from .errors import Cancelled
from .family import Family
from .grid import FieldSampler, Grid
from .guides import DEFAULT_SEGMENTS, build_guides, curved_rays
from .solvers import solve_membership
from .trace import StopReason

# Cells across the smallest camera's near plane, per pixel of accuracy asked for: the
# bundle is narrowest there, and its transitions need a few cells to be smooth.
CELLS_ACROSS_NEAR_PER_PX = 8.0
MIN_CELLS_ACROSS_NEAR = 8
# RK4 step, in cells: tangents are exact, only N is sampled, and it varies on the
# scale of a cell.
STEP_CELLS = 1.0
# A ray stalls where the blended tangents cancel to less than this length.
STALL_SPEED = 1e-3
# Newton iterations per tangent evaluation when warm-started from a point one step away.
WARM_ITERATIONS = 2
# Lattice stride bounds in pixels: one traced ray per stride x stride block, the others
# interpolated (rays bend on the scale of a cell, many pixels wide).
MAX_STRIDE = 8
# Rays traced together: bounds the memory of a chunk's polylines.
TRACE_CHUNK = 16384


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
        tail = g.points[-1] + g.directions[-1] * (0.25 * np.linalg.norm(g.points[-1] - g.points[-2], axis=-1))[:, None]
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


def _exit_distance(grid, origins, directions):
    """(P,) distance along unit ``directions`` from ``origins`` to where they leave the box."""
    lo, hi = grid.bounds
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origins) / directions
        t2 = (hi - origins) / directions
    far = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2)).min(axis=1)
    return np.maximum(far, 0.0)


def splat_camera(grid, family, mask, chunk=200_000):
    """Voxels near camera i's preserved rays (eq. 4's support for one camera).

    The family R_i is sampled over the mask at a pixel spacing and a tau spacing small
    enough that consecutive samples are at most half a cell apart; each sample marks its
    nearest voxel, and the marks are dilated by one voxel.

    Parameters
    ----------
    grid : Grid. family : Family of camera i. mask : (H, W) bool, camera i's mask.

    Returns
    -------
    (nx, ny, nz) bool.
    """
    claimed = np.zeros(grid.shape, dtype=bool)
    if not mask.any():
        return claimed
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
        t0, t1 = float(j), float(j + 1)
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
            cu = np.repeat(lu[s : s + per_chunk], n_tau)
            cv = np.repeat(lv[s : s + per_chunk], n_tau)
            ct = np.tile(taus, len(lu[s : s + per_chunk]))
            pts, _ = family.evaluate(cu, cv, ct)
            idx = np.rint(grid.to_index(pts)).astype(np.int64)
            ok = ((idx >= 0) & (idx < grid.shape)).all(axis=1)
            idx = idx[ok]
            claimed[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return _dilate(claimed) | straight_claims(grid, cam, mask)


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


def straight_claims(grid, cam, mask, chunk=1 << 20):
    """Voxels within a voxel's reach of camera i's preserved rays beyond its near plane.

    Each voxel centre is projected into camera i; it is claimed when it lies beyond the
    near plane and the mask, dilated by the voxel's half-diagonal seen from the camera
    (in pixels), holds its pixel. Exact for the straight part of the family, with no
    sampling.

    Returns
    -------
    (nx, ny, nz) bool.
    """
    h, w = mask.shape
    dil = _square_dilations(mask, DILATION_LEVELS)
    px_world = cam._affine[0]  # view-plane width of one pixel at unit distance
    out = np.zeros(grid.size, dtype=bool)
    centres = grid.centres(flat=True)
    for s in range(0, grid.size, chunk):
        pts = centres[s : s + chunk]
        pix, depth = cam.project(pts)
        front = depth >= cam.clip_start
        radius = np.sqrt(3.0) * grid.cell / (np.maximum(depth, 1e-30) * px_world)
        level = np.clip(np.ceil(np.log2(np.maximum(radius, 1.0))), 0, DILATION_LEVELS - 1).astype(int)
        reach = 2.0 ** level
        x, y = pix[:, 0], pix[:, 1]
        near = front & (x > -reach) & (x < w + reach) & (y > -reach) & (y < h + reach)
        xi = np.clip(x, 0, w - 1).astype(int)
        yi = np.clip(y, 0, h - 1).astype(int)
        hit = np.zeros(len(pts), dtype=bool)
        sel = np.flatnonzero(near)
        hit[sel] = dil[level[sel], yi[sel], xi[sel]]
        out[s : s + chunk] = hit
    return out.reshape(grid.shape)


@dataclass(frozen=True)
class Fill:
    """The constraint field M of eq. 4.

    values : (nx, ny, nz) float32, camera number (1-based) where constrained, else 0.
    constrained : (nx, ny, nz) bool. conflicts : int, voxels two cameras claimed (left free).
    per_camera : tuple of int, voxels each camera claims alone.
    """

    values: np.ndarray
    constrained: np.ndarray
    conflicts: int
    per_camera: tuple


def fill_membership(rig, grid, families):
    """Eq. 4: M = i along the preserved rays of camera i; shared voxels stay free."""
    claims = np.zeros(grid.shape, dtype=np.uint8)
    owner = np.zeros(grid.shape, dtype=np.float32)
    per = []
    for i, fam in enumerate(families):
        c = splat_camera(grid, fam, rig.masks[i])
        claims += c
        owner[c] = i + 1
        per.append(c)
    constrained = claims == 1
    values = np.where(constrained, owner, 0.0).astype(np.float32)
    return Fill(values, constrained, int((claims > 1).sum()), tuple(int((c & constrained).sum()) for c in per))


def blend_weights(nval, count, cubic=False):
    """Eq. 6's weights w(N, i) for i = 1..count.

    Parameters
    ----------
    nval : (P,) float, membership values. count : int, number of cameras.
    cubic : bool, the monotone cubic (smoothstep) variant; both sum to one between
        neighbouring cameras.

    Returns
    -------
    (count, P) float64.
    """
    i = np.arange(1, count + 1, dtype=np.float64)[:, None]
    w = np.clip(1.0 - np.abs(np.asarray(nval, dtype=np.float64)[None] - i), 0.0, 1.0)
    return w * w * (3.0 - 2.0 * w) if cubic else w


@dataclass(frozen=True)
class Traced:
    """Streamlines of a set of seeds, resampled to a common arc-length layout.

    vertices : (R, K, 3) float32: vertex k at arc length k * step from the seed; after a
        ray stops, its vertices run straight on along its last tangent.
    membership : (R, K) float32, N at each vertex.
    counts : (R,) int32, vertices actually traced (the rest are the straight run-on).
    reason : (R,) int8, ``StopReason`` values.
    step : float, world units.
    """

    vertices: np.ndarray
    membership: np.ndarray
    counts: np.ndarray
    reason: np.ndarray
    step: float


class FieldTracer:
    """Streamlines of the blended field Y (eq. 6) with exact tangents X_i.

    Parameters
    ----------
    rig : Rig. grid : Grid. membership : (nx, ny, nz) float32, the solved N.
    cubic : bool, monotone cubic blending weights.
    """

    def __init__(self, rig, grid, membership, cubic=False):
        self.rig = rig
        self.grid = grid
        self.n_of = FieldSampler(grid, membership)
        self.families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
        self.cubic = cubic
        self.tangent_seconds = 0.0

    def _tangent(self, i, x, params, rows):
        """Unit tangent X_i at points ``x`` for rays ``rows``; updates ``params[i, rows]``."""
        start = time.perf_counter()
        cam = self.rig.cameras[i]
        rel = x - cam.eye
        depth = rel @ cam.forward
        beyond = depth >= cam.clip_start
        out = np.empty_like(x)
        # on camera i's straight part the tangent is its pinhole direction
        out[beyond] = rel[beyond] / np.linalg.norm(rel[beyond], axis=-1, keepdims=True)
        bend = np.flatnonzero(~beyond)
        if len(bend):
            r = rows[bend]
            u, v, tau, _err, tangent = self.families[i].invert(
                x[bend], params[i, r, 0], params[i, r, 1], params[i, r, 2], WARM_ITERATIONS
            )
            params[i, r, 0], params[i, r, 1], params[i, r, 2] = u, v, tau
            out[bend] = tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)
        self.tangent_seconds += time.perf_counter() - start
        return out

    def velocity(self, x, params, rows):
        """Blended unit direction Y at ``x``.

        Returns
        -------
        y : (P, 3) float64 unit (zero where stalled). speed : (P,) float64, |sum w X|.
        nval : (P,) float32, N at x.
        """
        nval = self.n_of(x)
        w = blend_weights(nval, len(self.families), self.cubic)
        y = np.zeros_like(x)
        for i in range(len(self.families)):
            sel = np.flatnonzero(w[i] > 0)
            if len(sel):
                y[sel] += w[i, sel, None] * self._tangent(i, x[sel], params, rows[sel])
        speed = np.linalg.norm(y, axis=-1) / np.maximum(w.sum(0), 1e-30)
        y /= np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-30)
        return y, speed, nval

    def trace(self, u0, v0, step, max_steps, should_stop=None):
        """RK4 streamlines from the near-plane points of pixels (u0, v0) of camera 1.

        Parameters
        ----------
        u0, v0 : (R,) float pixel coordinates. step : float, world units.
        max_steps : int. should_stop : optional callable, polled between chunks.

        Returns
        -------
        Traced
        """
        parts = [self._trace_chunk(u0[s : s + TRACE_CHUNK], v0[s : s + TRACE_CHUNK], step, max_steps, should_stop)
                 for s in range(0, len(u0), TRACE_CHUNK)]
        k = max(p[0].shape[1] for p in parts)
        verts, mem = [], []
        for p in parts:
            v, m = p[0], p[1]
            if v.shape[1] < k:
                extra = k - v.shape[1]
                d = v[:, -1] - v[:, -2]
                d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-30)
                v = np.concatenate([v, v[:, -1:] + d[:, None] * (step * np.arange(1, extra + 1))[None, :, None]], axis=1)
                m = np.concatenate([m, np.repeat(m[:, -1:], extra, axis=1)], axis=1)
            verts.append(v)
            mem.append(m)
        return Traced(
            np.concatenate(verts).astype(np.float32), np.concatenate(mem).astype(np.float32),
            np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts]), step,
        )

    def _trace_chunk(self, u0, v0, step, max_steps, should_stop):
        if should_stop is not None and should_stop():
            raise Cancelled()
        r = len(u0)
        cam1 = self.rig.cameras[0]
        x = cam1.near_points(cam1.directions(u0, v0))
        params = np.zeros((len(self.families), r, 3))
        params[:, :, 0], params[:, :, 1] = u0, v0
        path = [x.copy()]
        nvals = [self.n_of(x).astype(np.float64)]
        count = np.ones(r, dtype=np.int32)
        reason = np.zeros(r, dtype=np.int8)
        last_dir = cam1.directions(u0, v0)
        active = np.arange(r)
        pos = x.copy()
        for _step in range(max_steps):
            if len(active) == 0:
                break
            p = pos[active]
            k1, s1, _ = self.velocity(p, params, active)
            k2, s2, _ = self.velocity(p + 0.5 * step * k1, params, active)
            k3, s3, _ = self.velocity(p + 0.5 * step * k2, params, active)
            k4, s4, _ = self.velocity(p + step * k3, params, active)
            new = p + (step / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
            stalled = np.minimum.reduce([s1, s2, s3, s4]) < STALL_SPEED
            left = ~self.grid.contains(new)
            moving = ~stalled
            d = new - p
            last_dir[active[moving]] = d[moving] / np.maximum(np.linalg.norm(d[moving], axis=-1, keepdims=True), 1e-30)
            pos[active[moving]] = new[moving]
            count[active[moving]] += 1
            full = pos.copy()
            path.append(full)
            nvals.append(np.full(r, np.nan))
            nvals[-1][active] = self.n_of(pos[active])
            reason[active[stalled]] = StopReason.STALLED
            reason[active[left & moving]] = StopReason.LEFT_GRID
            active = active[moving & ~left]
        reason[active] = StopReason.REACHED_LIMIT
        verts = np.stack(path, axis=1)
        mem = np.stack(nvals, axis=1)
        # after a ray stops, run straight on along its last direction at the same step
        k = np.arange(verts.shape[1])[None, :]
        after = k >= count[:, None]
        last = verts[np.arange(r), count - 1]
        run = (k - (count[:, None] - 1)) * step
        straight = last[:, None] + last_dir[:, None] * run[..., None]
        verts = np.where(after[..., None], straight, verts)
        last_m = mem[np.arange(r), count - 1]
        mem = np.where(after, last_m[:, None], mem)
        return verts, mem, count, reason
