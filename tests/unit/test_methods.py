import numpy as np
import pytest

from fixtures.rigs import three_camera_rig, two_camera_rig, zoom1000_rig, zoom_rig
from multiscale_camera.core.errors import RigError
from multiscale_camera.core.geometry import Rig, resolve_conflicts
from multiscale_camera.core.methods import prepare, settings_for


def test_image_blend_preserves_each_cameras_pinhole_rays():
    cams, masks = two_camera_rig()
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND")
    h, w = masks.shape[1:]
    iy, ix = np.mgrid[0:h, 0:w]
    b = fld.rays(ix.ravel(), iy.ravel())
    verts = b.vertices.astype(np.float64).reshape(h, w, -1, 3)
    # camera 2's preserved pixels: the last segment is camera 2's ray through that pixel
    for cam, mask, k in ((cams[1], masks[1], -2), (cams[0], masks[0], 0)):
        ys, xs = np.nonzero(mask)
        for vertex in (k, -1):
            pix, depth = cam.project(verts[ys, xs, vertex])
            assert (depth > 0).all()
            err = np.hypot(pix[:, 0] - xs - 0.5, pix[:, 1] - ys - 0.5)
            assert err.max() < 1e-3, err.max()
    m = b.membership.reshape(h, w, -1)[..., 0]
    assert np.all(m[masks[0]] == 1) and np.all(m[masks[1]] == 2)
    free = ~masks.any(0)
    assert (m[free] > 1).any() and (m[free] < 2).all()


def test_an_unknown_method_is_explained():
    cams, masks = two_camera_rig()
    with pytest.raises(RigError, match="Method 'BOGUS' is not available in this version"):
        prepare(Rig(cams, masks), "BOGUS")


def test_rig_rejects_empty_last_mask_but_allows_empty_intermediate():
    cams, masks = two_camera_rig()
    three = (cams[0], cams[1], cams[1])
    ok = np.stack([masks[0], np.zeros_like(masks[0]), masks[1]])
    Rig(three, ok)
    with pytest.raises(RigError, match="The mask of the last camera 'C2' is empty"):
        Rig(cams, np.stack([masks[0], np.zeros_like(masks[1])]))
    with pytest.raises(RigError, match="Every mask is empty"):
        Rig(cams, np.zeros_like(masks))


def test_resolve_conflicts_gives_shared_pixels_to_the_smaller_scale():
    masks = np.zeros((2, 4, 4), bool)
    masks[0, :, :3] = True
    masks[1, :, 2:] = True
    out, notices = resolve_conflicts(masks, ["A", "B"])
    assert not (out[0] & out[1]).any() and out[1, :, 2:].all()
    assert notices == [
        "4 pixels are in the masks of both 'A' and 'B'; the smaller scale ('B') keeps them "
        "(erase one of the masks there to decide yourself)"
    ]


def test_auto_takes_image_blend_where_its_rays_do_not_fold():
    from multiscale_camera.core.methods import prepare_image_blend
    from multiscale_camera.core.quality import fold_map

    cams, masks = zoom_rig(96, 72, turn_deg=10)
    assert not fold_map(prepare_image_blend(Rig(cams, masks)))[0].any()
    fld = prepare(Rig(cams, masks), "AUTO", settings_for("PREVIEW"))
    assert fld.method == "IMAGE_BLEND"
    assert fld.stats["auto"] == (
        "IMAGE_BLEND: the cheapest method whose rays meet the target (p95 <= 2 px, max <= 8 px "
        "along every preserved ray, no fold) on this rig"
    )


def test_eased_weights_keep_zero_one_and_the_sum_and_leave_them_flat():
    from multiscale_camera.core.methods.image_blend import eased

    w = np.array([0.0, 1e-3, 0.25, 0.5, 0.999, 1.0])
    out = eased(np.stack([w, 1.0 - w]))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out.sum(axis=0), 1.0, atol=1e-6)
    assert out[0, 0] == 0.0 and out[0, -1] == 1.0 and out[0, 3] == pytest.approx(0.5)
    # zero slope at both ends: a weight 1e-3 from an end moves about 3e-6 from it
    assert out[0, 1] < 1e-5 and out[0, 4] > 1.0 - 1e-5
    assert np.all(np.diff(out[0]) > 0)


