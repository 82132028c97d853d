"""Property-based fuzzing of the core: random rigs of 2 to 5 cameras, poses within and
outside the validity rules, random masks (empty, tiny, overlapping, touching, full),
resolutions from 4 pixels. Every build either hands out finite rays for every pixel,
with a report that is strict JSON, or raises the core's own error (RigError,
SolverDidNotConverge) with a message; nothing else.

Most rigs keep the validity rules (scales shrinking down the list, turns under 90
degrees, a last mask that shows somewhere), so most builds run to the end; about one
draw in five breaks them (any order and turn, or an empty last mask), so refusals and
warned rigs are fuzzed too. ``event`` counts both
(``--hypothesis-show-statistics``).

Two profiles (``MULTISCALE_FUZZ``): "bounded" (the default, in ``make test``: a few
small rigs) and "full" (``make fuzz``: 500 rigs per method, IMAGE_BLEND up to 256
pixels a side and SCALAR_FIELD, whose grid and trace cost grows with the image, up to
128, both at PREVIEW); ``MULTISCALE_FUZZ_EXAMPLES`` sets another number of rigs.
"""

import json
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from fixtures.rigs import camera, orbit
from multiscale_camera.core.errors import RigError, SolverDidNotConverge
from multiscale_camera.core.geometry import Rig, resolve_conflicts
from multiscale_camera.core.methods import prepare, settings_for
from multiscale_camera.core.quality import build_report, to_json

PROFILE = os.environ.get("MULTISCALE_FUZZ", "bounded")
# examples, largest side in pixels per method
PROFILES = {
    "bounded": (6, {"IMAGE_BLEND": 24, "SCALAR_FIELD": 24}),
    "full": (500, {"IMAGE_BLEND": 256, "SCALAR_FIELD": 128}),
}
EXAMPLES, MAX_SIDE = PROFILES[PROFILE]
EXAMPLES = int(os.environ.get("MULTISCALE_FUZZ_EXAMPLES", EXAMPLES))  # a shorter full run
settings.register_profile(
    PROFILE,
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=PROFILE == "bounded",  # the same rigs in every `make test`
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    print_blob=True,
)
MASK_KINDS = ("empty", "tiny", "disk", "rect", "full")
# Draws out of ten that keep the validity rules: the order of scales, and a last mask
# that is not empty.
VALID_OUT_OF_TEN = 9


@st.composite
def masks_of(draw, n, w, h):
    """(n, h, w) bool masks, each of a random kind, conflicts resolved as the scene's."""
    out = np.zeros((n, h, w), bool)
    for i in range(n):
        # the last camera's mask is mostly not empty: an empty one is refused at once
        last_shows = i == n - 1 and draw(st.integers(0, 9)) < VALID_OUT_OF_TEN
        kind = draw(st.sampled_from(MASK_KINDS[1:] if last_shows else MASK_KINDS))
        if kind == "tiny":
            for _ in range(draw(st.integers(1, 3))):
                out[i, draw(st.integers(0, h - 1)), draw(st.integers(0, w - 1))] = True
        elif kind == "disk":
            cx, cy = draw(st.floats(0, w)), draw(st.floats(0, h))
            r = draw(st.floats(0.5, max(w, h)))
            yy, xx = np.mgrid[0:h, 0:w] + 0.5
            out[i] = np.hypot(xx - cx, yy - cy) < r
        elif kind == "rect":
            x0, y0 = draw(st.integers(0, w - 1)), draw(st.integers(0, h - 1))
            out[i, y0 : draw(st.integers(y0 + 1, h)), x0 : draw(st.integers(x0 + 1, w))] = True
        elif kind == "full":
            out[i] = True
    masks, _said = resolve_conflicts(out, [f"C{i + 1}" for i in range(n)])
    return masks


