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
from ..quality import (
    crossing_entries,
    crossing_message,
    kept_folds,
    measure_map,
    transition_folds,
)
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


# AUTO's target for the worst preserved ray, as a multiple of the accuracy target (which
# the p95 must meet): 2 px at STANDARD's 0.5 px.
MAX_OVER_TARGET = 4.0
# AUTO's candidates, cheapest first: IMAGE_BLEND has no 3D grid; SCALAR_FIELD (the
# paper's method, nested grids past about 10x) is the one whose transitions are
# streamlines, which do not cross. LINEAR folds wherever a transition has more than one
# nearest preserved pixel and VECTOR_FIELD's preserved rays drift (docs/methods.md).
AUTO_CANDIDATES = ("IMAGE_BLEND", "SCALAR_FIELD")
# AUTO's word on a rig in motion whose shot was not measured (its frames could not be
# stepped: ``Settings.shot`` None).
UNMEASURED_SHOT = (
    "SCALAR_FIELD: the rig moves and a shot keeps one method; the shot's frames were not "
    "measured for IMAGE_BLEND"
)


def shortfall(cameras, folds, accuracy_px):
    """Why a field's measured rays miss AUTO's target, or "" when they meet it.

    The target: every camera's preserved error along the ray (docs/report.md) at p95 no
    more than ``accuracy_px`` and at worst ``MAX_OVER_TARGET`` times that, and no fold.

    Parameters
    ----------
    cameras : list of dict, the report's "cameras" entries (``quality.measure``).
    folds : int. accuracy_px : float.

    Returns
    -------
    str, the misses joined by "; " (camera names and figures), or "".
    """
    out = accuracy_misses(cameras, accuracy_px)
    if folds:
        out.append(f"{folds} folded quads")
    return "; ".join(out)


def accuracy_misses(cameras, accuracy_px):
    """``shortfall``'s misses of accuracy alone: a list of str, one per camera."""
    worst = MAX_OVER_TARGET * accuracy_px
    out = []
    for cam in cameras:
        if not cam["pixels"]:
            continue  # nothing to keep exact (an empty or thin mask)
        p95, top = cam["preserved_px"]["p95"], cam["preserved_px"]["max"]
        if p95 is None or top is None:
            out.append(f"camera '{cam['name']}' has rays that never reach its near plane")
        elif p95 > accuracy_px or top > worst:
            out.append(
                f"camera '{cam['name']}' p95 {p95:.2f} px, max {top:.2f} px "
                f"(target {accuracy_px:g} and {worst:g})"
            )
    return out


def not_measured(cameras):
    """What AUTO's word adds for the cameras it could not measure (``cameras``: the
    report's entries; those with no measured pixel carry an "unmeasured" reason):
    "; not measured, so not held to the target: camera 'X' (why), ...", or "" when
    every camera was measured. The target then holds on the others alone."""
    out = [f"camera '{c['name']}' ({c['unmeasured']})" for c in cameras if not c["pixels"]]
    return "; not measured, so not held to the target: " + ", ".join(out) if out else ""


# AUTO's word on a candidate whose only folds lie where masks touch (``seam_folds``).
AT_SEAMS = "lie where masks touch, and every method's rays fold there"


def seam_folds(rig, fold_quads, stride):
    """The pairs of cameras whose masks touch where every folded quad of ``fold_quads``
    lies (``quality.kept_folds``: every method's rays fold there), or None where a fold
    lies elsewhere (or there is none). ``fold_quads`` : ``fold_map``'s bool map, on the
    lattice of ``stride``. Returns list of (str, str), or None."""
    folds = int(fold_quads.sum())
    if not folds:
        return None
    fixed, pairs = kept_folds(rig.masks, fold_quads, stride, [cam.name for cam in rig.cameras])
    return pairs if fixed == folds else None


def seams_text(pairs):
    """ "'A' and 'B', ..." of the camera pairs whose masks touch ("one camera": none)."""
    return ", ".join(f"'{a}' and '{b}'" for a, b in pairs) or "one camera"


def seam_message(folds, pairs):
    """The warning for folds no method avoids (``seam_folds``): ``folds`` int, ``pairs``
    the (str, str) cameras whose masks touch there."""
    seams = seams_text(pairs)
    return (
        f"{folds} folded quads lie where the masks of {seams} touch, with no transition "
        "between them: the rays there are those cameras' own with every method, so they "
        "cross whatever is built. Leave a gap between the masks (erase one of them "
        "there) for the rays to turn in."
    )