def test_image_blend_rays_at_a_mask_edge_do_not_cross_their_neighbours():
    """At 480x270 on the three-camera 6x rig, the rays one pixel outside camera 3's mask
    took 2% of camera 2's curve and crossed camera 3's own: 11 folded quads along the
    mask's edge, which sent AUTO to SCALAR_FIELD. Eased weights leave the edge flat."""
    from multiscale_camera.core.field import mask_weights
    from multiscale_camera.core.methods import prepare_image_blend
    from multiscale_camera.core.quality import fold_map

    cams, masks = three_camera_rig(480, 270)
    fld = prepare_image_blend(Rig(cams, masks))
    assert not fold_map(fld)[0].any()
    fld.weights = mask_weights(masks).x.astype(np.float32)  # the weights as they were
    assert fold_map(fld)[0].sum() == 11


def test_auto_says_so_when_no_method_meets_the_target():
    """Turned 60 degrees, IMAGE_BLEND folds 12 quads (43 before its weights were eased)
    and SCALAR_FIELD 53 at PREVIEW (46 before its step shortened at near planes); AUTO
    once took SCALAR_FIELD on IMAGE_BLEND's folds alone and said nothing of its own, and
    then the last candidate however it did: it keeps the one that misses least, here the
    cheaper one."""
    cams, masks = zoom_rig(96, 72, turn_deg=60)
    fld = prepare(Rig(cams, masks), "AUTO", settings_for("PREVIEW"))
    assert fld.method == "IMAGE_BLEND"
    misses = (
        "IMAGE_BLEND would miss it: 12 folded quads; SCALAR_FIELD would miss it: 53 folded quads"
    )
    assert fld.stats["auto"] == "IMAGE_BLEND: no method meets the target on this rig; " + misses
    assert fld.warnings[-2] == (
        f"No method meets the accuracy target on this rig ({misses}); IMAGE_BLEND is used, "
        "the one that misses it least. Move the masks' edges apart or turn the cameras less."
    )
    assert fld.warnings[-1] == (
        "12 quads fold in the transitions ('C1'-'C2' 12), every camera exact: raise the "
        "Clip Start of 'C2' (nearer the subject), widen the gaps between their masks or "
        "turn the cameras less (docs/failures.md)."
    )
    assert fld.measured == (fld.measured[0], 12)


def test_least_miss_takes_a_fold_free_field_then_exact_cameras():
    """The choice among misses: a fold-free candidate first; among candidates that all
    fold, fewer cameras off the target, then fewer folds, then the cheaper. Both
    folding, AUTO once kept the one with fewer folds whatever its cameras: SCALAR_FIELD
    on the turned rig, two cameras 6 px off at 480x270 where IMAGE_BLEND kept every
    camera exact."""
    from multiscale_camera.core.methods.registry import least_miss

    # (folds, cameras off the target, rank, field): the fields stand in as names
    for ib, sf, chosen in (
        ((5, 0), (0, 1), "SF"),  # fold-free first, even with a camera off
        ((0, 1), (5, 0), "IB"),
        ((5, 0), (2, 1), "IB"),  # both fold: exact cameras first
        ((2, 1), (2, 0), "SF"),
        ((5, 1), (2, 1), "SF"),  # as many cameras off: fewer folds
        ((3, 1), (3, 1), "IB"),  # a tie: the cheaper
    ):
        assert least_miss([(*ib, 0, "IB"), (*sf, 1, "SF")]) == chosen, (ib, sf)


