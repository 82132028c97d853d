"""Direct volume rendering along bent rays (paper section 5.2): a scalar volume and the
lookup tables of each camera's transfer function (``source``), the volume prepared for a
frame with its empty-space structures (``scene``), the segment stage that tests every
ray's segments against the occupied blocks (``runs``), and the front-to-back march that
blends the cameras' tables by eq. 6's weights along each ray (``march``). Pure numpy; it
reads a field's rays as plain arrays and needs no other stage but the errors.
"""

from .march import (
    EARLY_TERMINATION,
    SHADE_AMBIENT,
    VolumeResult,
    composite_over,
    march_volume,
)
from .scene import (
    BLOCK,
    MIN_DIRECTION,
    MIN_GRADIENT,
    VolumeScene,
    block_ranges,
    camera_runs,
    corrected_tables,
    gradient_directions,
    occupancy_bits,
    occupancy_sums,
    occupied_blocks,
    run_grids,
)
from .source import (
    DEFAULT_POINTS,
    TABLE_SIZE,
    ScalarVolume,
    box_to_index,
    default_table,
    normalise,
    table_from_points,
)

__all__ = [
    "BLOCK",
    "DEFAULT_POINTS",
    "EARLY_TERMINATION",
    "MIN_DIRECTION",
    "MIN_GRADIENT",
    "SHADE_AMBIENT",
    "TABLE_SIZE",
    "ScalarVolume",
    "VolumeResult",
    "VolumeScene",
    "block_ranges",
    "box_to_index",
    "camera_runs",
    "composite_over",
    "corrected_tables",
    "default_table",
    "gradient_directions",
    "march_volume",
    "normalise",
    "occupancy_bits",
    "occupancy_sums",
    "occupied_blocks",
    "run_grids",
    "table_from_points",
]
