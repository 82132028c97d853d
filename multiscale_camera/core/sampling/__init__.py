"""From a built ray field to what the renderer casts: each ray simplified to a few
straight segments within a tolerance in pixels (``simplification``), rays at continuous
image positions with stratified, filtered sub-pixel samples (``sampler``), and a coarse
occupancy grid of the scene's triangles that marks segments in empty space so they are
never cast (``occupancy``). Built on ``geometry``; it reads a field only through its
rays.
"""

from .clipping import clip_far, far_planes, last_segments, ray_ends, reach_to_far_planes
from .occupancy import Occupancy
from .sampler import PixelRays, RaySampler, blackman_harris_inverse, sample_offsets
from .simplification import (
    DEFAULT_TOLERANCE_PX,
    Segments,
    box_distance,
    camera_footprints,
    footprint,
    greedy_keep,
    in_chunks,
    polyline_measures,
    segments_from_points,
    simplify,
)

__all__ = [
    "DEFAULT_TOLERANCE_PX",
    "Occupancy",
    "PixelRays",
    "RaySampler",
    "Segments",
    "blackman_harris_inverse",
    "box_distance",
    "camera_footprints",
    "clip_far",
    "far_planes",
    "footprint",
    "greedy_keep",
    "in_chunks",
    "last_segments",
    "polyline_measures",
    "ray_ends",
    "reach_to_far_planes",
    "sample_offsets",
    "segments_from_points",
    "simplify",
]
