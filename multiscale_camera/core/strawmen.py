"""The paper's two weaker ray-generation methods, kept to compare the field method against.

- LINEAR (section 3, "Ray intersection"): a pixel in camera i's mask gets its curve R_i;
  a transition pixel gets the linear interpolation, vertex by vertex, of the curves of
  the nearest preserved pixels of the two nearest masks. Nothing keeps neighbouring
  rays apart: where the nearest preserved pixel jumps (along the pixel steps of a mask's
  edge, and between the sectors of its nearest-pixel map), neighbouring pixels follow
  curves bent by different amounts, and they cross (fold).
- VECTOR_FIELD (section 4.4, eq. 3): the unit tangents of the preserved rays are smoothed
  directly into a vector field whose RK4 streamlines are the rays. Away from small masks
  the field copies the tangents at their boundary, so rays there leave the cameras'
  perspective projections (the paper's Figure 7).
"""

import time
from dataclasses import dataclass

import numpy as np

from .errors import Cancelled, SolverDidNotConverge
from .field import FieldSampler, FieldTracer, Traced, fill_membership, solve_membership
from .geometry import DEFAULT_SEGMENTS, Family, build_guides, curved_rays, dot3
from .methods import (
    RayField,
    Settings,
    TracedField,
    field_grid,
    guard_warnings,
    trace_field,
)
from .quality import check_rig

# --- LINEAR ----------------------------------------------------------------------------

_FAR = np.iinfo(np.int32).max  # squared pixel distance standing for "no mask pixel yet"


def _shifted(a, dy, dx, fill):
    """``a`` read at (y + dy, x + dx); ``fill`` where that lies off the image."""
    h, w = a.shape[-2:]
    out = np.full_like(a, fill)
    if abs(dy) < h and abs(dx) < w:
        dst = (..., slice(max(-dy, 0), h - max(dy, 0)), slice(max(-dx, 0), w - max(dx, 0)))
        src = (..., slice(max(dy, 0), h - max(-dy, 0)), slice(max(dx, 0), w - max(-dx, 0)))
        out[dst] = a[src]
    return out


def nearest_mask_pixels(mask):
    """The nearest pixel of a mask to every pixel, by jump flooding (JFA+1).

    Each pass offers every pixel the nearest-pixel guesses of its 8 neighbours at a
    distance of k pixels, k halving from half the image size to 1, plus one more pass at
    k = 1 that mends most of jump flooding's rare misses.

    Parameters
    ----------
    mask : (H, W) bool.

    Returns
    -------
    near : (2, H, W) int32, (x, y) of the nearest mask pixel (-1 when the mask is empty).
    dist : (H, W) float64, distance to it between pixel centres, pixels (inf when empty).
    """
    h, w = mask.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.int32)
    near = np.where(mask, np.stack([xs, ys]), -1).astype(np.int32)
    best = np.where(mask, 0, _FAR).astype(np.int32)
    k = 1 << max(int(np.ceil(np.log2(max(h, w)))) - 1, 0)
    steps = []
    while k >= 1:
        steps.append(k)
        k //= 2
    for k in steps + [1]:
        for dy in (-k, 0, k):
            for dx in (-k, 0, k):
                if dy == 0 and dx == 0:
                    continue
                cand = _shifted(near, dy, dx, -1)
                d = (cand[0] - xs) ** 2 + (cand[1] - ys) ** 2
                better = (cand[0] >= 0) & (d < best)
                best = np.where(better, d, best)
                near = np.where(better, cand, near)
    dist = np.where(best < _FAR, np.sqrt(best.astype(np.float64)), np.inf)
    return near, dist


