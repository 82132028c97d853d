"""The ray-generation methods by name, and AUTO, which picks the cheapest that meets the
accuracy target on a rig.

- IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights.
- LINEAR: the paper's strawman, a transition pixel's ray interpolates linearly between
  the rays of the nearest preserved pixels of two cameras.
- VECTOR_FIELD: eq. 3, the tangents of preserved rays smoothed directly into a field.
- SCALAR_FIELD: eq. 4 to 6, a smoothed membership blends exact tangent fields.

Each method is one function ``prepare_<method>(rig, settings, diag=None)`` that builds
a ``RayField`` once; ``diag`` (core.diagnostics.Diagnostics) steers it (cancel) and
gets its seconds per stage.
"""

from ..diagnostics import diagnostics_of
from ..errors import RigError
from ..quality import fold_map
from .base import Settings
from .image_blend import prepare_image_blend
from .linear import prepare_linear
from .scalar_field import prepare_scalar_field
from .vector_field import prepare_vector_field

METHODS = {
    "IMAGE_BLEND": prepare_image_blend,
    "LINEAR": prepare_linear,
    "VECTOR_FIELD": prepare_vector_field,
    "SCALAR_FIELD": prepare_scalar_field,
}


def prepare_auto(rig, settings=None, diag=None, reuse=None):
    """AUTO: the cheapest method that meets the accuracy target on this rig.

    IMAGE_BLEND is the cheapest (no 3D grid) and its preserved rays are exact by
    construction, so it meets any target unless its transition rays fold; its folds
    are counted on the rays it would render, and where there are any, SCALAR_FIELD is
    built (on nested grids where one uniform grid cannot hold the cells the target asks
    for). LINEAR folds wherever a transition has more than one nearest preserved pixel,
    and VECTOR_FIELD's preserved rays drift (docs/methods.md), so neither is a candidate.
    The choice and why are in ``stats["auto"]``.

    A rig in motion (``settings.steady``) gets SCALAR_FIELD at every frame: one method
    for the whole shot (IMAGE_BLEND's folds, counted frame by frame, could switch it
    mid-shot), built with ``reuse`` (``reuse.FrameReuse`` or None) as SCALAR_FIELD is.
    """
    diag = diagnostics_of(diag)
    settings = settings or Settings()
    if settings.steady:
        out = prepare_scalar_field(rig, settings, diag, reuse)
        out.stats["auto"] = "SCALAR_FIELD: the rig moves, and a shot keeps one method"
        return out
    fld = prepare_image_blend(rig, settings, diag)
    folds = int(fold_map(fld)[0].sum())
    if folds == 0:
        fld.stats["auto"] = "IMAGE_BLEND: its rays do not fold on this rig"
        return fld
    diag.check()
    out = prepare_scalar_field(rig, settings, diag)
    out.stats["auto"] = f"SCALAR_FIELD: IMAGE_BLEND would fold {folds} quads on this rig"
    return out


METHODS["AUTO"] = prepare_auto


def prepare(rig, method, settings=None, diag=None, reuse=None):
    """Prepare the ray field of ``method`` (the enum name of ``scene.multiscale.method``)
    for ``rig``, steered by ``diag`` (core.diagnostics.Diagnostics or None). ``reuse``
    (``reuse.FrameReuse`` or None): what SCALAR_FIELD may take from earlier builds of a
    sequence, and keeps for the next (AUTO on a rig in motion too; other methods build
    from scratch)."""
    try:
        builder = METHODS[method]
    except KeyError:
        raise RigError(
            f"Method '{method}' is not available in this version; use one of: " + ", ".join(METHODS)
        ) from None
    if builder in (prepare_scalar_field, prepare_auto):
        return builder(rig, settings or Settings(), diag, reuse)
    return builder(rig, settings or Settings(), diag)
