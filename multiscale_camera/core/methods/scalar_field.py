"""SCALAR_FIELD (paper eq. 4 to 6): a membership field solved on a grid, or on nested
grids that refine toward the smaller cameras, blends exact per-camera tangent fields;
rays are its RK4 streamlines, traced on the adaptive lattice of ``traced``.
"""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from ..diagnostics import diagnostics_of
from ..errors import SolverDidNotConverge
from ..field import (
    CELLS_ACROSS_NEAR_PER_PX,
    MIN_CELLS_ACROSS_NEAR,
    FieldTracer,
    NestedDomain,
    ScaleField,
    choose_grid,
    choose_levels,
    fill_membership,
    shot_layout,
    solve_levels,
    solve_membership,
    steady_levels,
)
from ..geometry import Family
from ..quality import check_rig
from ..runtime import worker_count
from .base import Settings, record_seconds
from .traced import TracedField, capped_message, field_grid, trace_field


def prepare_scalar_field(rig, settings=None, diag=None, reuse=None):
    """SCALAR_FIELD (paper eq. 4 to 6): a membership field solved on a grid blends
    exact per-camera tangent fields; rays are its RK4 streamlines. ``diag``
    (core.diagnostics.Diagnostics or None) steers the build and gets its seconds.
    ``reuse`` (``reuse.FrameReuse`` or None): claims and solutions of earlier builds on
    the same grids to take (a sequence's frames), and where this build's are kept."""
    settings = settings or Settings()
    diag = diagnostics_of(diag)
    if _nested(rig, settings):
        return _prepare_nested(rig, settings, diag, reuse)
    run = diag.child()
    fld = TracedField(rig=rig, method="SCALAR_FIELD")
    fld.warnings += check_rig(rig)
    with run.stage("fill"):
        fld.grid = field_grid(fld, settings)
        known, warm = _reusable(reuse, rig, (fld.grid,), settings)
        families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
        fill = fill_membership(rig, fld.grid, families, should_stop=run.should_stop, known=known[0])
    run.check()
    with run.stage("solve"):
        solve = solve_membership(
            fill.values, fill.constrained, x0=warm[0], should_stop=run.should_stop
        )
    if not solve.converged:
        raise SolverDidNotConverge(
            f"The membership solve stopped at relative residual {solve.residuals[-1]:.2e} after "
            f"{solve.iterations} iterations; simplify the masks or lower the quality"
        )
    fld.membership = solve.x
    _keep(reuse, rig, (fld.grid,), (fill,), (solve.x,), settings)
    with run.stage("trace"):
        tracer = FieldTracer(
            rig, fld.grid, solve.x, cubic=settings.cubic, processes=settings.processes
        )
        trace_field(fld, tracer, fill, settings, run)
    _record_trace_seconds(fld, run, tracer)
    fld.solver.update(
        iterations=solve.iterations,
        residual=float(solve.residuals[-1]) if solve.residuals else 0.0,
        converged=bool(solve.converged),
    )
    _record(reuse, fld, rig, known, warm)
    diag.merge(run)
    return fld


def _nested(rig, settings):
    """Whether SCALAR_FIELD builds ``rig`` on nested grids: as the shot's layout is
    (``settings.layout``), else as ``settings.nested`` says, or (None) where one
    uniform grid within the budget cannot have the cells the target asks for."""
    if settings.layout is not None:
        return settings.layout.nested
    nested = settings.nested
    if nested is None:
        nested = choose_grid(rig, settings.accuracy_px, settings.max_voxels).capped
    return bool(nested and len(rig.cameras) > 1)


def _cells_across(settings):
    return max(MIN_CELLS_ACROSS_NEAR, CELLS_ACROSS_NEAR_PER_PX / settings.accuracy_px)


def frame_levels(rig, settings):
    """``nested.choose_levels`` for ``rig`` alone, its outer box from ``choose_grid``."""
    outer = choose_grid(rig, settings.accuracy_px, 1 << 62).grid
    return choose_levels(
        rig, settings.accuracy_px, settings.max_voxels, _cells_across(settings), outer.bounds
    )


