"""SCALAR_FIELD (paper eq. 4 to 6): a membership field solved on a grid, or on nested
grids that refine toward the smaller cameras, blends exact per-camera tangent fields;
rays are its RK4 streamlines, traced on the adaptive lattice of ``traced``.
"""

import time
from types import SimpleNamespace

import numpy as np

from ..errors import Cancelled, SolverDidNotConverge
from ..field import (
    CELLS_ACROSS_NEAR_PER_PX,
    MIN_CELLS_ACROSS_NEAR,
    FieldTracer,
    NestedDomain,
    ScaleField,
    choose_grid,
    choose_levels,
    fill_membership,
    solve_levels,
    solve_membership,
)
from ..geometry import Family
from ..parallel import worker_count
from ..quality import check_rig
from .base import Settings
from .traced import TracedField, capped_message, field_grid, trace_field


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
