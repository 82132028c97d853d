"""AUTO for a rig in motion: one method for the whole shot, measured once on a few of
its frames (``core.methods.shot``), and IMAGE_BLEND's weights taken from the build
before when the masks are unchanged (``core.methods.reuse``).

The references: IMAGE_BLEND measured on its own at each frame (``measure`` and
``shortfall``, one frame at a time), and the same frame built cold."""

from dataclasses import replace

import numpy as np
import pytest

from fixtures.rigs import disk_masks, zoom_rig
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import (
    FrameReuse,
    ShotChoice,
    choose_shot_method,
    field_key,
    prepare,
    registry,
    sample_frames,
    settings_for,
)
from multiscale_camera.core.methods import image_blend as image_blend_module
from multiscale_camera.core.quality import measure

W, H = 96, 72
SETTINGS = replace(settings_for("PREVIEW"), processes=1, steady=True)


def turned(turn_deg, inner=0.35):
    """The zoom rig with camera 2 turned ``turn_deg`` about the subject; ``inner`` sets
    camera 2's mask radius (a share of the width)."""
    cams, _masks = zoom_rig(W, H, turn_deg=turn_deg)
    return Rig(cams, disk_masks(W, H, 0.2 * W, inner * W))


class _Built:
    """What a recording SCALAR_FIELD builder hands back: a field's stats alone."""

    def __init__(self):
        self.stats = {}


def shot(first_turn, last_turn, frames):
    """{frame: Rig} of a shot over frames 1..``frames`` whose camera 2 turns uniformly
    from ``first_turn`` to ``last_turn`` degrees (keys on the first and last frame)."""
    step = (last_turn - first_turn) / (frames - 1)
    return {f: turned(first_turn + step * (f - 1)) for f in range(1, frames + 1)}


def misses(rig):
    """The reference: IMAGE_BLEND built and measured on ``rig`` alone."""
    fld = prepare(rig, "IMAGE_BLEND", replace(SETTINGS, steady=False))
    cameras, folds = measure(fld, 1)
    return registry.shortfall(cameras, folds, SETTINGS.accuracy_px)


@pytest.mark.parametrize(
    ("first", "last", "keys", "expected"),
    [
        (1, 48, range(1, 49), (1, 24, 48)),  # a key on every frame: the earlier middle
        (1, 3, (1, 3), (1, 2, 3)),  # keys at the ends alone: the range's middle
        (1, 10, (), (1, 5, 10)),  # nothing keyed: the range
        (1, 11, (1.0, 4.2, 11.0, 30.0), (1, 4, 11)),  # keys rounded, outside dropped
        (5, 5, (5,), (5,)),
        (1, 21, (1, 2, 3, 20, 21), (1, 3, 21)),  # the key nearest the middle (11)
    ],
)
def test_sample_frames_are_the_ends_and_the_middle_key(first, last, keys, expected):
    assert sample_frames(first, last, keys) == expected


def test_sample_frames_keep_the_ends_and_spread_the_rest():
    assert sample_frames(1, 9, range(1, 10), most=5) == (1, 4, 5, 6, 9)
    assert sample_frames(1, 9, range(1, 10), most=2) == (1, 9)