@dataclass
class LinearField(RayField):
    """Rays interpolated between two preserved curves per pixel.

    near : (2, 2, H, W) int32, for curve a and curve b the (x, y) pixel whose curve is
    taken. camera : (2, H, W) int8, the 0-based camera of curves a and b. lam : (H, W)
    float32, the weight of curve b (0 inside a mask, where a = b = the pixel's own R_i).
    """

    near: np.ndarray = None
    camera: np.ndarray = None
    lam: np.ndarray = None
    segments: int = DEFAULT_SEGMENTS

    def _curves(self, x, y, cam):
        """(P, K, 3) float64: curve R_cam of pixels (x, y)."""
        g = build_guides(self.rig.cameras, x + 0.5, y + 0.5, beta=self.rig.beta)
        return curved_rays(g, self.segments)[cam, np.arange(len(x))]

    def rays(self, ix, iy):
        ix, iy = np.asarray(ix), np.asarray(iy)
        (xa, ya), (xb, yb) = self.near[:, :, iy, ix]
        ca, cb = self.camera[:, iy, ix]
        lam = self.lam[iy, ix].astype(np.float64)
        verts = self._curves(xa, ya, ca)
        blend = np.flatnonzero(lam > 0)
        if len(blend):
            other = self._curves(xb[blend], yb[blend], cb[blend])
            verts[blend] += lam[blend, None, None] * (other - verts[blend])
        # the curves are other pixels': move each ray to start at its own pixel's point
        # on camera 1's near plane (no move inside a mask)
        cam = self.rig.cameras[0]
        start = cam.near_points(cam.directions(ix + 0.5, iy + 0.5))
        verts += (start - verts[:, 0])[:, None]
        m = (1.0 - lam) * (ca + 1) + lam * (cb + 1)
        return self._bundle(ix, iy, verts, np.repeat(m[:, None], verts.shape[1], axis=1))


def prepare_linear(rig, settings=None, should_stop=None):
    """LINEAR: a transition pixel p takes the curves R_a(q_a) and R_b(q_b) of q_a and q_b,
    its nearest preserved pixels in the two nearest masks (cameras a and b), blended
    vertex by vertex with weight lambda = d_a / (d_a + d_b) on R_b (d: distances to the
    masks, pixels), and moved to start at p's own point on camera 1's near plane: the
    paper's "ray direction interpolation". Where p lies on the segment q_a q_b (across a
    band or ring of transition) the blend starts there anyway, up to the rounding of q_a
    and q_b to pixels. Its membership is (1 - lambda) a + lambda b. Where only one mask is
    painted, transition pixels take the curve of its nearest pixel. No grid is built.
    """
    fld = LinearField(rig=rig, method="LINEAR")
    fld.warnings += check_rig(rig)
    t0 = time.perf_counter()
    n = len(rig.cameras)
    near = np.empty((n, 2, *rig.masks.shape[1:]), dtype=np.int32)
    dist = np.empty(rig.masks.shape)
    for i, mask in enumerate(rig.masks):
        if should_stop is not None and should_stop():
            raise Cancelled()
        near[i], dist[i] = nearest_mask_pixels(mask)
    order = np.argsort(dist, axis=0, kind="stable")[:2]
    if n == 1 or not np.isfinite(np.take_along_axis(dist, order[1:], axis=0)).any():
        order = np.concatenate([order[:1], order[:1]])  # one painted mask: b = a
    d_a, d_b = np.take_along_axis(dist, order, axis=0)
    with np.errstate(invalid="ignore"):
        lam = np.where((d_a > 0) & (order[1] != order[0]), d_a / (d_a + d_b), 0.0)
    fld.near = np.stack([np.take_along_axis(near, o[None, None], axis=0)[0] for o in order])
    fld.camera, fld.lam = order.astype(np.int8), lam.astype(np.float32)
    fld.seconds.update(fill=time.perf_counter() - t0, solve=0.0, tangents=0.0, trace=0.0)
    fld.stats.update(conflicts=0, stalled=0)
    fld.warnings += guard_warnings(rig)
    return fld


# --- VECTOR_FIELD ----------------------------------------------------------------------

# Newton iterations to invert R_i at a voxel centre from a first guess.
INVERT_ITERATIONS = 8
# A voxel centre counts as found on R_i within this fraction of camera i's near distance.
INVERT_TOLERANCE = 1e-6
# Voxels inverted together: bounds the Newton temporaries (a few dozen (P, 3) arrays).
TANGENT_CHUNK = 1 << 18


def unit_tangents(family, points):
    """Unit tangents of camera i's curves R_i through world points (eq. 2's X).

    Beyond camera i's near plane, the pinhole direction of camera i; before camera 1's
    near plane, where the rays come from, camera 1's; in between, the guide tangent found
    by inverting the family from ``Family.start``'s guess (``Family.solve`` retries the
    points Newton misses from there).

    Parameters
    ----------
    family : Family. points : (P, 3) float64, world units.

    Returns
    -------
    (P, 3) float64, unit.
    """
    first, cam = family.cameras[0], family.cameras[-1]
    straight = dot3(points - cam.eye, cam.forward) >= cam.clip_start
    eye = np.where(straight[:, None], cam.eye, first.eye)
    out = points - eye
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    bend = np.flatnonzero(~straight & (dot3(points - first.eye, first.forward) >= first.clip_start))
    if len(bend):
        pts = points[bend]
        u, v, tau = family.start(pts)
        out[bend] = family.solve(pts, u, v, tau, INVERT_ITERATIONS)[3]
    return out