def transition_message(pairs, names):
    """The warning for IMAGE_BLEND's folds in transitions, its cameras exact: ``pairs``
    ``quality.transition_folds``' list, ``names`` the rig's cameras. What to change
    comes early: the panel shows a warning's first four lines."""
    folds = sum(count for _pair, count in pairs)
    where = ", ".join(f"'{a}'-'{b}' {c}" for (a, b), c in pairs)
    inner = [f"'{b}'" for b in sorted({b for (_a, b), _c in pairs}, key=names.index)]
    return (
        f"{folds} quads fold in the transitions ({where}), every camera exact: raise the "
        f"Clip Start of {' and '.join(inner)} (nearer the subject), widen the gaps between "
        "their masks or turn the cameras less (docs/failures.md)."
    )


def least_miss(kept):
    """The field that misses AUTO's target least among ``kept``, a list of (folds,
    cameras off the target, rank among the candidates, field): a fold-free one first (a
    fold is a tear in the picture); among those that all fold, the one with the fewest
    cameras off the target, then the fewest folds, then the cheapest. The masks say
    what the artist asked to keep: where every candidate tears somewhere, the one that
    keeps the cameras exact is kept (on a rig turned 41 and 50 degrees, IMAGE_BLEND
    with every camera exact rather than SCALAR_FIELD with two cameras 6 px off, both
    folding: docs/architecture.md, "Where IMAGE_BLEND folds")."""
    *_, fld = min(kept, key=lambda k: (k[0] > 0, k[1], k[0], k[2]))
    return fld


def prepare_auto(rig, settings=None, diag=None, reuse=None):
    """AUTO: the cheapest method whose rays meet the accuracy target on this rig.

    Each candidate of ``AUTO_CANDIDATES`` is built, cheapest first, and measured as the
    report measures it (``quality.measure``: preserved error along the whole ray for
    every camera, exact folds); the first whose rays meet the target (``shortfall``) is
    kept. IMAGE_BLEND's preserved rays are its cameras' curves by construction, so it
    misses only where its transition rays fold (the turned rig) or a preserved ray goes
    wrong. Folds that every method would have (``quality.kept_folds``: quads across a
    seam where masks touch) send it no further: its rays are kept and a warning names the
    cameras. When no candidate meets the target, the one that misses it least is kept
    (``least_miss``: a fold-free one, else the fewest cameras off the target, then the
    fewest folds, then the cheapest) and the report says why; where that is IMAGE_BLEND
    with every camera exact, a warning names its folding transitions and what to change
    (``transition_message``). A camera with no pixel to measure (an empty mask, or one
    too thin once eroded: ``quality.unmeasured_camera``) is held to nothing, and the word
    names it. The choice and why are in ``stats["auto"]``; the measurement stays with
    the field (``measured``), so the report does not measure it again.

    A rig in motion (``settings.steady``) keeps one method for the whole shot (a choice
    measured frame by frame could switch it mid-shot): the one ``settings.shot`` holds
    (``shot.choose_shot_method``, made once per shot from a few of its frames), else
    SCALAR_FIELD; either is built with ``reuse`` (``reuse.FrameReuse`` or None).

    Before a candidate after the first, ``diag.guard`` (when set) is asked with its
    name: the memory guard estimates AUTO's first candidate before the build, and this
    one here, refusing it (a ``RigError``) when it would not fit.
    """
    settings = settings or Settings()
    diag = diagnostics_of(diag)
    if settings.steady:
        choice = settings.shot
        if choice is not None and choice.method == "IMAGE_BLEND":
            out = prepare_image_blend(rig, settings, diag, reuse)
        else:
            out = prepare_scalar_field(rig, settings, diag, reuse)
        out.stats["auto"] = choice.why if choice is not None else UNMEASURED_SHOT
        return out
    misses, kept, maps = [], [], {}
    names = [cam.name for cam in rig.cameras]
    for n, name in enumerate(AUTO_CANDIDATES):
        if n:
            diag.check()
            if diag.guard is not None:  # the memory guard estimated the first alone
                diag.guard(name)
        fld = METHODS[name](rig, settings, diag)
        cameras, fold_quads, stride = measure_map(fld, settings.processes, diag)
        folds = int(fold_quads.sum())
        fld.measured = (cameras, folds)
        off = accuracy_misses(cameras, settings.accuracy_px)
        target = (
            f"p95 <= {settings.accuracy_px:g} px, max <= "
            f"{MAX_OVER_TARGET * settings.accuracy_px:g} px along every preserved ray"
        )
        tried = "".join(f"; {m}" for m in misses) + not_measured(cameras)
        if not off and not folds:
            fld.stats["auto"] = (
                f"{name}: the cheapest method whose rays meet the target ({target}, no "
                f"fold) on this rig{tried}"
            )
            return fld
        pairs = None if off else seam_folds(rig, fold_quads, stride)
        if pairs is not None:  # no other method can do better: say so, keep this one
            fld.stats["auto"] = (
                f"{name}: the cheapest method whose rays meet the target ({target}); "
                f"its {folds} folded quads {AT_SEAMS}{tried}"
            )
            fld.warnings.append(seam_message(folds, pairs))
            return fld
        crossing = [] if off or n + 1 == len(AUTO_CANDIDATES) else crossing_entries(rig)
        if crossing:  # every method folds here: the exact cameras, at once
            return _kept_crossing(fld, rig, crossing, fold_quads, target, tried)
        misses.append(f"{name} would miss it: {shortfall(cameras, folds, settings.accuracy_px)}")
        kept.append((folds, len(off), n, fld))
        maps[name] = fold_quads
    # none meets it: the one that misses least (``least_miss``)
    fld = least_miss(kept)
    name = fld.method
    fld.stats["auto"] = f"{name}: no method meets the target on this rig; " + "; ".join(misses)
    fld.warnings.append(
        f"No method meets the accuracy target on this rig ({'; '.join(misses)}); "
        f"{name} is used, the one that misses it least. Move the masks' edges apart or "
        "turn the cameras less."
    )
    cameras, folds = fld.measured
    if name == "IMAGE_BLEND" and folds and not accuracy_misses(cameras, settings.accuracy_px):
        turns = transition_folds(fld.weights, rig.masks, maps[name], names)
        if turns:
            fld.warnings.append(transition_message(turns, names))
    return fld


