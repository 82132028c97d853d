"""One notion of visible: the rig check (a viewport depsgraph), the render and the Cycles
hand-off (whose tables march the render's own frame) count the same objects, case by
case (docs/failures.md, *Scene content*)."""

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import add_mesh
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.meshes import scene_geometry
from multiscale_camera.io.cache import FieldCache
from multiscale_camera.render import fields, pipeline
from multiscale_camera.render.tables import ray_tables
from tests.exr import read_passes

CUBE = 2  # the cube's pass index in two_camera_scene


@pytest.fixture
def scene(empty_scene, tmp_path, monkeypatch):
    monkeypatch.setattr(fields.SERVICE, "cache", FieldCache(str(tmp_path / "cache")))
    two_camera_scene(empty_scene)
    empty_scene.multiscale.method = "IMAGE_BLEND"
    return empty_scene


def counted(scene, tmp_path, monkeypatch):
    """(objects the rig check counts, objects the render's frame counts, the render's
    passes, the tables' object index of that frame)."""
    bpy.context.view_layer.update()
    checked = set(scene_geometry(bpy.context.evaluated_depsgraph_get()).object_names)
    frames = []
    prepare = pipeline.prepare_frame

    def kept(*args, **kwargs):
        frames.append(prepare(*args, **kwargs))
        return frames[-1]

    monkeypatch.setattr(pipeline, "prepare_frame", kept)
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(tmp_path / "passes.exr")
    bpy.ops.render.render(write_still=True)
    monkeypatch.setattr(pipeline, "prepare_frame", prepare)
    frame = frames[-1]
    tables = ray_tables(frame)
    return checked, set(frame.geometry.object_names), read_passes(tmp_path / "passes.exr"), tables


def agree_without_cube(scene, tmp_path, monkeypatch):
    checked, rendered, passes, tables = counted(scene, tmp_path, monkeypatch)
    assert "Cube" not in checked and "Cube" not in rendered and "Plane" in checked
    assert CUBE not in passes["IndexOB"] and CUBE not in tables.object_index
    return checked, rendered


def agree_with_cube(scene, tmp_path, monkeypatch):
    checked, rendered, passes, tables = counted(scene, tmp_path, monkeypatch)
    assert "Cube" in checked and "Cube" in rendered
    assert CUBE in passes["IndexOB"] and CUBE in tables.object_index
    return checked, rendered


def test_object_with_camera_visibility_off_is_left_out_everywhere(scene, tmp_path, monkeypatch):
    agree_with_cube(scene, tmp_path, monkeypatch)
    scene.objects["Cube"].visible_camera = False
    agree_without_cube(scene, tmp_path, monkeypatch)


def test_collection_excluded_from_the_view_layer_is_left_out_everywhere(
    scene, tmp_path, monkeypatch
):
    coll = bpy.data.collections.new("Excluded")
    scene.collection.children.link(coll)
    coll.objects.link(scene.objects["Cube"])
    scene.collection.objects.unlink(scene.objects["Cube"])
    bpy.context.view_layer.layer_collection.children["Excluded"].exclude = True
    agree_without_cube(scene, tmp_path, monkeypatch)


def test_indirect_only_collection_is_left_out_everywhere(scene, tmp_path, monkeypatch):
    coll = bpy.data.collections.new("Indirect")
    scene.collection.children.link(coll)
    coll.objects.link(scene.objects["Cube"])
    scene.collection.objects.unlink(scene.objects["Cube"])
    bpy.context.view_layer.layer_collection.children["Indirect"].indirect_only = True
    agree_without_cube(scene, tmp_path, monkeypatch)


@pytest.mark.parametrize("how", ["hide_viewport", "hide_set", "collection_hide_viewport"])
def test_objects_hidden_in_the_viewport_only_count_as_the_render_shows_them(
    scene, tmp_path, monkeypatch, how
):
    """The viewport's depsgraph holds none of these; the render shows them, so the rig
    check counts them too (it used to miss them)."""
    cube = scene.objects["Cube"]
    if how == "hide_viewport":
        cube.hide_viewport = True
    elif how == "hide_set":
        cube.hide_set(True)
    else:
        coll = bpy.data.collections.new("NotInViewports")
        scene.collection.children.link(coll)
        coll.objects.link(cube)
        scene.collection.objects.unlink(cube)
        coll.hide_viewport = True
    bpy.context.view_layer.update()
    names = [i.object.name for i in bpy.context.evaluated_depsgraph_get().object_instances]
    assert "Cube" not in names  # what the rig check used to count from
    agree_with_cube(scene, tmp_path, monkeypatch)