def measured_as(monkeypatch, figures):
    """Make AUTO's measure of each candidate what ``figures`` says: method -> (cameras,
    folded quads), none of them where masks touch. Returns ``figures`` (to update)."""
    from multiscale_camera.core.methods import registry

    def fake_measure(fld, processes=1, diag=None):
        cameras, folds = figures[fld.method]
        quads = np.zeros((4, 4), dtype=bool)
        quads.flat[:folds] = True
        return cameras, quads, 1

    monkeypatch.setattr(registry, "measure_map", fake_measure)
    monkeypatch.setattr(registry, "kept_folds", lambda *a: (0, []))
    return figures


def test_auto_keeps_the_candidate_that_misses_least_when_none_meets_the_target(monkeypatch):
    """On made-up measurements: IMAGE_BLEND with a camera off the target sends AUTO on
    to SCALAR_FIELD, and ``least_miss`` chooses between them."""

    def cam(p95):
        return {"name": "C", "pixels": 10, "preserved_px": {"p50": p95, "p95": p95, "max": p95}}

    figures = measured_as(monkeypatch, {})
    cams, masks = zoom_rig(32, 24)
    for ib, sf, chosen in (
        (([cam(0.9)], 0), ([cam(0.1)], 3), "IMAGE_BLEND"),
        (([cam(0.9)], 2), ([cam(0.1)], 2), "SCALAR_FIELD"),
        (([cam(0.9)], 5), ([cam(0.9)], 2), "SCALAR_FIELD"),
        (([cam(0.9)], 3), ([cam(0.9)], 3), "IMAGE_BLEND"),
    ):
        figures.update(IMAGE_BLEND=ib, SCALAR_FIELD=sf)
        fld = prepare(Rig(cams, masks), "AUTO", settings_for("STANDARD"))
        assert fld.method == chosen, (ib, sf)
        assert fld.stats["auto"].startswith(f"{chosen}: no method meets the target")


def test_auto_builds_scalar_field_after_a_folding_image_blend(monkeypatch):
    """On made-up measurements of a rig whose kept views need not cross (the 4x rig):
    IMAGE_BLEND with every camera exact and folds sends AUTO on to SCALAR_FIELD, kept
    where it meets the target; only a rig whose kept views must cross stops AUTO at
    IMAGE_BLEND (the turned rig, ``test_auto_keeps_exact_image_blend_on_the_turned_rig_...``)."""

    exact = [{"name": "C", "pixels": 10, "preserved_px": {"p50": 0.0, "p95": 0.0, "max": 0.0}}]
    measured_as(monkeypatch, {"IMAGE_BLEND": (exact, 3), "SCALAR_FIELD": (exact, 0)})
    cams, masks = zoom_rig(32, 24)
    fld = prepare(Rig(cams, masks), "AUTO", settings_for("STANDARD"))
    assert fld.method == "SCALAR_FIELD"
    assert fld.stats["auto"].startswith("SCALAR_FIELD: the cheapest method whose rays meet")
    assert "IMAGE_BLEND would miss it: 3 folded quads" in fld.stats["auto"]


def test_auto_keeps_image_blend_where_its_only_folds_are_where_masks_touch():
    """Overlapping masks leave two preserved regions touching: the rays across the seam
    are the cameras' own with every method. AUTO built SCALAR_FIELD there (102 s at
    1920x1080) for folds no method avoids, and its preserved rays missed the target."""
    from fixtures.rigs import contradictory_rig
    from multiscale_camera.core.quality import fold_map, kept_folds

    cams, masks = contradictory_rig(192, 108)
    fld = prepare(Rig(cams, masks), "AUTO", settings_for("STANDARD"))
    folds, stride = fold_map(fld)
    assert fld.method == "IMAGE_BLEND"
    n = int(folds.sum())
    assert n > 0 and kept_folds(masks, folds, stride, ["C1", "C2"]) == (n, [("C1", "C2")])
    assert fld.stats["auto"].endswith(
        f"its {n} folded quads lie where masks touch, and every method's rays fold there"
    )
    assert fld.warnings[-1] == (
        f"{n} folded quads lie where the masks of 'C1' and 'C2' touch, with no transition "
        "between them: the rays there are those cameras' own with every method, so they "
        "cross whatever is built. Leave a gap between the masks (erase one of them there) "
        "for the rays to turn in."
    )


