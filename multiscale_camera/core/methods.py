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

import time
from dataclasses import dataclass, field

import numpy as np

from .bundle import RayBundle
from .errors import Cancelled, RigError, SolverDidNotConverge
from .family import Family
from .field import (
    MAX_STRIDE,
    FieldTracer,
    choose_grid,
    fill_membership,
    merge,
    near_plane_width,
    step_cells,
)
from .guides import DEFAULT_SEGMENTS, build_guides, curved_rays
from .harmonic import mask_weights
from .solvers import solve_membership
from .trace import StopReason


@dataclass(frozen=True)
class Settings:
    """What a build is asked for.

    accuracy_px : float, target preserved error in pixels.
    max_voxels : int, the grid's voxel budget.
    cubic : bool, monotone cubic blending weights (SCALAR_FIELD).
    """

    accuracy_px: float = 0.5
    max_voxels: int = 160**3
    cubic: bool = False


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
class RayField:
    """A prepared ray generator (base of every method's field).

    Attributes
    ----------
    rig : Rig. method : str, the method's enum name.
    seconds : dict stage -> float seconds ("fill", "solve", "tangents", "trace").
    solver : dict with "iterations", "residual", "converged".
    warnings : list of str, for the report and the user.
    grids : list of [nx, ny, nz].
    stats : dict of counts ("conflicts", "stalled", ...).
    """

    rig: object
    method: str
    seconds: dict = field(default_factory=dict)
    solver: dict = field(default_factory=lambda: {"iterations": 0, "residual": 0.0, "converged": True})
    warnings: list = field(default_factory=list)
    grids: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    def rays(self, ix, iy):
        """Rays for pixels ``(ix, iy)`` ((P,) int arrays, row 0 at the top): a RayBundle."""
        raise NotImplementedError

    def lattice(self):
        """Rays on the pixel lattice the method traced, for fold counting.

        Returns
        -------
        vertices : (Hy, Wx, K, 3) float32. counts : (Hy, Wx) int, vertices actually
        traced. stride : int, pixels between lattice rays.
        """
        raise NotImplementedError

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


def _lattice_axis(n, stride):
    """Lattice pixel indices 0, stride, ..., always including the last pixel n - 1."""
    return np.unique(np.append(np.arange(0, n, stride), n - 1))


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

    def lattice(self):
        w, h = self.rig.size
        stride = 1 if w * h <= 512 * 512 else 2
        ys, xs = _lattice_axis(h, stride), _lattice_axis(w, stride)
        iy, ix = np.meshgrid(ys, xs, indexing="ij")
        b = self.rays(ix.ravel(), iy.ravel())
        k = b.vertices.shape[1]
        return b.vertices.reshape(len(ys), len(xs), k, 3), np.full((len(ys), len(xs)), k), stride


def prepare_image_blend(rig, settings=None, should_stop=None):
    """IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights.

    Exact where it matters: a pixel inside camera i's mask gets R_i itself, so beyond
    camera i's near plane it is camera i's own pinhole ray. Neighbouring rays can cross
    in the transitions (folds), since nothing ties them together.
    """
    t0 = time.perf_counter()
    solve = mask_weights(rig.masks)
    fld = CurveBlendField(rig=rig, method="IMAGE_BLEND", weights=solve.x)
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
    w, h = rig.size
    cx, cy = np.meshgrid(np.linspace(0.5, w - 0.5, 9), np.linspace(0.5, h - 0.5, 9))
    shortened = build_guides(rig.cameras, cx.ravel(), cy.ravel(), rig.beta).shortened
    out = []
    for j, count in enumerate(shortened):
        if count:
            a, b = rig.cameras[j], rig.cameras[j + 1]
            out.append(
                f"Guides from '{a.name}' into '{b.name}' were shortened to keep them in front of "
                f"'{b.name}' (beta x distance between near planes exceeds its near distance "
                f"{b.clip_start:g}); move its near plane (Clip Start) farther from its eye"
            )
    return out


