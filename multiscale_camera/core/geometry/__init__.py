"""Geometry of the camera rig: the pinhole cameras and their chain with masks, the
Bezier guides between consecutive cameras (paper eq. 1), the ray families R_i they
define and their inverses, the ray bundle the core hands to the renderer, and the
row-wise vector helpers everything else builds on. The bottom stage: it imports no
other part of the core but its errors.
"""

from .bundle import RayBundle
from .camera import SENSOR_FITS, PinholeCamera, pixel_centres
from .crossing import near_plane_entries, near_plane_entries_on_planes
from .family import Family
from .guides import (
    DEFAULT_SEGMENTS,
    GUARD_FRACTION,
    Guides,
    bezier,
    blended_planes,
    build_guides,
    curve_planes,
    curved_rays,
)
from .rig import Rig, resolve_conflicts
from .vectors import cross3, dot3, solve3

__all__ = [
    "DEFAULT_SEGMENTS",
    "GUARD_FRACTION",
    "SENSOR_FITS",
    "Family",
    "Guides",
    "PinholeCamera",
    "RayBundle",
    "Rig",
    "bezier",
    "blended_planes",
    "build_guides",
    "cross3",
    "curve_planes",
    "curved_rays",
    "dot3",
    "near_plane_entries",
    "near_plane_entries_on_planes",
    "pixel_centres",
    "resolve_conflicts",
    "solve3",
]