def test_kept_folds_counts_only_quads_whose_four_pixels_are_kept():
    from multiscale_camera.core.quality import kept_folds

    masks = np.zeros((2, 4, 5), dtype=bool)
    masks[0, :, :2] = True  # camera A: columns 0-1; B: columns 2-3; column 4 free
    masks[1, :, 2:4] = True
    folds = np.zeros((3, 4), dtype=bool)
    folds[0, 0] = folds[1, 1] = folds[2, 3] = True  # inside A, across A|B, B|free
    assert kept_folds(masks, folds, 1, ["A", "B"]) == (2, [("A", "B")])
    folds[1, 1] = False
    assert kept_folds(masks, folds, 1, ["A", "B"]) == (1, [])


def test_auto_takes_image_blend_on_the_1000x_rig_where_false_folds_sent_it_to_nested_grids():
    """The count at equal arc length flagged 33 folds among IMAGE_BLEND's exact rays here
    (174 at 240x135, all inside camera 3's disk), and AUTO built nested SCALAR_FIELD
    (minutes at full size, and its preserved rays drift); in sections there are none."""
    cams, masks = zoom1000_rig(120, 68)
    fld = prepare(Rig(cams, masks), "AUTO", settings_for("STANDARD"))
    assert fld.method == "IMAGE_BLEND"
    assert fld.stats["auto"].startswith("IMAGE_BLEND: the cheapest method whose rays meet")


@pytest.mark.slow
def test_auto_keeps_exact_image_blend_on_the_turned_rig_and_builds_nothing_after_it(
    monkeypatch,
):
    """On the turned rig (views 40.6 and 49.5 degrees apart) C3's kept rays begin, seen
    from C2, on C2's ring or beyond it: they must cross C2's kept rays, and every
    method's rays fold between the two (``quality.crossing_entries``). AUTO once built
    SCALAR_FIELD after IMAGE_BLEND there (minutes at 1920x1080), which folded too; it
    keeps IMAGE_BLEND, every camera exact, says why, names the crossing and the folding
    transitions, and builds nothing after it. (The fold count once skipped every ray
    that started beyond camera 3's near plane and found none here: the counts below
    are the exact counter's, split by the two cameras of largest weight.)"""
    from fixtures.rigs import turned_rig
    from multiscale_camera.core.methods import registry

    def not_built(*_args, **_kw):
        raise AssertionError("SCALAR_FIELD was built")

    monkeypatch.setitem(registry.METHODS, "SCALAR_FIELD", not_built)
    cams, masks = turned_rig(64, 48)
    fld = prepare(Rig(cams, masks), "AUTO", settings_for("PREVIEW"))
    assert fld.method == "IMAGE_BLEND"
    cameras, folds = fld.measured
    assert folds == 185 and all(c["preserved_px"]["p95"] <= 2.0 for c in cameras)
    assert fld.stats["auto"] == (
        "IMAGE_BLEND: no method can meet the target on this rig: the kept rays of 'C3' "
        "and 'C2' must cross, so every method's rays fold between them; IMAGE_BLEND "
        "meets it otherwise (p95 <= 2 px, max <= 8 px along every preserved ray) with "
        "185 folded quads, and the methods after it were not built"
    )
    assert fld.warnings[-2].startswith(
        "Kept rays of 'C3' and 'C2' must cross: raise the Clip Start of 'C3' to 1.99 or "
        "more (now 1.28), or turn 'C3' less; every method folds there until then."
    )
    assert fld.warnings[-1] == (
        "185 quads fold in the transitions ('C2'-'C3' 128, 'C1'-'C2' 57), every camera "
        "exact: raise the Clip Start of 'C2' and 'C3' (nearer the subject), widen the gaps "
        "between their masks or turn the cameras less (docs/failures.md)."
    )


