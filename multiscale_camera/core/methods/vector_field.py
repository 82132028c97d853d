"""VECTOR_FIELD (section 4.4, eq. 3), one of the paper's two weaker ray-generation
methods, kept to compare the field method against (the other is ``linear``): the unit
tangents of the preserved rays are smoothed directly into a vector field whose RK4
streamlines are the rays. Away from small masks the field copies the tangents at their
boundary, so rays there leave the cameras' perspective projections (the paper's
Figure 7).
"""

import numpy as np

from ..diagnostics import check_stop, diagnostics_of
from ..errors import SolverDidNotConverge
from ..field import (
    FieldSampler,
    FieldTracer,
    Traced,
    fill_membership,
    solve_membership,
)
from ..geometry import Family, dot3
from ..quality import check_rig
from .base import Settings, record_seconds
from .traced import TracedField, field_grid, trace_field

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
    (P, 3) float64, unit. lost : int, points Newton missed (``Family.solve``), whose
    tangent is camera 1's direction.
    """
    first, cam = family.cameras[0], family.cameras[-1]
    straight = dot3(points - cam.eye, cam.forward) >= cam.clip_start
    eye = np.where(straight[:, None], cam.eye, first.eye)
    out = points - eye
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    bend = np.flatnonzero(~straight & (dot3(points - first.eye, first.forward) >= first.clip_start))
    lost = 0
    if len(bend):
        pts = points[bend]
        u, v, tau = family.start(pts)
        _u, _v, _tau, out[bend], lost = family.solve(pts, u, v, tau, INVERT_ITERATIONS)
    return out, lost


def constraint_tangents(grid, families, fill, should_stop=None):
    """The constraint field X of eq. 2 on the voxels of ``fill`` (eq. 4's support).

    Each voxel that camera i's preserved rays claim alone holds the unit tangent of R_i
    through its centre, exact at any grid resolution; voxels two cameras claim are free.
    ``should_stop`` (callable () -> bool or None) is asked before each chunk of
    ``TANGENT_CHUNK`` voxels.

    Returns
    -------
    (nx, ny, nz, 3) float32, zero off the constraints. lost : (N,) int, per camera the
    voxels whose tangent Newton missed (camera 1's direction stands in).

    Raises
    ------
    Cancelled when ``should_stop`` says so.
    """
    out = np.zeros((*grid.shape, 3), dtype=np.float32)
    flat = out.reshape(-1, 3)
    owner = fill.values.ravel()
    lost = np.zeros(len(families), dtype=np.int64)
    for i, fam in enumerate(families):
        idx = np.flatnonzero(owner == i + 1)
        for s in range(0, len(idx), TANGENT_CHUNK):
            check_stop(should_stop)
            sel = idx[s : s + TANGENT_CHUNK]
            pts = grid.origin + grid.cell * np.stack(np.unravel_index(sel, grid.shape), axis=-1)
            flat[sel], missed = unit_tangents(fam, pts)
            lost[i] += missed
    return out, lost


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

    exact_preserved = False

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


def prepare_vector_field(rig, settings=None, diag=None):
    """VECTOR_FIELD (paper eq. 3): the unit tangents X of the preserved rays, fixed on the
    voxels they pass (the hard-constraint limit of eq. 3's |X|^2 weights), are smoothed
    component by component into Y (``solve_membership``); rays are Y's RK4 streamlines
    from camera 1's near-plane pixels, traced on SCALAR_FIELD's grid and adaptive lattice.

    The Membership pass samples the scalar membership N of SCALAR_FIELD, solved on the
    same constraints (one more solve): Y itself carries no camera numbers. ``diag``
    (core.diagnostics.Diagnostics or None) steers the build and gets its seconds.
    """
    settings = settings or Settings()
    diag = diagnostics_of(diag)
    run = diag.child()
    fld = TracedField(rig=rig, method="VECTOR_FIELD")
    fld.warnings += check_rig(rig)
    with run.stage("fill"):
        grid = fld.grid = field_grid(fld, settings)
        families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
        fill = fill_membership(rig, grid, families)
    with run.stage("tangents"):
        tangents, lost = constraint_tangents(grid, families, fill, run.should_stop)
    solves = []
    with run.stage("solve"):
        for values in (fill.values, tangents[..., 0], tangents[..., 1], tangents[..., 2]):
            run.check()
            solves.append(solve_membership(values, fill.constrained, should_stop=run.should_stop))
    del tangents
    for s in solves:
        if not s.converged:
            raise SolverDidNotConverge(
                f"A vector field solve stopped at relative residual {s.residuals[-1]:.2e} after "
                f"{s.iterations} iterations; simplify the masks or lower the quality"
            )
    fld.membership = solves[0].x
    field = np.stack([s.x for s in solves[1:]], axis=-1)
    tracer = VectorFieldTracer(rig, grid, solves[0].x, field, settings.processes)
    with run.stage("trace"):
        trace_field(fld, tracer, fill, settings, run)
    record_seconds(fld, run.seconds)
    fld.stats["newton_lost"] = fld.stats.get("newton_lost", 0) + int(lost.sum())
    fld.warnings += [
        f"Newton's inversion of camera '{cam.name}''s curved rays failed at {n} constraint "
        f"voxels: there the field holds camera '{rig.cameras[0].name}''s direction instead"
        for cam, n in zip(rig.cameras, lost.tolist())
        if n
    ]
    fld.solver.update(
        iterations=max(s.iterations for s in solves),
        residual=max((s.residuals[-1] for s in solves if s.residuals), default=0.0),
        converged=True,
    )
    diag.merge(run)
    return fld
