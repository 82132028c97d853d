"""Operators on the camera list, driven headless."""

import bpy
import pytest

from fixtures.blender.objects import add_camera
from fixtures.blender.scenes import two_camera_scene


def names(scene):
    return [item.camera.name if item.camera else None for item in scene.multiscale.cameras]


def select(*objs):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in objs:
        o.select_set(True)
    bpy.context.view_layer.objects.active = objs[-1] if objs else None


def test_camera_add_remove_move(empty_scene):
    scene = empty_scene
    a = add_camera(scene, "A", (0, -10, 5), (0, 0, 0))
    b = add_camera(scene, "B", (0, -5, 3), (0, 0, 0))
    select(a)
    assert bpy.ops.multiscale.camera_add() == {"FINISHED"}
    select(b)
    bpy.ops.multiscale.camera_add()
    assert names(scene) == ["A", "B"]
    assert scene.multiscale.active_index == 1
    assert bpy.ops.multiscale.camera_add() == {"CANCELLED"}  # already listed: nothing added
    bpy.ops.multiscale.camera_move(direction="UP")
    assert names(scene) == ["B", "A"] and scene.multiscale.active_index == 0
    bpy.ops.multiscale.camera_move(direction="DOWN")
    assert names(scene) == ["A", "B"]
    bpy.ops.multiscale.camera_remove()
    assert names(scene) == ["A"]
    assert "B" in bpy.data.objects  # removing from the list keeps the camera
    select()
    bpy.ops.multiscale.camera_add()
    assert names(scene) == ["A", None]


def test_move_and_remove_poll(empty_scene):
    assert not bpy.ops.multiscale.camera_remove.poll()
    assert not bpy.ops.multiscale.camera_move.poll()


@pytest.mark.slow
def test_render_operator_sets_engine_and_scene_camera(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.camera = None
    scene.render.filepath = str(tmp_path / "out.png")
    assert bpy.ops.multiscale.render(write_still=True) == {"FINISHED"}
    assert scene.render.engine == "MULTISCALE" and scene.camera.name == "C1"
    assert (tmp_path / "out.png").exists()


def test_validate_reports_ready(empty_scene):
    two_camera_scene(empty_scene)
    assert bpy.ops.multiscale.validate() == {"FINISHED"}