def test_transition_folds_name_the_two_cameras_of_each_folded_quad():
    """Against a count written here: each folded quad that masks do not keep whole goes
    to the two cameras of largest weight summed over its pixels."""
    from multiscale_camera.core.quality import transition_folds

    masks = np.zeros((3, 3, 5), dtype=bool)
    masks[0, :, 0] = True  # C1 keeps column 0, C3 column 4; columns 1 to 3 are open
    masks[2, :, 4] = True
    weights = np.zeros((3, 3, 5))
    weights[0, :, :2], weights[1, :, 1:4], weights[2, :, 3:] = 1.0, 1.0, 1.0
    weights[:, :, 1] = [[0.6], [0.4], [0.0]]  # column 1: C1 and C2
    weights[:, :, 3] = [[0.0], [0.3], [0.7]]  # column 3: C2 and C3
    weights[:, :, 2] = [[0.1], [0.8], [0.1]]
    folds = np.zeros((2, 4), dtype=bool)
    folds[0, 0] = folds[1, 0] = True  # columns 0-1: C1 (2 + 1.2) and C2 (0.8)
    folds[0, 3] = True  # columns 3-4: C3 (1.4 + 2) and C2 (0.6)
    folds[1, 2] = True  # columns 2-3: C2 (1.6 + 0.6) and C3 (0.2 + 1.4)
    assert transition_folds(weights, masks, folds, ["C1", "C2", "C3"]) == [
        (("C1", "C2"), 2),
        (("C2", "C3"), 2),
    ]
    folds[:] = False
    assert transition_folds(weights, masks, folds, ["C1", "C2", "C3"]) == []


def test_auto_says_which_camera_misses_the_target_and_by_how_much():
    from multiscale_camera.core.methods.registry import shortfall

    def cam(name, pixels, p95, top):
        return {"name": name, "pixels": pixels, "preserved_px": {"p50": 0, "p95": p95, "max": top}}

    ok = [cam("A", 10, 0.5, 2.0), cam("B", 0, None, None)]
    assert shortfall(ok, 0, 0.5) == ""
    assert shortfall(ok, 3, 0.5) == "3 folded quads"
    assert shortfall([cam("A", 10, 0.51, 1.0)], 0, 0.5) == (
        "camera 'A' p95 0.51 px, max 1.00 px (target 0.5 and 2)"
    )
    assert shortfall([cam("A", 10, 0.2, 2.5)], 0, 0.5) == (
        "camera 'A' p95 0.20 px, max 2.50 px (target 0.5 and 2)"
    )
    assert shortfall([cam("C", 10, None, None)], 1, 0.5) == (
        "camera 'C' has rays that never reach its near plane; 1 folded quads"
    )


def test_auto_names_a_camera_it_could_not_measure():
    # camera 3's mask is 2x2 pixels: none left once eroded for measuring, so AUTO's choice
    # holds it to nothing and must say so rather than claim every camera meets the target
    cams, masks = three_camera_rig(96, 54)
    masks = masks.copy()
    ys, xs = np.nonzero(masks[2])
    cy, cx = int(ys.mean()), int(xs.mean())
    masks[2] = False
    masks[2, cy : cy + 2, cx : cx + 2] = True
    fld = prepare(Rig(cams, masks), "AUTO", settings_for("PREVIEW"))
    assert fld.stats["auto"].startswith(f"{fld.method}: the cheapest method whose rays meet")
    assert fld.stats["auto"].endswith(
        "; not measured, so not held to the target: camera 'C3' (its mask keeps no pixel "
        "once eroded by 2 px for measuring (too small or too thin at this render size); its "
        "pixels render, unmeasured)"
    ), fld.stats["auto"]
