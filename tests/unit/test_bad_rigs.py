"""Degenerate rigs in the core: a camera transform that cannot give rays is refused with
its own message; a camera with nothing to measure is reported unmeasured (null figures
and a reason) while the field builds; the report is strict JSON."""

import dataclasses
import json

import numpy as np
import pytest

from fixtures.masks import disk
from fixtures.rigs import camera, look_at, three_camera_rig, two_camera_rig
from multiscale_camera.core.errors import RigError
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import Settings, prepare
from multiscale_camera.core.quality import build_report, headline, readable, to_json
from multiscale_camera.core.quality.metrics import Preserved

SETTINGS = Settings(2.0, 32**3)
FIX = "Object Properties > Transform (and its parents' transforms)"


def posed(matrix, **kw):
    base = camera("Cam", (0, -10, 5), (0, 0, 0), 32, 24)
    return dataclasses.replace(base, matrix_world=matrix, **kw)


def scaled(scale):
    m = look_at((0, -10, 5), (0, 0, 0))
    m[:3, :3] = m[:3, :3] * np.asarray(scale, dtype=float)
    return m


def test_zero_scale_camera_is_refused():
    with pytest.raises(RigError) as info:
        posed(scaled((0, 0, 0)))
    assert str(info.value) == (
        "Camera 'Cam' has a scale of zero on an axis (world scale (0, 0, 0)): give it a "
        f"non-zero scale, 1 is best, in {FIX}"
    )
    with pytest.raises(RigError, match=r"scale of zero on an axis \(world scale \(1, 0, 1\)\)"):
        posed(scaled((1, 0, 1)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_infinite_camera_location_is_refused(bad):
    m = look_at((0, -10, 5), (0, 0, 0))
    m[0, 3] = bad
    with pytest.raises(RigError) as info:
        posed(m)
    assert str(info.value) == (
        "Camera 'Cam' has a location, rotation or scale that is not a number (NaN or "
        f"infinite): set its transform again in {FIX}"
    )


def test_mirrored_camera_negative_scale_is_refused():
    with pytest.raises(RigError) as info:
        posed(scaled((-1, 1, 1)))
    assert str(info.value) == (
        "Camera 'Cam' is mirrored (a negative scale, its own or a parent's): its image "
        f"would be flipped; make every scale positive in {FIX}"
    )
    # two negative axes are a rotation, not a mirror: the camera is good
    ok = posed(scaled((-1, -1, 1)))
    assert np.isfinite(ok.directions(np.array([3.5]), np.array([4.5]))).all()


def test_sheared_camera_is_refused():
    m = look_at((0, -10, 5), (0, 0, 0))
    shear = np.eye(4)
    shear[0, 1] = 0.5
    with pytest.raises(RigError, match="Camera 'Cam' is sheared"):
        posed(shear @ m)


def test_uniformly_scaled_camera_gives_the_rays_of_the_unscaled_one():
    plain = posed(scaled((1, 1, 1)))
    big = posed(scaled((3, 3, 3)))
    px, py = np.array([0.5, 10.25, 31.5]), np.array([0.5, 7.0, 23.5])
    np.testing.assert_allclose(big.directions(px, py), plain.directions(px, py), atol=1e-12)


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("lens", 0.0, "Camera 'Cam' has lens that is not a positive number"),
        ("clip_start", float("nan"), "Camera 'Cam' has clip_start that is not a positive"),
        ("clip_end", 0.5, "Camera 'Cam' has Clip End (0.5) not beyond Clip Start (1)"),
        ("clip_end", float("nan"), "Camera 'Cam' has clip_end that is not a positive"),
        ("clip_start", float("inf"), "Camera 'Cam' has clip_start that is not a positive"),
    ],
)
def test_camera_with_impossible_lens_figures_is_refused(field, value, message):
    with pytest.raises(RigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        posed(look_at((0, -10, 5), (0, 0, 0)), **{field: value})


def test_unbounded_clip_end_is_a_camera_that_sees_forever():
    """clip_end = inf is the core's unbounded camera (its measures run 1000 near-plane
    distances out), not an impossible lens figure."""
    cam = posed(look_at((0, -10, 5), (0, 0, 0)), clip_end=float("inf"))
    assert cam.clip_end == float("inf")


def three_with_middle(mask):
    cams, masks = three_camera_rig(48, 27)
    masks = masks.copy()
    masks[1] = mask
    masks[0] &= ~mask
    masks[2] &= ~mask
    return Rig(cams, masks)


def assert_strict_json(report):
    text = to_json(report)
    json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the report"))
    return json.loads(text)


@pytest.mark.parametrize(
    "name, pixels, reason",
    [
        ("empty middle mask", [], "its mask is empty: no preserved pixel to measure"),
        (
            "few-pixel middle mask",
            [(10, 20), (11, 20), (12, 21)],
            "its mask keeps no pixel once eroded by 2 px for measuring (too small or too "
            "thin at this render size); its pixels render, unmeasured",
        ),
    ],
)
@pytest.mark.parametrize("method", ["IMAGE_BLEND", "SCALAR_FIELD"])
def test_camera_with_no_measurable_pixel_is_reported_unmeasured(name, pixels, reason, method):
    mask = np.zeros((27, 48), bool)
    for y, x in pixels:
        mask[y, x] = True
    rig = three_with_middle(mask)
    fld = prepare(rig, method, SETTINGS)
    report = assert_strict_json(build_report(fld, "PREVIEW"))
    mid = report["cameras"][1]
    null = {"p50": None, "p95": None, "max": None}
    assert mid == {
        "name": "C2",
        "pixels": 0,
        "preserved_px": null,
        "angle_deg": null,
        "unmeasured": reason,
    }
    assert report["cameras"][2]["pixels"] > 0 and report["cameras"][2]["preserved_px"]["p95"] >= 0
    assert headline(report).endswith(", 1 camera(s) not measured")
    assert f"'C2': not measured: {reason}" in readable(report)
    # the field still renders every pixel of the few-pixel mask
    iy, ix = np.nonzero(mask)
    if len(ix):
        assert np.isfinite(fld.rays(ix, iy).vertices).all()


def test_rays_of_no_pixels_are_an_empty_bundle():
    cams, masks = two_camera_rig(32, 24)
    for method in ("IMAGE_BLEND", "SCALAR_FIELD", "LINEAR"):
        bundle = prepare(Rig(cams, masks), method, SETTINGS).rays(
            np.zeros(0, int), np.zeros(0, int)
        )
        assert bundle.vertices.shape[0] == 0, method


def test_all_white_last_mask_leaves_the_first_camera_unmeasured():
    cams, _ = two_camera_rig(32, 24)
    masks = np.stack([np.zeros((24, 32), bool), np.ones((24, 32), bool)])
    report = assert_strict_json(
        build_report(prepare(Rig(cams, masks), "IMAGE_BLEND", SETTINGS), "PREVIEW")
    )
    assert report["cameras"][0]["unmeasured"] == "its mask is empty: no preserved pixel to measure"
    assert report["cameras"][1]["pixels"] == (24 - 4) * (32 - 4)


def test_rays_that_never_cross_the_near_plane_are_null_with_a_reason():
    pres = Preserved(4, np.array([0.1, 0.2, np.nan, 0.3]), np.array([1.0, 2.0, np.nan, 3.0]))
    err, angle = pres.summary()
    assert err == {"p50": 0.25, "p95": None, "max": None}
    assert angle["p50"] == 2.5 and angle["max"] is None
    assert pres.unmeasured() == 1


def test_report_json_has_no_nan_or_infinity():
    report = {"a": float("nan"), "b": [np.float32(np.inf), 1.5], "c": {"d": -np.inf}}
    assert json.loads(to_json(report)) == {"a": None, "b": [None, 1.5], "c": {"d": None}}


def test_identical_cameras_do_not_crash_the_measure():
    cams, masks = two_camera_rig(32, 24)
    twin = dataclasses.replace(cams[0], name="C1 twin")
    masks = np.stack([~disk(32, 24, 6), disk(32, 24, 6)])
    rig = Rig((cams[0], twin), masks)
    try:
        fld = prepare(rig, "IMAGE_BLEND", SETTINGS)
    except RigError as err:  # refusing is the core's own error, with a message
        assert str(err)
        return
    assert_strict_json(build_report(fld, "PREVIEW"))
