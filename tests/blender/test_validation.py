"""multiscale.validate: each message, triggered by the rig that causes it, word for word,
and kept in scene.multiscale.validation for the panel."""

import json
import re

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import add_camera, add_mesh, mask_image
from fixtures.blender.scenes import two_camera_scene
from fixtures.masks import disk
from fixtures.rigs import orbit
from multiscale_camera.adapters.cameras import pinhole_from_object
from multiscale_camera.core.quality import turn_deg

GUARD_C2 = (
    "Guides from 'C1' into 'C2' were shortened to keep them in front of 'C2' (beta x "
    "distance between near planes exceeds its near distance {near}); move its near plane "
    "(Clip Start) farther from its eye"
)


def check(scene):
    """Run the operator; return (result, the messages the panel lists)."""
    try:
        result = bpy.ops.multiscale.validate()
    except RuntimeError:
        result = {"CANCELLED"}
    return result, [(e["level"], e["text"]) for e in json.loads(scene.multiscale.validation)]


def warnings(scene):
    result, found = check(scene)
    assert result == {"FINISHED"}
    assert all(level == "WARNING" for level, _ in found)
    return [text for _, text in found]


def error(scene):
    result, found = check(scene)
    assert result == {"CANCELLED"} and len(found) == 1 and found[0][0] == "ERROR"
    return found[0][1]


@pytest.fixture()
def rig(empty_scene):
    """The two-camera scene with camera 2's near plane far enough for the guard."""
    c1, c2 = two_camera_scene(empty_scene)
    c2.data.clip_start = 2.2
    bpy.context.view_layer.update()
    return empty_scene, c1, c2


def test_a_good_rig_has_no_messages(rig):
    scene, _c1, _c2 = rig
    assert warnings(scene) == []


def test_guide_guard(rig):
    scene, _c1, c2 = rig
    c2.data.clip_start = 0.5
    assert warnings(scene) == [GUARD_C2.format(near="0.5")]


def test_order_of_scales(rig):
    scene, _c1, _c2 = rig
    scene.multiscale.active_index = 1
    bpy.ops.multiscale.camera_move(direction="UP")
    found = warnings(scene)
    assert (
        "The near plane of 'C1' lies before the near plane of 'C2': the list should run from "
        "the largest scale to the smallest (move it down the list, or move the camera)"
    ) in found


def test_turn_over_90_degrees(rig):
    scene, c1, c2 = rig
    c2.rotation_euler.z += np.pi  # camera 2 now looks back towards camera 1
    bpy.context.view_layer.update()
    a, b = (pinhole_from_object(o, scene) for o in (c1, c2))
    assert error(scene) == (
        f"Cameras 'C1' and 'C2' look {turn_deg(a, b):.0f} degrees apart; consecutive cameras "
        "must turn less than 90 degrees (add a camera between them to bend the rays in stages)"
    )


def test_contradictory_masks_share_pixels(rig):
    scene, _c1, _c2 = rig
    big = disk(48, 36, 0.3 * 48 + 3)  # reaches 3 px into camera 1's ring
    scene.multiscale.cameras[1].mask = mask_image("big", big)
    shared = int((big & disk(48, 36, 0.3 * 48, inside=False)).sum())
    assert warnings(scene) == [
        f"{shared} pixels are in the masks of both 'C1' and 'C2'; the smaller scale ('C2') "
        "keeps them (erase one of the masks there to decide yourself)"
    ]


def test_empty_intermediate_mask(rig):
    scene, _c1, _c2 = rig
    mid = add_camera(scene, "Mid", (0.3, -8, 6), (0.5, -0.3, 1.8), clip_start=3.0)
    scene.multiscale.cameras.add().camera = mid
    scene.multiscale.cameras.move(2, 1)
    found = warnings(scene)
    assert (
        "The mask of 'Mid' is empty: it only bends rays and shows nowhere (paint it white "
        "where its view should be kept, if that was the intent)"
    ) in found


def test_empty_masks_everywhere_and_last(rig):
    scene, _c1, _c2 = rig
    scene.multiscale.cameras[1].mask = None
    assert error(scene) == (
        "The mask of the last camera 'C2' is empty: the smallest scale must show somewhere "
        "(paint it white there), or remove that camera"
    )
    scene.multiscale.cameras[0].mask = None
    assert error(scene) == (
        "Every mask is empty: paint white where each camera's view should be kept"
    )