@pytest.mark.parametrize("where", ["object", "collection"])
def test_holdout_hides_what_lies_behind_it_and_shows_transparent(
    scene, tmp_path, monkeypatch, where
):
    before = counted(scene, tmp_path, monkeypatch)[2]
    cube_pixels = before["IndexOB"][..., 0] == CUBE
    assert cube_pixels.sum() > 5
    if where == "object":
        scene.objects["Cube"].is_holdout = True
    else:
        coll = bpy.data.collections.new("Held")
        scene.collection.children.link(coll)
        coll.objects.link(scene.objects["Cube"])
        scene.collection.objects.unlink(scene.objects["Cube"])
        bpy.context.view_layer.layer_collection.children["Held"].holdout = True
    checked, rendered, passes, tables = counted(scene, tmp_path, monkeypatch)
    assert "Cube" in checked and "Cube" in rendered  # it hides what lies behind it
    geometry = scene_geometry(bpy.context.evaluated_depsgraph_get())
    cube = geometry.object_names.index("Cube")
    assert geometry.holdout[geometry.object_of == cube].all()
    assert not geometry.holdout[geometry.object_of != cube].any()
    combined = passes["Combined"]
    # the cube's pixels (the same as before: a holdout still stops the rays) are
    # transparent black; the others keep their colour and alpha 1
    assert np.array_equal(passes["IndexOB"][..., 0] == CUBE, cube_pixels)
    assert np.all(combined[cube_pixels] == 0.0)
    assert np.all(combined[~cube_pixels][:, 3] == 1.0)
    np.testing.assert_array_equal(combined[~cube_pixels], before["Combined"][~cube_pixels])
    assert CUBE in tables.object_index


def particle_emitter(scene):
    """A small plane emitting 20 copies of the cube as particles, the cube itself
    disabled in renders."""
    emitter = add_mesh("plane", (0, 0, 0.01), 7, (0.9, 0.9, 0.9), size=6)
    bpy.context.view_layer.objects.active = emitter
    bpy.ops.object.particle_system_add()
    settings = emitter.particle_systems[0].settings
    settings.type = "HAIR"
    settings.count = 20
    settings.hair_length = 1.0
    settings.render_type = "OBJECT"
    settings.instance_object = scene.objects["Cube"]
    settings.particle_size = 0.3
    scene.objects["Cube"].hide_render = True
    return emitter


def test_particles_count_as_the_render_shows_them_and_the_emitter_as_it_is_set(
    scene, tmp_path, monkeypatch
):
    emitter = particle_emitter(scene)
    emitter.show_instancer_for_viewport = True
    emitter.show_instancer_for_render = False
    checked, rendered, passes, tables = counted(scene, tmp_path, monkeypatch)
    # the particles (copies of the cube) count; the cube itself and the emitter do not
    assert "Cube" in checked and "Cube" in rendered
    assert emitter.name not in checked and emitter.name not in rendered
    assert 7 not in passes["IndexOB"] and 7 not in tables.object_index
    emitter.show_instancer_for_viewport = False
    emitter.show_instancer_for_render = True
    checked, rendered, passes, tables = counted(scene, tmp_path, monkeypatch)
    assert emitter.name in checked and emitter.name in rendered
    assert 7 in passes["IndexOB"] and 7 in tables.object_index


def test_rig_check_and_render_count_the_same_objects_in_a_mixed_scene(scene, tmp_path, monkeypatch):
    """Every case at once: the sets of objects are equal, not only the cube's fate."""
    add_mesh("cube", (-2, 1, 1), 4, (0.5, 0.5, 0.5)).hide_viewport = True
    add_mesh("cube", (2, 1, 1), 5, (0.5, 0.5, 0.5)).visible_camera = False
    add_mesh("cube", (-2, 3, 1), 6, (0.5, 0.5, 0.5)).hide_render = True
    particle_emitter(scene)
    checked, rendered, _passes, _tables = counted(scene, tmp_path, monkeypatch)
    assert checked == rendered


def test_object_disabled_in_renders_inside_an_instanced_collection_is_left_out(
    scene, tmp_path, monkeypatch
):
    """Unlike a particle's source object (above), an object disabled in renders does
    not show through a collection instance; the viewport's depsgraph holds it."""
    inner = bpy.data.collections.new("Inner")
    inner.objects.link(scene.objects["Cube"])
    scene.collection.objects.unlink(scene.objects["Cube"])
    holder = bpy.data.objects.new("Holder", None)
    holder.instance_type, holder.instance_collection = "COLLECTION", inner
    scene.collection.objects.link(holder)
    agree_with_cube(scene, tmp_path, monkeypatch)
    bpy.data.objects["Cube"].hide_render = True
    agree_without_cube(scene, tmp_path, monkeypatch)