def test_auto_keeps_image_blend_for_a_shot_it_meets_at_every_sampled_frame(monkeypatch):
    """Camera 2 turns from 10 to 30 degrees: IMAGE_BLEND meets the target at frames 1,
    11 and 21 (as measured alone), so every frame of the shot, sampled or not, builds
    IMAGE_BLEND and the report says which frames were measured."""
    rigs = shot(10, 30, 21)
    frames = sample_frames(1, 21, (1, 21))
    assert frames == (1, 11, 21)
    assert all(misses(rigs[f]) == "" for f in frames)
    choice = choose_shot_method([(f, rigs[f]) for f in frames], SETTINGS)
    assert choice.method == "IMAGE_BLEND" and choice.frames == (1, 11, 21)
    assert choice.why == (
        "IMAGE_BLEND: the rig moves and a shot keeps one method; IMAGE_BLEND meets the "
        "target (p95 <= 2 px, max <= 8 px along every preserved ray, no fold) at frames "
        "1, 11, 21 of the shot"
    )
    settings = replace(SETTINGS, shot=choice)
    scalar = []
    monkeypatch.setattr(registry, "prepare_scalar_field", lambda *a, **k: scalar.append(a))
    reuse = FrameReuse()
    for f in (4, 5, 21):
        fld = prepare(rigs[f], "AUTO", settings, reuse=reuse)
        assert fld.method == "IMAGE_BLEND" and fld.stats["auto"] == choice.why, f
    assert scalar == []


def test_auto_takes_scalar_field_for_a_shot_where_one_sampled_frame_folds(monkeypatch):
    """Camera 2 turns from 10 to 60 degrees: at frame 11 (60 degrees) IMAGE_BLEND folds
    12 quads, so the whole shot builds SCALAR_FIELD, even frame 2, where IMAGE_BLEND
    alone would meet the target (a choice per frame would switch mid-shot)."""
    rigs = shot(10, 60, 11)
    frames = sample_frames(1, 11, (1, 11))
    assert frames == (1, 6, 11)
    assert [misses(rigs[f]) for f in frames] == ["", "", "12 folded quads"]
    assert misses(rigs[2]) == ""
    choice = choose_shot_method([(f, rigs[f]) for f in reversed(frames)], SETTINGS)
    assert choice == ShotChoice(
        "SCALAR_FIELD",
        (1, 6, 11),
        "SCALAR_FIELD: the rig moves and a shot keeps one method; IMAGE_BLEND would miss "
        "the target at frame 11: 12 folded quads (frames measured: 1, 6, 11)",
    )
    built = []

    def scalar(rig, settings, diag=None, reuse=None):
        built.append(rig)
        return _Built()

    monkeypatch.setattr(registry, "prepare_scalar_field", scalar)
    fld = prepare(rigs[2], "AUTO", replace(SETTINGS, shot=choice), reuse=FrameReuse())
    assert built == [rigs[2]] and fld.stats["auto"] == choice.why


def test_a_shot_whose_masks_touch_keeps_image_blend_as_a_still_does():
    """Overlapping masks leave two kept regions touching: the rays across the seam are
    the cameras' own with every method, so a still's AUTO keeps IMAGE_BLEND there
    (``quality.kept_folds``). A shot counted those folds against IMAGE_BLEND and built
    SCALAR_FIELD on every frame, slower and folding at the same seam."""
    from fixtures.rigs import contradictory_rig
    from multiscale_camera.core.quality import fold_map, kept_folds

    rig = Rig(*contradictory_rig(W, H))
    still = prepare(rig, "AUTO", replace(SETTINGS, steady=False))
    folds, stride = fold_map(still)
    n = int(folds.sum())
    assert still.method == "IMAGE_BLEND" and n > 0
    assert kept_folds(rig.masks, folds, stride, ["C1", "C2"]) == (n, [("C1", "C2")])
    moved = Rig(*contradictory_rig(W, H))
    choice = choose_shot_method([(1, rig), (9, moved)], SETTINGS)
    assert choice == ShotChoice(
        "IMAGE_BLEND",
        (1, 9),
        "IMAGE_BLEND: the rig moves and a shot keeps one method; IMAGE_BLEND meets the "
        "target (p95 <= 2 px, max <= 8 px along every preserved ray, no fold) at frames "
        "1, 9 of the shot; its folded quads lie where masks touch, and every method's "
        f"rays fold there (frame 1: {n}, 'C1' and 'C2'; frame 9: {n}, 'C1' and 'C2')",
    )


