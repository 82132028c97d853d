"""A mask that is an image sequence is read at the frame Blender's image user would
show (frames, start, offset, cyclic on the camera's list item), and the field's cache
key follows the frame's pixels."""

import threading

import bpy
import numpy as np
import pytest

from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.masks import (
    ANIMATED_MASK,
    FRAME_NOT_LOADED,
    MISSING_FRAME,
    MaskFrames,
    frame_path,
    mask_from_image,
    sequence_frame,
)
from multiscale_camera.adapters.scene import rig_from_scene
from multiscale_camera.core.methods import prepare
from multiscale_camera.render import fields, pipeline
from multiscale_camera.render.fields import SERVICE
from multiscale_camera.ui.mask_overlay import rig_masks

W, H = 16, 12


@pytest.fixture
def image_user(tmp_path):
    """Blender's own image user of a 3-file sequence: an image texture node's (auto
    refresh on) in a material on an object, read from the evaluated material."""
    for k in range(1, 4):
        still = bpy.data.images.new(f"f{k}", 4, 4)
        still.filepath_raw = str(tmp_path / f"m_{k:04d}.png")
        still.file_format = "PNG"
        still.save()
        bpy.data.images.remove(still)
    sequence = bpy.data.images.load(str(tmp_path / "m_0001.png"))
    sequence.source = "SEQUENCE"
    material = bpy.data.materials.new("M")
    material.use_nodes = True
    node = material.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = sequence
    node.image_user.use_auto_refresh = True
    mesh = bpy.data.meshes.new("me")
    mesh.materials.append(material)
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("ob", mesh))
    return material, node


def blenders_frame(image_user, frame):
    """The frame number Blender's image user shows at scene frame ``frame``."""
    material, node = image_user
    scene = bpy.context.scene
    scene.frame_set(frame)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = material.evaluated_get(depsgraph)
    return evaluated.node_tree.nodes[node.name].image_user.frame_current


@pytest.mark.parametrize("cyclic", [False, True])
@pytest.mark.parametrize("start", [1, 5, -3])
@pytest.mark.parametrize("offset", [0, 2, -1])
def test_sequence_frame_plays_as_blenders_image_user(image_user, cyclic, start, offset):
    user = image_user[1].image_user
    for frames in (0, 1, 2, 7):
        user.frame_duration, user.frame_start = frames, start
        user.frame_offset, user.use_cyclic = offset, cyclic
        for frame in range(-12, 20):
            want = blenders_frame(image_user, frame)
            got = sequence_frame(frame, frames, start, offset, cyclic)
            assert got == want, (frames, frame)


def test_sequence_frame_pinned_cases():
    # two frames from frame 1: held on the last, frame 0 before the start
    assert [sequence_frame(f, 2) for f in (0, 1, 2, 3, 9)] == [0, 1, 2, 2, 2]
    # cyclic: 1, 2, 1, 2 ... and frame 0 is the last one
    assert [sequence_frame(f, 2, cyclic=True) for f in (0, 1, 2, 3, 4)] == [2, 1, 2, 1, 2]
    assert sequence_frame(10, 5, start=10, offset=100) == 101


def test_frame_path_renumbers_the_last_digits_of_the_file_name():
    assert frame_path("//masks/m_0001.png", 12) == "//masks/m_0012.png"
    assert frame_path("/a/shot2_v03_0001.exr", 7) == "/a/shot2_v03_0007.exr"
    assert frame_path("/a/m7.png", 123) == "/a/m123.png"
    assert frame_path("/take1/mask.png", 3) == "/take1/mask.png"


