"""What a build is measured and checked by: the metrics of a field's rays (preserved
error, folded quads, where they bend), the build report of the report schema, and the
checks of a rig that explain before a build what would go wrong and what to change,
among them the peak memory a build and a render would take (``memory``, shapes in,
bytes out). Built on ``geometry`` and ``field``; it measures any ray field through its ``rays``
alone, so it needs none of the methods.
"""

from .folds import quad_folds, section_points
from .memory import (
    MB,
    MemoryEstimate,
    budget_message,
    build_memory,
    estimate_memory,
    render_memory,
    size_text,
)
from .metrics import (
    ERODE_PX,
    MAX_MEASURED,
    UNBOUNDED_NEAR_DISTANCES,
    Preserved,
    along_ray,
    bending_active,
    erode,
    far_depth,
    measured_pixels,
    preserved_error,
)
from .report import build_report, fold_map, headline, measure, readable, to_json
from .validate import (
    MAX_TURN_DEG,
    bending_paths,
    check_rig,
    conflict_messages,
    crossing_messages,
    empty_mask_messages,
    guard_message,
    guard_messages,
    guard_pairs,
    obstruction_messages,
    preflight,
    sample_pixels,
    turn_deg,
)

__all__ = [
    "MB",
    "ERODE_PX",
    "MAX_MEASURED",
    "MAX_TURN_DEG",
    "MemoryEstimate",
    "Preserved",
    "UNBOUNDED_NEAR_DISTANCES",
    "along_ray",
    "bending_active",
    "bending_paths",
    "budget_message",
    "build_memory",
    "build_report",
    "check_rig",
    "conflict_messages",
    "crossing_messages",
    "empty_mask_messages",
    "erode",
    "estimate_memory",
    "far_depth",
    "fold_map",
    "guard_message",
    "guard_messages",
    "guard_pairs",
    "headline",
    "measure",
    "measured_pixels",
    "obstruction_messages",
    "preflight",
    "preserved_error",
    "quad_folds",
    "readable",
    "render_memory",
    "sample_pixels",
    "section_points",
    "size_text",
    "to_json",
    "turn_deg",
]