def test_frusta_of_non_consecutive_cameras_cross(rig):
    scene, _c1, _c2 = rig
    target = (4.0, 3.0, 0.0)
    c3 = add_camera(scene, "C3", (4.0, 1.0, 2.5), target, clip_start=0.8)
    item = scene.multiscale.cameras.add()
    item.camera, item.mask = c3, mask_image("C3 mask", disk(48, 36, 5))
    bpy.context.view_layer.update()
    pattern = (
        r"The preserved views of 'C1' and 'C3', which are not neighbours in the list, cross "
        r"\(\d+% of the checked rays of 'C3'\): rays there cannot follow both \(shrink the mask "
        r"of 'C1' away from where 'C3' looks, or move one of the cameras\)"
    )
    found = warnings(scene)
    assert any(re.fullmatch(pattern, t) for t in found), found
    # camera 3 looking at the sphere, which camera 1 leaves to the others: no crossing
    c3b = add_camera(scene, "C3b", (0.6, -1.7, 2.8), (0.6, -0.6, 2.3), clip_start=0.5)
    scene.multiscale.cameras[2].camera = c3b
    bpy.context.view_layer.update()
    assert not any("cross" in t for t in warnings(scene))


def test_kept_views_that_must_cross(rig):
    """C2 turned 80 degrees about the sphere with its near plane close to its eye: its
    kept rays begin where C1 sees them on C1's own kept pixels, so they must cross C1's
    kept rays (``quality.crossing_entries``); the Clip Start the warning asks for clears
    it."""
    scene, _c1, _c2 = rig
    sphere = (0.6, -0.6, 2.3)
    c2b = add_camera(scene, "C2b", orbit(sphere, 3.0, 80, 35), sphere, clip_start=0.5)
    scene.multiscale.cameras[1].camera = c2b
    bpy.context.view_layer.update()
    pattern = (
        r"Kept rays of 'C2b' and 'C1' must cross: raise the Clip Start of 'C2b' to "
        r"([0-9.]+) or more \(now 0\.5\), or turn 'C2b' less; every method folds there "
        r"until then\. The kept rays of 'C2b' begin on its near plane where 'C1' sees them "
        r"outside the opening of its mask \((\d+) of \2 checked, all on its kept pixels; "
        r"docs/failures\.md\)\."
    )
    found = [m for m in map(re.compile(pattern).fullmatch, warnings(scene)) if m]
    assert len(found) == 1, warnings(scene)
    c2b.data.clip_start = float(found[0].group(1))
    bpy.context.view_layer.update()
    assert not any("must cross" in t for t in warnings(scene))


def test_geometry_between_near_planes_on_preserved_rays(rig):
    scene, _c1, _c2 = rig
    wall = add_mesh("cube", (0.27, -5.9, 4.9), 7, size=1.0)
    bpy.context.view_layer.update()
    pattern = (
        rf"'{wall.name}' stands between the near planes of 'C1' and 'C2' on \d+% of the "
        r"preserved rays of 'C2': it hides what 'C2' sees there \(lower the Clip Start of "
        r"'C2' so its near plane lies before the object, or move the camera or the object\)"
    )
    found = warnings(scene)
    assert len(found) == 1 and re.fullmatch(pattern, found[0]), found
    wall.location.x += 6  # out of the way
    bpy.context.view_layer.update()
    assert warnings(scene) == []


def test_camera_listed_twice(rig):
    scene, c1, _c2 = rig
    scene.multiscale.cameras.add().camera = c1
    assert error(scene) == (
        "A camera appears twice in the camera list; each camera may appear once"
    )


@pytest.mark.parametrize("kind, word", [("ORTHO", "orthographic"), ("PANO", "panoramic")])
def test_unsupported_camera_type(rig, kind, word):
    scene, _c1, c2 = rig
    c2.data.type = kind
    assert error(scene) == (
        f"Camera 'C2' is {word}; multiscale rays need perspective cameras "
        "(Camera Properties > Lens > Type: Perspective)"
    )


@pytest.mark.slow
def test_a_build_validates_first(rig, capfd):
    scene, _c1, c2 = rig
    c2.data.clip_start = 0.5
    bpy.ops.multiscale.compute_field()
    assert json.loads(scene.multiscale.validation) == [
        {"level": "WARNING", "text": GUARD_C2.format(near="0.5")}
    ]


def test_mask_whose_file_is_missing(rig, tmp_path):
    scene, _c1, _c2 = rig
    mid = add_camera(scene, "Mid", (0.3, -8, 6), (0.5, -0.3, 1.8), clip_start=3.0)
    img = bpy.data.images.new("lost", 4, 4)
    img.source = "FILE"
    img.filepath = str(tmp_path / "gone.png")
    img.reload()
    item = scene.multiscale.cameras.add()
    item.camera, item.mask = mid, img
    scene.multiscale.cameras.move(2, 1)
    assert "Mask 'lost' has no pixels (is its file missing?); treated as empty" in warnings(scene)


def test_panel_marks_the_near_distance_that_breaks_the_guard(rig):
    from multiscale_camera.ui.panels import guard_cameras

    scene, _c1, c2 = rig
    assert guard_cameras(bpy.context) == set()
    c2.data.clip_start = 0.5
    assert guard_cameras(bpy.context) == {"C2"}
    c2.data.type = "ORTHO"  # a rig the check refuses: the panel only stays quiet
    assert guard_cameras(bpy.context) == set()