@st.composite
def rigs(draw, max_side):
    """(cameras, masks) of a random rig, at most ``max_side`` pixels a side: mostly
    scales shrinking down the list (the validity rules), sometimes any order, turn and
    near distance."""
    n = draw(st.integers(2, 5))
    w, h = draw(st.integers(4, max_side)), draw(st.integers(4, max_side))
    ordered = draw(st.integers(0, 9)) < VALID_OUT_OF_TEN
    target = np.array([0.0, 0.0, 0.5])
    cams, dist = [], draw(st.floats(8.0, 40.0))
    for i in range(n):
        dist = dist / draw(st.floats(1.5, 4.0)) if ordered and i else draw(st.floats(0.5, 40.0))
        az = draw(st.floats(-30, 30) if ordered else st.floats(-180, 180))
        el = draw(st.floats(5, 60) if ordered else st.floats(-89, 89))
        aim = target + np.array(draw(st.tuples(*[st.floats(-0.3, 0.3)] * 3)))
        cams.append(
            camera(
                f"C{i + 1}",
                orbit(target, dist, az, el),
                aim,
                w,
                h,
                lens=draw(st.floats(18.0, 120.0)),
                clip_start=dist * draw(st.floats(0.05, 0.95)),
                clip_end=1000.0,
            )
        )
    return cams, draw(masks_of(n, w, h))


def build_or_refuse(cams, masks, method):
    """Build the field of the rig and read every pixel's rays and the report; a refusal
    must be the core's own error with a message. Returns the field or None."""
    try:
        fld = prepare(Rig(tuple(cams), masks), method, settings_for("PREVIEW"))
    except (RigError, SolverDidNotConverge) as err:
        assert str(err).strip(), f"{type(err).__name__} without a message"
        event(f"refused: {type(err).__name__}")  # --hypothesis-show-statistics counts them
        return None
    event("built")
    w, h = fld.rig.size
    iy, ix = np.mgrid[0:h, 0:w]
    bundle = fld.rays(ix.ravel(), iy.ravel())
    bad = ~np.isfinite(bundle.vertices).all(axis=(1, 2))
    assert not bad.any(), f"{int(bad.sum())} of {w * h} rays are not finite ({method})"
    json.loads(to_json(build_report(fld, "PREVIEW")))  # strict JSON: raises on NaN
    return fld


@pytest.mark.slow
@pytest.mark.parametrize("method", ["IMAGE_BLEND", "SCALAR_FIELD"])
@settings(settings.get_profile(PROFILE))
@given(data=st.data())
def test_random_rigs_build_finite_rays_or_refuse_with_a_message(method, data):
    build_or_refuse(*data.draw(rigs(MAX_SIDE[method]), label="rig"), method)


# Rigs the checks before a build see in the bounded profile: they build nothing, so many.
CHECK_EXAMPLES = {"bounded": 60, "full": 1000}[PROFILE]


@settings(settings.get_profile(PROFILE), max_examples=CHECK_EXAMPLES)
@given(data=st.data())
def test_random_rigs_pass_the_checks_before_a_build_or_refuse_with_a_message(data):
    """The checks before every build and in Check Rig (``quality.preflight``, the kept
    views that must cross among them) on random rigs up to 64 pixels a side: warnings
    that are text, or the core's own refusal with a message; each pair of kept views
    that must cross counts what it says."""
    from multiscale_camera.core.quality import crossing_entries, preflight

    cams, masks = data.draw(rigs(64), label="rig")
    try:
        rig = Rig(tuple(cams), masks)
        said = preflight(rig)
    except RigError as err:
        assert str(err).strip()
        event("refused")
        return
    assert all(isinstance(t, str) and t.strip() for t in said)
    for found in crossing_entries(rig):
        event("kept views that must cross")
        assert found.outer < found.inner
        assert 1 < found.crossing <= found.checked and 0 <= found.on_kept <= found.crossing
        assert found.clip_start is None or found.clip_start > cams[found.inner].clip_start
        pair = f"Kept rays of '{cams[found.inner].name}' and '{cams[found.outer].name}'"
        assert any(t.startswith(pair) for t in said)