def plan_shot(rigs, settings):
    """The layout of a shot whose frames have the rigs ``rigs`` (same cameras and size,
    one rig per frame): SCALAR_FIELD's grids for every frame at once (``field.layout``).
    Nested when any frame needs nested grids (``settings.nested`` None) or as
    ``settings.nested`` says; the boxes are the union of the frames', the cell the
    finest any frame asks for, within ``settings.max_voxels``.

    Returns
    -------
    field.ShotLayout
    """
    plain = replace(settings, layout=None)
    nested = any(_nested(rig, plain) for rig in rigs)
    if nested:
        frames = [frame_levels(rig, settings).grids for rig in rigs]
    else:
        frames = [
            (choose_grid(rig, settings.accuracy_px, settings.max_voxels).grid,) for rig in rigs
        ]
    return shot_layout(frames, nested, settings.max_voxels)


def _reusable(reuse, rig, grids, settings):
    """(known claims, warm starts) per grid from ``reuse`` (Nones without it)."""
    if reuse is None:
        return [None] * len(grids), [None] * len(grids)
    return reuse.known(rig, grids), reuse.warm(grids, repr(settings))


def _keep(reuse, rig, grids, fills, fields, settings):
    if reuse is not None:
        reuse.keep(rig, grids, fills, fields, repr(settings))


def _record(reuse, fld, rig, known, warm):
    """What the build took and built, in ``fld.stats["reuse"]`` (with ``reuse``)."""
    if reuse is not None:
        names = [c.name for c in rig.cameras]
        fld.stats["reuse"] = reuse.record(names, known, warm, fld.seconds)


def _record_trace_seconds(fld, run, tracer):
    """The build's seconds on ``fld``: the tracer's tangent evaluations apart from the
    rest of the trace."""
    tangents = tracer.tangent_seconds
    record_seconds(fld, dict(run.seconds, tangents=tangents, trace=run.seconds["trace"] - tangents))


def _prepare_nested(rig, settings, diag, reuse=None):
    """SCALAR_FIELD on nested grids (``nested``): the same equations, with cells that
    shrink with the bundle toward the smaller cameras. Fill and solve interleave level
    by level: both count as "fill", and "solve" holds none."""
    run = diag.child()
    fld = TracedField(rig=rig, method="SCALAR_FIELD")
    fld.warnings += check_rig(rig)
    with run.stage("fill"):
        across = _cells_across(settings)
        levels = frame_levels(rig, settings)
        if levels.capped:
            fld.warnings.append(capped_message(settings, levels.wanted_cell, levels.grids[-1].cell))
        grids = _level_grids(fld, levels.grids, settings)
        known, warm = _reusable(reuse, rig, grids, settings)
        families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
        workers = worker_count(settings.processes)
        solved = solve_levels(
            rig, grids, families, fill_membership, run.should_stop, workers, known, warm
        )
    if not solved.converged:
        raise SolverDidNotConverge(
            f"The membership solve stopped at relative residual {solved.residual:.2e} after "
            f"{solved.iterations} iterations; simplify the masks or lower the quality"
        )
    fld.grid, fld.membership = grids[0], solved.fields[0]
    _keep(reuse, rig, grids, solved.fills, solved.fields, settings)
    with run.stage("trace"):
        domain = fld.domain = NestedDomain(grids, solved.fields, ScaleField(rig.cameras), across)
        tracer = FieldTracer(
            rig,
            fld.grid,
            fld.membership,
            cubic=settings.cubic,
            domain=domain,
            processes=settings.processes,
        )
        fill = _composite_fill(grids, solved.fills)
        trace_field(fld, tracer, fill, settings, run, levels=grids)
    _record_trace_seconds(fld, run, tracer)
    fld.solver.update(
        iterations=solved.iterations, residual=solved.residual, converged=solved.converged
    )
    _record(reuse, fld, rig, known, warm)
    diag.merge(run)
    return fld


def _level_grids(fld, own, settings):
    """The levels a nested build uses: the shot's (``settings.layout``) where they hold
    the frame's own levels ``own``, else ``own`` laid on the world lattice within the
    budget when ``settings.steady``, else ``own``; ``fld.stats["layout"]`` says which."""
    layout = settings.layout
    if layout is not None and layout.nested and layout.covers(own):
        fld.stats["layout"] = "shot"
        return layout.grids
    if settings.steady:
        fld.stats["layout"] = "frame"
        return steady_levels(own, settings.max_voxels)
    return own


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