def _kept_crossing(fld, rig, crossing, fold_quads, target, tried):
    """AUTO's field on a rig whose kept views must cross (``quality.crossing_entries``):
    ``fld``, every camera on the target and its rays folding, is kept without building
    the candidates after it, which fold there too (docs/architecture.md, "Kept views
    that must cross"); its word and warnings say which cameras and what to change."""
    names = [cam.name for cam in rig.cameras]
    folds = int(fold_quads.sum())
    pairs = "; ".join(f"'{names[e.inner]}' and '{names[e.outer]}'" for e in crossing)
    fld.stats["auto"] = (
        f"{fld.method}: no method can meet the target on this rig: the kept rays of "
        f"{pairs} must cross, so every method's rays fold between them; {fld.method} meets it "
        f"otherwise ({target}) with {folds} folded quads, and the methods after it were "
        f"not built{tried}"
    )
    fld.warnings += [crossing_message(e, rig.cameras) for e in crossing]
    if fld.method == "IMAGE_BLEND":
        turns = transition_folds(fld.weights, rig.masks, fold_quads, names)
        if turns:
            fld.warnings.append(transition_message(turns, names))
    return fld


METHODS["AUTO"] = prepare_auto


def prepare(rig, method, settings=None, diag=None, reuse=None):
    """Prepare the ray field of ``method`` (the enum name of ``scene.multiscale.method``)
    for ``rig``, steered by ``diag`` (core.diagnostics.Diagnostics or None). ``reuse``
    (``reuse.FrameReuse`` or None): what SCALAR_FIELD and IMAGE_BLEND may take from
    earlier builds of a sequence, and keep for the next (AUTO on a rig in motion too;
    other methods build from scratch)."""
    try:
        builder = METHODS[method]
    except KeyError:
        raise RigError(
            f"Method '{method}' is not available in this version; use one of: " + ", ".join(METHODS)
        ) from None
    if builder in (prepare_scalar_field, prepare_image_blend, prepare_auto):
        return builder(rig, settings or Settings(), diag, reuse)
    return builder(rig, settings or Settings(), diag)
