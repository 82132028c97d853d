"""Bad input: each case gives one clear message where the user looks, and loses nothing."""

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import add_camera, add_mesh, mask_image
from fixtures.blender.scenes import two_camera_scene
from fixtures.masks import disk
from tests.exr import read_passes

EMPTY = (
    "The camera list is empty: add cameras in the 3D viewport's sidebar "
    "(Multiscale tab), largest scale first"
)


def render_error(scene):
    """Render through the engine; return the error text Blender raised."""
    with pytest.raises(RuntimeError) as info:
        bpy.ops.render.render()
    return str(info.value)


def operator_error(op):
    with pytest.raises(RuntimeError) as info:
        op()
    return str(info.value)


def render_to(scene, path):
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_passes(path)


def test_no_cameras_in_list(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.cameras.clear()
    assert f"Error: Multiscale: {EMPTY}" in render_error(scene)
    assert f"Error: {EMPTY}" in operator_error(bpy.ops.multiscale.validate)
    assert f"Error: {EMPTY}" in operator_error(bpy.ops.multiscale.render)


def test_deleted_camera_in_list(empty_scene):
    scene = empty_scene
    c1, c2 = two_camera_scene(scene)
    bpy.data.objects.remove(c2)
    assert scene.multiscale.cameras[1].camera is None
    assert (
        "Camera list item 2 has no camera (none was set, or it was deleted): "
        "pick a camera for it or remove the item"
    ) in operator_error(bpy.ops.multiscale.validate)
    assert len(scene.multiscale.cameras) == 2
    assert scene.multiscale.cameras[1].mask is not None


def test_list_item_that_is_not_a_camera(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)
    cube = add_mesh("cube", (5, 5, 0), 9)
    scene.multiscale.cameras[0].camera = cube
    msg = "Camera list item 1: 'Cube.001' is not a camera but a mesh; pick a camera object"
    assert msg in render_error(scene)


@pytest.mark.parametrize("kind, word", [("ORTHO", "orthographic"), ("PANO", "panoramic")])
def test_non_perspective_camera(empty_scene, kind, word):
    scene = empty_scene
    _, c2 = two_camera_scene(scene)
    c2.data.type = kind
    msg = (
        f"Camera 'C2' is {word}; multiscale rays need perspective cameras "
        "(Camera Properties > Lens > Type: Perspective)"
    )
    assert msg in render_error(scene)
    assert msg in operator_error(bpy.ops.multiscale.validate)


def test_every_mask_empty(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)
    for item in scene.multiscale.cameras:
        item.mask = mask_image("black", np.zeros((36, 48), bool))
    msg = "Every mask is empty: paint white where each camera's view should be kept"
    assert msg in render_error(scene)


def test_last_mask_empty_and_missing(empty_scene):
    scene = empty_scene
    two_camera_scene(scene)
    msg = (
        "The mask of the last camera 'C2' is empty: the smallest scale must show somewhere "
        "(paint it white there), or remove that camera"
    )
    scene.multiscale.cameras[1].mask = mask_image("black", np.zeros((36, 48), bool))
    assert msg in render_error(scene)
    scene.multiscale.cameras[1].mask = None
    assert msg in render_error(scene)


@pytest.mark.slow
def test_intermediate_camera_with_empty_mask_renders(empty_scene, tmp_path):
    scene = empty_scene
    c1, c2 = two_camera_scene(scene)
    mid = add_camera(scene, "Mid", (0.3, -8, 6), (0.5, -0.3, 1.8), clip_start=3.0)
    item = scene.multiscale.cameras.add()
    item.camera = mid
    scene.multiscale.cameras.move(2, 1)
    passes = render_to(scene, tmp_path / "mid.exr")
    m = passes["Membership"][..., 0]
    assert m.min() == pytest.approx(1.0) and m.max() == pytest.approx(3.0)


@pytest.mark.slow
def test_mask_of_another_size_is_resampled_with_notice(empty_scene, tmp_path, capfd):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.cameras[1].mask = mask_image("big", disk(96, 72, 14))
    passes = render_to(scene, tmp_path / "resampled.exr")
    out = capfd.readouterr().out
    assert "Mask 'big' is 96x72, the render is 48x36: resampled to the render size" in out
    assert passes["Membership"][18, 24, 0] == pytest.approx(2.0)


@pytest.mark.slow
def test_scene_without_mesh_renders_world_with_notice(empty_scene, tmp_path, capfd):
    scene = empty_scene
    two_camera_scene(scene)
    for obj in [o for o in scene.objects if o.type == "MESH"]:
        bpy.data.objects.remove(obj)
    scene.world = bpy.data.worlds.new("sky")
    if bpy.app.version < (5, 0, 0):
        scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.05, 0.1, 0.15, 1)
    scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 2.0
    passes = render_to(scene, tmp_path / "world.exr")
    assert "The scene has no visible mesh: only the world is rendered" in capfd.readouterr().out
    np.testing.assert_allclose(
        passes["Combined"][..., :3], np.broadcast_to([0.1, 0.2, 0.3], (36, 48, 3)), atol=1e-6
    )
    assert (passes["IndexOB"] == 0).all()


def test_failed_render_keeps_cameras_and_masks(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.cameras[1].camera.data.type = "ORTHO"
    render_error(scene)
    assert [i.camera.name for i in scene.multiscale.cameras] == ["C1", "C2"]
    assert all(i.mask is not None for i in scene.multiscale.cameras)
    path = tmp_path / "kept.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    assert [i.camera.name for i in bpy.context.scene.multiscale.cameras] == ["C1", "C2"]
