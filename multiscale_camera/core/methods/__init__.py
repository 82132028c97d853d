"""The ray-generation methods, the top stage of the core: each builds a ``RayField`` once
from a rig and its settings, and the field then hands out ray bundles for any set of
pixels. ``base`` holds the settings, quality presets and the field's base class;
``image_blend``, ``linear``, ``vector_field`` and ``scalar_field`` one method each
(``traced`` the adaptive lattice that the two field methods trace on); ``registry``
names them, with AUTO, and ``prepare`` builds one by name; ``shot`` chooses AUTO's one
method for a rig in motion's whole shot; ``fingerprint`` keys a built field by
everything it depends on. Built on every other stage of the core.
"""

from .base import QUALITY, RayField, Settings, guard_warnings, settings_for
from .fingerprint import field_key
from .image_blend import CurveBlendField, prepare_image_blend
from .linear import LinearField, nearest_mask_pixels, prepare_linear
from .registry import METHODS, prepare, prepare_auto
from .reuse import FrameReuse, family_digest, masks_digest, solve_phrase
from .scalar_field import frame_levels, plan_shot, prepare_scalar_field
from .shot import MAX_SAMPLED, ShotChoice, choose_shot_method, sample_frames
from .traced import (
    MAX_STRIDE,
    TracedField,
    capped_message,
    field_grid,
    lattice_stride,
    trace_field,
)
from .vector_field import (
    VectorFieldTracer,
    constraint_tangents,
    prepare_vector_field,
    unit_tangents,
)

__all__ = [
    "MAX_SAMPLED",
    "ShotChoice",
    "choose_shot_method",
    "masks_digest",
    "sample_frames",
    "FrameReuse",
    "frame_levels",
    "plan_shot",
    "family_digest",
    "solve_phrase",
    "MAX_STRIDE",
    "METHODS",
    "QUALITY",
    "CurveBlendField",
    "LinearField",
    "RayField",
    "Settings",
    "TracedField",
    "VectorFieldTracer",
    "capped_message",
    "constraint_tangents",
    "field_grid",
    "field_key",
    "guard_warnings",
    "lattice_stride",
    "nearest_mask_pixels",
    "prepare",
    "prepare_auto",
    "prepare_image_blend",
    "prepare_linear",
    "prepare_scalar_field",
    "prepare_vector_field",
    "settings_for",
    "trace_field",
    "unit_tangents",
]