@dataclass
class TracedField(RayField):
    """Rays traced on a pixel lattice; other pixels' rays are interpolated bilinearly,
    vertex by vertex (vertex k of every ray lies at the same arc length).

    xs, ys : lattice pixel columns and rows. traced : field.Traced, rays in row-major
    lattice order. grid : Grid. membership : (nx, ny, nz) float32.
    """

    xs: np.ndarray = None
    ys: np.ndarray = None
    traced: object = None
    grid: object = None
    membership: np.ndarray = None

    def lattice(self):
        k = self.traced.vertices.shape[1]
        shape = (len(self.ys), len(self.xs))
        stride = int(self.xs[1] - self.xs[0]) if len(self.xs) > 1 else 1
        return self.traced.vertices.reshape(*shape, k, 3), self.traced.counts.reshape(shape), stride

    def rays(self, ix, iy):
        ix, iy = np.asarray(ix), np.asarray(iy)
        verts, mem = _interpolate_lattice(
            self.xs, self.ys, self.traced.vertices, self.traced.membership, ix, iy
        )
        return self._bundle(ix, iy, verts, mem)

    def exit_index(self, ix, iy):
        """(P,) int: for each pixel, the vertex where its ray leaves the grid (the
        smallest traced count among the lattice rays it is interpolated from)."""
        counts = self.traced.counts.reshape(len(self.ys), len(self.xs))
        ax, fx = _locate(self.xs, np.asarray(ix))
        ay, fy = _locate(self.ys, np.asarray(iy))
        c = np.minimum.reduce([counts[ay, ax], counts[ay, ax + 1], counts[ay + 1, ax], counts[ay + 1, ax + 1]])
        return c - 1


def _locate(axis, values):
    """Lattice cell index and fraction of integer pixel ``values`` along a lattice axis."""
    if len(axis) == 1:
        return np.zeros(len(values), dtype=np.int64), np.zeros(len(values))
    a = np.clip(np.searchsorted(axis, values, side="right") - 1, 0, len(axis) - 2)
    f = (values - axis[a]) / (axis[a + 1] - axis[a])
    return a, f


def _interpolate_lattice(xs, ys, vertices, membership, ix, iy):
    """Bilinear interpolation of lattice polylines at pixels (ix, iy).

    Returns
    -------
    vertices : (P, K, 3) float32. membership : (P, K) float32.
    """
    nx = len(xs)
    ax, fx = _locate(xs, ix)
    ay, fy = _locate(ys, iy)
    if len(xs) == 1:
        ax1 = ax
    else:
        ax1 = ax + 1
    ay1 = ay + 1 if len(ys) > 1 else ay
    fx = fx.astype(np.float32)[:, None]
    fy = fy.astype(np.float32)[:, None]
    corners = ((ay, ax, (1 - fy) * (1 - fx)), (ay, ax1, (1 - fy) * fx), (ay1, ax, fy * (1 - fx)), (ay1, ax1, fy * fx))
    verts = np.zeros((len(ix), vertices.shape[1], 3), dtype=np.float32)
    mem = np.zeros((len(ix), vertices.shape[1]), dtype=np.float32)
    for cy, cx, w in corners:
        row = cy * nx + cx
        verts += vertices[row] * w[:, :, None]
        mem += membership[row] * w
    return verts, mem


def lattice_stride(rig, grid):
    """Pixels between traced rays: half the smallest camera's pixels per cell, so every
    cell the rays cross is seen by two lattice rays, clamped to 1 .. MAX_STRIDE."""
    cams = rig.cameras
    w = rig.size[0]
    px = min(near_plane_width(c) / w for c in cams)
    return int(np.clip(grid.cell / px / 2, 1, MAX_STRIDE))