def write_sequence(folder, halves):
    """Files mask_0001.png ... : frame k white on its left half when halves[k-1] is
    "left", else on its right half."""
    for k, half in enumerate(halves, start=1):
        still = bpy.data.images.new(f"frame {k}", W, H)
        rgba = np.zeros((H, W, 4), np.float32)
        rgba[..., 3] = 1.0
        cols = slice(0, W // 2) if half == "left" else slice(W // 2, W)
        rgba[:, cols, :3] = 1.0
        still.pixels.foreach_set(rgba.ravel())
        still.filepath_raw = str(folder / f"mask_{k:04d}.png")
        still.file_format = "PNG"
        still.save()
        bpy.data.images.remove(still)
    sequence = bpy.data.images.load(str(folder / "mask_0001.png"))
    sequence.source = "SEQUENCE"
    return sequence


def read_at(scene, frame):
    scene.frame_set(frame)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    rig = rig_from_scene(depsgraph.scene, depsgraph)
    return rig, SERVICE.request(depsgraph.scene, rig=rig).key


@pytest.fixture
def scene(empty_scene, tmp_path):
    two_camera_scene(empty_scene, W, H)
    item = empty_scene.multiscale.cameras[0]
    item.mask = write_sequence(tmp_path, ["left", "right"])
    item.mask_frames = 2
    return empty_scene


def halves():
    """Camera 1's expected masks: left and right halves (before camera 2 takes its
    pixels)."""
    left = np.zeros((H, W), bool)
    left[:, : W // 2] = True
    return left, ~left


def test_a_two_frame_sequence_is_read_at_each_frame(scene):
    left, right = halves()
    c2 = rig_from_scene(scene).masks[1]  # camera 2 keeps its own pixels
    rig1, key1 = read_at(scene, 1)
    rig2, key2 = read_at(scene, 2)
    rig3, key3 = read_at(scene, 3)  # held on the last frame
    np.testing.assert_array_equal(rig1.masks[0], left & ~c2)
    np.testing.assert_array_equal(rig2.masks[0], right & ~c2)
    np.testing.assert_array_equal(rig3.masks[0], right & ~c2)
    assert key1 != key2 and key2 == key3  # the cache key follows the frame's pixels
    assert not any("animated" in n for n in rig1.notices)


def test_start_offset_and_cyclic_choose_the_frame_read(scene):
    left, right = halves()
    c2 = rig_from_scene(scene).masks[1]
    item = scene.multiscale.cameras[0]
    item.mask_cyclic = True
    assert np.array_equal(read_at(scene, 3)[0].masks[0], left & ~c2)  # 1, 2, 1
    item.mask_cyclic = False
    item.mask_frame_start = 2
    assert np.array_equal(read_at(scene, 2)[0].masks[0], left & ~c2)  # starts at 2
    assert np.array_equal(read_at(scene, 3)[0].masks[0], right & ~c2)
    item.mask_frame_start = 1
    item.mask_frame_offset = 1
    assert np.array_equal(read_at(scene, 1)[0].masks[0], right & ~c2)  # file 2 first


def test_a_missing_frame_is_said_and_reads_empty(scene):
    item = scene.multiscale.cameras[0]
    item.mask_frames = 3  # there is no mask_0003.png
    rig, _key = read_at(scene, 3)
    assert not rig.masks[0].any()
    path = bpy.path.abspath(frame_path(item.mask.filepath, 3))
    said = MISSING_FRAME.format(name=item.mask.name, number=3, path=path)
    assert said in rig.notices


def test_a_sequence_read_without_a_frame_number_says_so(scene):
    """Movies are read now (tests/blender/test_movie_masks.py); an animated mask read
    without a frame number still says so."""
    image = scene.multiscale.cameras[0].mask
    mask, notices = mask_from_image(image, W, H)
    assert notices == [ANIMATED_MASK.format(name=image.name, kind="an image sequence")]
    assert not mask.any()


def test_reading_a_sequence_mask_again_changes_no_blender_data(scene):
    """Reading the rig (as the Rendered viewport does while it draws) must not load
    and remove images each time: that is a change to Blender's data, which redraws
    every view (an endless redraw loop) and is unsafe on a render thread."""
    frames = MaskFrames()
    rig_from_scene(scene, frames=frames)  # the first read loads frame 1 once
    bpy.context.evaluated_depsgraph_get()
    names = sorted(i.name for i in bpy.data.images)
    updates = []

    def seen(_scene, depsgraph):
        updates.extend(u.id.name for u in depsgraph.updates)

    bpy.app.handlers.depsgraph_update_post.append(seen)
    try:
        for _ in range(2):
            rig_from_scene(scene, frames=frames)
            bpy.context.evaluated_depsgraph_get()
    finally:
        bpy.app.handlers.depsgraph_update_post.remove(seen)
    assert updates == []
    assert sorted(i.name for i in bpy.data.images) == names


def test_a_frame_first_needed_off_the_main_thread_is_said_not_loaded(scene):
    frames = MaskFrames()
    item = scene.multiscale.cameras[0]
    got = {}
    worker = threading.Thread(target=lambda: got.update(rig=rig_from_scene(scene, frames=frames)))
    worker.start()
    worker.join()
    path = bpy.path.abspath(frame_path(item.mask.filepath, 1))
    said = FRAME_NOT_LOADED.format(name=item.mask.name, number=1, path=path)
    assert said in got["rig"].notices
    assert not got["rig"].masks[0].any()
    rig_from_scene(scene, frames=frames)  # the main thread loads it; then a thread reads it
    worker = threading.Thread(target=lambda: got.update(rig=rig_from_scene(scene, frames=frames)))
    worker.start()
    worker.join()
    assert got["rig"].masks[0].any()
    assert not any("not loaded" in n for n in got["rig"].notices)


def test_the_overlay_shows_a_sequence_mask_at_the_scene_frame(scene):
    """The overlay read sequence masks without a frame: they showed empty."""
    left, right = halves()
    scene.frame_set(1)
    np.testing.assert_array_equal(rig_masks(scene, (W, H))[0], left)
    scene.frame_set(2)
    np.testing.assert_array_equal(rig_masks(scene, (W, H))[0], right)


def moving(scene):
    """Camera 2 keyed to move a little on frames 1-3: a rig in motion."""
    c2 = scene.multiscale.cameras[1].camera
    for frame in (1, 2, 3):
        c2.location.x += 0.01
        c2.keyframe_insert("location", frame=frame)
    scene.frame_set(1)


def test_image_blend_solves_its_weights_again_where_a_mask_sequence_changes(scene):
    """Camera 1's mask is the left half at frame 1 and the right half from frame 2 on,
    camera 2 moves: frame 2 solves the weights again, frame 3 (the same masks) takes
    them as they were, and each frame's weights equal those of a cold build."""
    moving(scene)
    scene.multiscale.method = "IMAGE_BLEND"
    SERVICE.forget_sequence()
    said = {}
    for frame in (1, 2, 3):
        scene.frame_set(frame)
        ready = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
        said[frame] = ready.field.stats["reuse"]["weights"]
        assert ("mask weights" in ready.rebuilt["built"]) == (said[frame] == "solved")
        cold = prepare(ready.field.rig, "IMAGE_BLEND")
        np.testing.assert_array_equal(ready.field.weights, cold.weights)
    assert said == {1: "solved", 2: "solved", 3: "reused"}


def test_auto_measures_each_sampled_frame_with_its_own_masks(scene, monkeypatch):
    """A shot with a mask sequence is one shot at every frame (the choice is keyed by
    the sequence, not the frame's pixels): measured once, each sampled frame with the
    masks Blender shows there."""
    moving(scene)
    scene.multiscale.method = "AUTO"
    SERVICE.forget_sequence()
    left, right = halves()
    measured = []
    real = fields.choose_shot_method

    def choose(samples, *args):
        measured.append({f: rig.masks[0].copy() for f, rig in samples})
        return real(samples, *args)

    monkeypatch.setattr(fields, "choose_shot_method", choose)
    shots = set()
    for frame in (1, 2, 3):
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        shots.add(SERVICE.request(depsgraph.scene, depsgraph=depsgraph).settings.shot)
    assert len(measured) == 1 and len(shots) == 1
    assert sorted(measured[0]) == [1, 2, 3]
    c2 = rig_from_scene(scene).masks[1]
    np.testing.assert_array_equal(measured[0][1], left & ~c2)
    np.testing.assert_array_equal(measured[0][2], right & ~c2)
    np.testing.assert_array_equal(measured[0][3], right & ~c2)
