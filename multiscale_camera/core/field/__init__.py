"""The paper's ray field (section 4.4, eq. 4 to 6) and its streamlines (section 4.5):
a grid around the bending stretch of the rig's rays, the membership constraint M filled
along each camera's preserved rays (``fill``), its harmonic interpolation N by
multigrid-preconditioned conjugate gradients (``solvers``; ``harmonic`` solves the same
equation over the image for IMAGE_BLEND's weights), nested grids that refine toward the
smaller cameras (``nested``), RK4 streamlines of a vector field (``trace``) and the
tracer of the blended tangent field Y (``tracer``). Built on ``geometry``.
"""

from .fill import (
    CELLS_ACROSS_NEAR_PER_PX,
    MIN_CELLS_ACROSS_NEAR,
    Fill,
    GridChoice,
    choose_grid,
    fill_membership,
    near_plane_width,
    splat_camera,
    straight_claims,
)
from .grid import FieldSampler, Grid, sample
from .harmonic import mask_weights, solve_workers
from .layout import (
    SNAP_CELLS,
    ShotLayout,
    ladder_cell,
    shot_layout,
    steady_boxes,
    steady_grid,
    steady_levels,
)
from .nested import (
    BAND_CELLS,
    Levels,
    LevelSolve,
    NestedDomain,
    ScaleField,
    bundle_profile,
    choose_levels,
    solve_levels,
)
from .plane_step import NearPlaneStep
from .preserved_rays import arc_length_rays, scheduled_rays
from .solvers import (
    ISOLATED_VALUE,
    SolveResult,
    apply_laplacian,
    explicit_diffusion,
    isolated_voxels,
    solve_membership,
)
from .trace import (
    MIDPOINT,
    RK4,
    StopReason,
    Streamlines,
    Tableau,
    Traced,
    merge,
    rk4_streamlines,
    run_on,
)
from .tracer import (
    STEP_CELLS,
    STEP_WIDTH_GAIN,
    FieldTracer,
    blend_weights,
    step_cells,
)

__all__ = [
    "BAND_CELLS",
    "CELLS_ACROSS_NEAR_PER_PX",
    "ISOLATED_VALUE",
    "MIDPOINT",
    "MIN_CELLS_ACROSS_NEAR",
    "RK4",
    "SNAP_CELLS",
    "STEP_CELLS",
    "STEP_WIDTH_GAIN",
    "ShotLayout",
    "FieldSampler",
    "FieldTracer",
    "Fill",
    "Grid",
    "GridChoice",
    "LevelSolve",
    "Levels",
    "NestedDomain",
    "ScaleField",
    "SolveResult",
    "StopReason",
    "Streamlines",
    "Tableau",
    "Traced",
    "apply_laplacian",
    "NearPlaneStep",
    "arc_length_rays",
    "blend_weights",
    "bundle_profile",
    "choose_grid",
    "choose_levels",
    "explicit_diffusion",
    "fill_membership",
    "isolated_voxels",
    "ladder_cell",
    "mask_weights",
    "merge",
    "near_plane_width",
    "rk4_streamlines",
    "run_on",
    "sample",
    "scheduled_rays",
    "solve_levels",
    "solve_membership",
    "solve_workers",
    "shot_layout",
    "steady_boxes",
    "steady_grid",
    "steady_levels",
    "splat_camera",
    "step_cells",
    "straight_claims",
]