def prepare_scalar_field(rig, settings=None, should_stop=None):
    """SCALAR_FIELD (paper eq. 4 to 6): a membership field solved on a grid blends
    exact per-camera tangent fields; rays are its RK4 streamlines."""
    settings = settings or Settings()
    fld = TracedField(rig=rig, method="SCALAR_FIELD")
    t0 = time.perf_counter()
    choice = choose_grid(rig, settings.accuracy_px, settings.max_voxels)
    grid = choice.grid
    if choice.capped:
        fld.warnings.append(
            f"The accuracy target of {settings.accuracy_px:g} px wants {choice.wanted_cell:.3g}-unit "
            f"cells; the voxel budget allows {grid.cell:.3g}: transitions near the smallest "
            "camera may be coarser than asked (raise the quality, or move that camera's near "
            "plane farther from its eye)"
        )
    families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
    fill = fill_membership(rig, grid, families)
    t1 = time.perf_counter()
    if should_stop is not None and should_stop():
        raise Cancelled()
    solve = solve_membership(fill.values, fill.constrained)
    t2 = time.perf_counter()
    if not solve.converged:
        raise SolverDidNotConverge(
            f"The membership solve stopped at relative residual {solve.residuals[-1]:.2e} after "
            f"{solve.iterations} iterations; simplify the masks or lower the quality"
        )
    tracer = FieldTracer(rig, grid, solve.x, cubic=settings.cubic)
    w, h = rig.size
    stride = lattice_stride(rig, grid)
    xs, ys = _lattice_axis(w, stride), _lattice_axis(h, stride)
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    cells = step_cells(settings.accuracy_px)
    step = cells * grid.cell
    max_steps = int(np.ceil(np.linalg.norm(np.array(grid.shape)) / cells * 2)) + 8
    traced = _trace_lattice(tracer, rig, gx.ravel(), gy.ravel(), step, max_steps, should_stop)
    t3 = time.perf_counter()
    fld.xs, fld.ys, fld.traced, fld.grid, fld.membership = xs, ys, traced, grid, solve.x
    fld.grids.append(list(grid.shape))
    fld.seconds.update(
        fill=t1 - t0, solve=t2 - t1, tangents=tracer.tangent_seconds, trace=t3 - t2 - tracer.tangent_seconds
    )
    fld.solver.update(iterations=solve.iterations, residual=float(solve.residuals[-1]) if solve.residuals else 0.0,
                      converged=bool(solve.converged))
    fld.stats.update(
        conflicts=fill.conflicts,
        stalled=int((traced.reason == StopReason.STALLED).sum()),
        unfinished=int((traced.reason == StopReason.REACHED_LIMIT).sum()),
        stride=stride,
        cell=grid.cell,
    )
    if fill.conflicts:
        fld.warnings.append(
            f"{fill.conflicts} voxels lie on preserved rays of two cameras and were left free: "
            "the masks contradict each other there (widen the gap between them, or move a near plane)"
        )
    fld.warnings += guard_warnings(rig)
    return fld


def _trace_lattice(tracer, rig, ix, iy, step, max_steps, should_stop):
    """Lattice rays: analytic R_i where a preserved pixel's ray stays in camera i's
    constraint, RK4 streamlines for the rest (the transitions)."""
    u, v = ix + 0.5, iy + 0.5
    todo = np.ones(len(ix), dtype=bool)
    parts, order = [], []
    vertices = max_steps + 1
    for i in range(len(rig.cameras)):
        sel = np.flatnonzero(rig.masks[i][iy, ix])
        if len(sel) == 0:
            continue
        ok, exact = tracer.preserved_rays(i, u[sel], v[sel], step, vertices)
        parts.append(exact)
        order.append(sel[ok])
        todo[sel[ok]] = False
    rest = np.flatnonzero(todo)
    if len(rest):
        parts.append(tracer.trace(u[rest], v[rest], step, max_steps, should_stop))
        order.append(rest)
    return merge(parts, order, len(ix))


METHODS = {"IMAGE_BLEND": prepare_image_blend, "SCALAR_FIELD": prepare_scalar_field}
# AUTO picks the cheapest method that meets the accuracy target on this rig; until that
# choice is measured per rig, the most accurate method.
AUTO_CHOICE = "SCALAR_FIELD"


def prepare(rig, method, settings=None, should_stop=None):
    """Prepare the ray field of ``method`` (an enum name of DESIGN.md) for ``rig``."""
    try:
        builder = METHODS[AUTO_CHOICE if method == "AUTO" else method]
    except KeyError:
        raise RigError(
            f"Method '{method}' is not available in this version; use one of: " + ", ".join(METHODS)
        ) from None
    return builder(rig, settings or Settings(), should_stop)