def test_a_shots_choice_is_deterministic_and_part_of_every_frames_key():
    """Two processes (fresh rigs and stores each) measure the same sampled frames and
    choose alike, so every frame's cache key agrees; the key follows the method."""
    first = shot(10, 60, 11)
    again = shot(10, 60, 11)
    frames = sample_frames(1, 11, (1, 11))
    one = choose_shot_method([(f, first[f]) for f in frames], SETTINGS)
    two = choose_shot_method([(f, again[f]) for f in frames], SETTINGS)
    assert one == two and repr(one) == repr(two)
    key = field_key(first[3], "AUTO", replace(SETTINGS, shot=one))
    assert key == field_key(again[3], "AUTO", replace(SETTINGS, shot=two))
    other = replace(one, method="IMAGE_BLEND")
    assert key != field_key(first[3], "AUTO", replace(SETTINGS, shot=other))


def counted_solves(monkeypatch):
    """A list that grows by one each time IMAGE_BLEND solves its mask weights."""
    calls = []
    solve = image_blend_module.mask_weights

    def counting(masks, *args, **kwargs):
        calls.append(np.asarray(masks).copy())
        return solve(masks, *args, **kwargs)

    monkeypatch.setattr(image_blend_module, "mask_weights", counting)
    return calls


def rays_of(fld):
    iy, ix = np.mgrid[0:H, 0:W]
    return fld.rays(ix.ravel(), iy.ravel()).vertices


def test_image_blend_reuses_its_weights_while_the_masks_hold(monkeypatch):
    """Camera 2 turns, the masks hold: the second frame takes the first's weights (no
    solve) and its rays equal those of the same frame built cold; a frame whose mask
    changed solves again, and says so."""
    calls = counted_solves(monkeypatch)
    reuse = FrameReuse()
    first = prepare(turned(20), "IMAGE_BLEND", SETTINGS, reuse=reuse)
    second = prepare(turned(25), "IMAGE_BLEND", SETTINGS, reuse=reuse)
    assert len(calls) == 1
    assert first.stats["reuse"]["weights"] == "solved"
    assert first.stats["reuse"]["rebuilt"] == ["weights"]
    assert second.stats["reuse"]["weights"] == "reused"
    assert second.stats["reuse"]["rebuilt"] == []
    assert second.solver == first.solver
    cold = prepare(turned(25), "IMAGE_BLEND", SETTINGS)
    assert len(calls) == 2 and "reuse" not in cold.stats
    np.testing.assert_array_equal(second.weights, cold.weights)
    np.testing.assert_array_equal(rays_of(second), rays_of(cold))

    grown = prepare(turned(25, inner=0.3), "IMAGE_BLEND", SETTINGS, reuse=reuse)
    assert len(calls) == 3 and grown.stats["reuse"]["weights"] == "solved"
    np.testing.assert_array_equal(calls[-1], turned(25, inner=0.3).masks)
    assert not np.array_equal(grown.weights, second.weights)
    cold = prepare(turned(25, inner=0.3), "IMAGE_BLEND", SETTINGS)
    np.testing.assert_array_equal(grown.weights, cold.weights)
    # the store keeps the last masks' weights alone
    again = prepare(turned(30), "IMAGE_BLEND", SETTINGS, reuse=reuse)
    assert again.stats["reuse"]["weights"] == "solved" and len(calls) == 5


def test_auto_on_a_blending_shot_reuses_the_weights(monkeypatch):
    """AUTO's IMAGE_BLEND for a shot goes through the same store as IMAGE_BLEND."""
    rigs = shot(10, 30, 21)
    choice = ShotChoice("IMAGE_BLEND", (1, 11, 21), "why")
    calls = counted_solves(monkeypatch)
    reuse = FrameReuse()
    took = [
        prepare(rigs[f], "AUTO", replace(SETTINGS, shot=choice), reuse=reuse).stats["reuse"]
        for f in (1, 2, 3)
    ]
    assert [t["weights"] for t in took] == ["solved", "reused", "reused"]
    assert len(calls) == 1