def constraint_tangents(grid, families, fill):
    """The constraint field X of eq. 2 on the voxels of ``fill`` (eq. 4's support).

    Each voxel that camera i's preserved rays claim alone holds the unit tangent of R_i
    through its centre, exact at any grid resolution; voxels two cameras claim are free.

    Returns
    -------
    (nx, ny, nz, 3) float32, zero off the constraints.
    """
    out = np.zeros((*grid.shape, 3), dtype=np.float32)
    flat = out.reshape(-1, 3)
    owner = fill.values.ravel()
    for i, fam in enumerate(families):
        idx = np.flatnonzero(owner == i + 1)
        for s in range(0, len(idx), TANGENT_CHUNK):
            sel = idx[s : s + TANGENT_CHUNK]
            pts = grid.origin + grid.cell * np.stack(np.unravel_index(sel, grid.shape), axis=-1)
            flat[sel] = unit_tangents(fam, pts)
    return out


class VectorFieldTracer(FieldTracer):
    """Streamlines of the smoothed vector field Y (trilinear), traced and laid out by
    ``FieldTracer.trace`` (arc-length vertices, straight run-on, steps cut at near planes).

    Parameters
    ----------
    rig : Rig. grid : Grid. membership : (nx, ny, nz) float32, N, sampled along the rays
    for the Membership pass. field : (nx, ny, nz, 3) float32, Y.
    processes : int, as ``FieldTracer``.
    """

    def __init__(self, rig, grid, membership, field, processes=1):
        super().__init__(rig, grid, membership, processes=processes)
        self.y_of = FieldSampler(grid, field)

    def velocity(self, x, rows):
        """(P, 3) float64: Y at ``x``; its length is the stall test's speed."""
        return self.y_of(x).astype(np.float64)

    def preserved_rays(self, i, u, v, step, vertices):
        """No ray is laid out analytically: Y only approximates R_i even in the masks, and
        tracing every ray keeps the method's error in sight. ``ok`` is all False."""
        empty = Traced(
            np.zeros((0, 2, 3), np.float32),
            np.zeros((0, 2), np.float32),
            np.zeros(0, np.int32),
            np.zeros(0, np.int8),
            step,
        )
        return np.zeros(len(u), dtype=bool), empty


def prepare_vector_field(rig, settings=None, should_stop=None):
    """VECTOR_FIELD (paper eq. 3): the unit tangents X of the preserved rays, fixed on the
    voxels they pass (the hard-constraint limit of eq. 3's |X|^2 weights), are smoothed
    component by component into Y (``solve_membership``); rays are Y's RK4 streamlines
    from camera 1's near-plane pixels, traced on SCALAR_FIELD's grid and adaptive lattice.

    The Membership pass samples the scalar membership N of SCALAR_FIELD, solved on the
    same constraints (one more solve): Y itself carries no camera numbers.
    """
    settings = settings or Settings()
    fld = TracedField(rig=rig, method="VECTOR_FIELD")
    fld.warnings += check_rig(rig)
    t0 = time.perf_counter()
    grid = fld.grid = field_grid(fld, settings)
    families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
    fill = fill_membership(rig, grid, families)
    t1 = time.perf_counter()
    tangents = constraint_tangents(grid, families, fill)
    t2 = time.perf_counter()
    solves = []
    for values in (fill.values, tangents[..., 0], tangents[..., 1], tangents[..., 2]):
        if should_stop is not None and should_stop():
            raise Cancelled()
        solves.append(solve_membership(values, fill.constrained, should_stop=should_stop))
    del tangents
    t3 = time.perf_counter()
    for s in solves:
        if not s.converged:
            raise SolverDidNotConverge(
                f"A vector field solve stopped at relative residual {s.residuals[-1]:.2e} after "
                f"{s.iterations} iterations; simplify the masks or lower the quality"
            )
    fld.membership = solves[0].x
    field = np.stack([s.x for s in solves[1:]], axis=-1)
    tracer = VectorFieldTracer(rig, grid, solves[0].x, field, settings.processes)
    trace_field(fld, tracer, fill, settings, should_stop)
    t4 = time.perf_counter()
    fld.seconds.update(fill=t1 - t0, tangents=t2 - t1, solve=t3 - t2, trace=t4 - t3)
    fld.solver.update(
        iterations=max(s.iterations for s in solves),
        residual=max((s.residuals[-1] for s in solves if s.residuals), default=0.0),
        converged=True,
    )
    return fld
