"""Fail safe: every failure of a render ends it with one message where the user looks,
writes nothing over the user's output file, and does not finish (the render operator
raises, ``multiscale.render`` is cancelled); a damaged or unusable cache is said and
worked around; the report is strict JSON, written after every build and cleared by a
failed one (docs/failures.md)."""

import json
import os

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import add_camera, mask_image
from fixtures.blender.scenes import two_camera_scene
from fixtures.masks import disk
from multiscale_camera.adapters.meshes import scene_geometry
from multiscale_camera.io.cache import FieldCache
from multiscale_camera.render import fields, pipeline, workers
from tests.exr import read_passes

FIX = "Object Properties > Transform (and its parents' transforms)"
KEEP = b"the user's own image"


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """The field service with a fresh disk cache in ``tmp_path / 'cache'``."""
    cache = FieldCache(str(tmp_path / "cache"))
    monkeypatch.setattr(fields.SERVICE, "cache", cache)
    return cache


@pytest.fixture
def scene(empty_scene, cache):
    two_camera_scene(empty_scene)
    empty_scene.multiscale.method = "IMAGE_BLEND"  # the cheapest build: these test failures
    return empty_scene


@pytest.fixture
def output(scene, tmp_path):
    """An existing output file the failing renders must not touch."""
    path = tmp_path / "existing.png"
    path.write_bytes(KEEP)
    scene.render.filepath = str(path)
    return path


def failed_render(op=None):
    """Render (write_still) through ``op`` (default ``bpy.ops.render.render``); the text
    of the RuntimeError Blender raised (the render did not finish)."""
    with pytest.raises(RuntimeError) as info:
        (op or bpy.ops.render.render)(write_still=True)
    return str(info.value)


def refused_everywhere(output, message):
    """The render, ``multiscale.render`` and Check Rig all refuse with ``message``; the
    output file is untouched and the camera list is the same."""
    names = [i.camera.name for i in bpy.context.scene.multiscale.cameras]
    assert f"Error: Multiscale: {message}" in failed_render()
    assert f"Error: {message}" in failed_render(bpy.ops.multiscale.render)
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.validate()
    assert f"Error: {message}" in str(info.value)  # Check Rig does not call it ready
    assert output.read_bytes() == KEEP
    assert [i.camera.name for i in bpy.context.scene.multiscale.cameras] == names


def test_zero_scale_camera_is_refused_and_the_output_kept(scene, output):
    scene.objects["C2"].scale = (0, 0, 0)
    refused_everywhere(
        output,
        "Camera 'C2' has a scale of zero on an axis (world scale (0, 0, 0)): give it a "
        f"non-zero scale, 1 is best, in {FIX}",
    )


def test_nan_camera_location_is_refused_and_the_output_kept(scene, output):
    scene.objects["C1"].location = (float("nan"), -14, 9)
    refused_everywhere(
        output,
        "Camera 'C1' has a location, rotation or scale that is not a number (NaN or "
        f"infinite): set its transform again in {FIX}",
    )


def test_mirrored_camera_is_refused_and_the_output_kept(scene, output):
    parent = bpy.data.objects.new("Flip", None)
    scene.collection.objects.link(parent)
    parent.scale = (1, -1, 1)
    scene.objects["C2"].parent = parent
    refused_everywhere(
        output,
        "Camera 'C2' is mirrored (a negative scale, its own or a parent's): its image "
        f"would be flipped; make every scale positive in {FIX}",
    )


def test_resolution_percentage_1_that_loses_a_mask_is_refused(empty_scene, cache, tmp_path):
    scene = empty_scene
    two_camera_scene(scene, 480, 360)
    scene.multiscale.method = "IMAGE_BLEND"
    # a disk of radius 20 px: at 1% (4x3) no pixel centre falls in it
    scene.multiscale.cameras[1].mask = mask_image("C2 small", disk(480, 360, 20))
    scene.render.resolution_percentage = 1
    out = tmp_path / "kept.png"
    out.write_bytes(KEEP)
    scene.render.filepath = str(out)
    refused_everywhere(
        out,
        "Mask 'C2 small' keeps no pixel at the render size 4x3: its white area is smaller "
        "than a pixel there; raise Output Properties > Format > Resolution (or its %), or "
        "widen the white area",
    )


def test_mask_with_its_shape_in_alpha_only_is_refused(scene, output):
    h, w = 36, 48
    img = bpy.data.images.new("alpha only", w, h, alpha=True)
    rgba = np.zeros((h, w, 4), np.float32)
    rgba[10:20, 10:30, 3] = 1.0
    img.pixels.foreach_set(rgba.ravel())
    scene.multiscale.cameras[1].mask = img
    refused_everywhere(
        output,
        "Mask 'alpha only' is black in colour and holds its shape in alpha only; masks are "
        "read from their colour (white: kept), not from alpha: paint the kept area white "
        "(Image editor, Paint mode), or save the image without alpha",
    )


def test_unexpected_engine_error_keeps_the_output_and_is_one_message(scene, output, monkeypatch):
    def broken(*_a, **_k):
        raise ZeroDivisionError("a defect")

    monkeypatch.setattr(pipeline, "prepare_frame", broken)
    said = failed_render()
    assert (
        "Error: Multiscale: The render failed (ZeroDivisionError: a defect); nothing was "
        "written; the details are in the system console (Window > Toggle System Console)"
    ) in said
    assert "Traceback" not in said
    assert output.read_bytes() == KEEP
    assert "Traceback" not in failed_render(bpy.ops.multiscale.render)


def test_error_after_tiles_were_written_keeps_the_output(scene, output, monkeypatch):
    real = workers.render_tiles

    def fails_midway(*args):
        for n, tile in enumerate(real(*args)):
            if n == 1:
                raise MemoryError("no room for the next tile")
            yield tile

    monkeypatch.setattr(pipeline, "rows_per_tile", lambda *a, **k: 4)
    monkeypatch.setattr(workers, "render_tiles", fails_midway)
    assert "The render failed (MemoryError: no room for the next tile)" in failed_render()
    assert output.read_bytes() == KEEP


def test_unwritable_render_filepath_is_a_message_not_a_traceback(scene):
    scene.render.filepath = "/proc/no such folder/out.png"
    said = failed_render(bpy.ops.multiscale.render)
    assert said == (
        "Error: Render error (No such file or directory) cannot save: "
        "'/proc/no such folder/out.png'\n"
    )


def entry_of(cache):
    (path,) = [p for p, _s, _t in cache.entries()]
    return path


def test_damaged_cache_entry_that_loads_is_deleted_rebuilt_and_said(scene, cache, tmp_path, capfd):
    scene.render.filepath = str(tmp_path / "first.png")
    bpy.ops.render.render(write_still=True)
    path = entry_of(cache)
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    name = next(k for k, a in arrays.items() if a.dtype.kind == "f" and a.size > 100)
    arrays[name] = arrays[name] + np.float32(0.25)  # damaged, yet it unzips and loads
    np.savez(path, **arrays)
    cache.memory.clear()
    capfd.readouterr()
    scene.render.filepath = str(tmp_path / "second.png")
    bpy.ops.render.render(write_still=True)
    assert (
        f"The cached field '{os.path.basename(path)}' was damaged (its arrays do not match "
        "their checksum): it was deleted and the field is built again"
    ) in capfd.readouterr().out
    assert (tmp_path / "second.png").is_file()
    cache.memory.clear()  # the rebuilt entry is whole: read back without a word
    again = FieldCache(cache.folder)
    assert again.get(os.path.basename(path)[:-4], fields.SERVICE.request(scene).rig) is not None
    assert again.take_notices() == []


def test_cache_folder_that_is_a_file_falls_back_to_memory(scene, tmp_path, monkeypatch, capfd):
    blocker = tmp_path / "cache is a file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("MULTISCALE_CACHE_DIR", str(blocker))
    monkeypatch.setattr(fields.SERVICE, "cache", FieldCache(lazy_folder=True))
    scene.render.filepath = str(tmp_path / "out.png")
    bpy.ops.render.render(write_still=True)
    assert (
        f"The field cache folder '{blocker}' cannot be used (File exists): fields are kept "
        "in memory only, for this session; point $MULTISCALE_CACHE_DIR at a writable folder"
    ) in capfd.readouterr().out
    assert (tmp_path / "out.png").is_file() and len(fields.SERVICE.cache.memory) == 1


def test_f12_writes_strict_json_report_and_a_failed_build_clears_it(scene, tmp_path):
    scene.multiscale.report = ""
    scene.render.filepath = str(tmp_path / "out.png")
    bpy.ops.render.render(write_still=True)
    report = json.loads(
        scene.multiscale.report, parse_constant=lambda c: pytest.fail(f"{c} in the report")
    )
    assert report["method"] == "IMAGE_BLEND" and [c["name"] for c in report["cameras"]] == [
        "C1",
        "C2",
    ]
    assert report["cached"] is False
    # the build measured the visible surface for its warning: the report keeps it too
    # (IMAGE_BLEND's preserved rays are exact, so the hits land on their pixels)
    assert all(c["surface_pixels"] > 0 for c in report["cameras"])
    assert all(c["surface_px"]["p95"] < 0.01 for c in report["cameras"])
    scene.objects["C2"].scale = (0, 0, 0)
    failed_render()
    assert scene.multiscale.report == ""


def test_compute_field_with_an_empty_middle_mask_reports_it_unmeasured(scene, cache):
    mid = add_camera(scene, "Mid", (0.3, -8, 6), (0.5, -0.3, 1.8), clip_start=3.0)
    item = scene.multiscale.cameras.add()
    item.camera = mid
    item.mask = mask_image("black", np.zeros((36, 48), bool))
    scene.multiscale.cameras.move(2, 1)
    assert bpy.ops.multiscale.compute_field() == {"FINISHED"}
    report = json.loads(scene.multiscale.report)
    assert report["cameras"][1]["unmeasured"] == (
        "its mask is empty: no preserved pixel to measure"
    )
    assert report["cameras"][1]["preserved_px"] == {"p50": None, "p95": None, "max": None}
    assert len(cache.entries()) == 1  # the built field is kept
    assert bpy.ops.multiscale.compute_field() == {"FINISHED"}
    assert json.loads(scene.multiscale.report)["cached"] is True


def test_rig_check_leaves_out_hide_render_objects_as_the_render_does(scene):
    scene.objects["Cube"].hide_render = True
    names = scene_geometry(bpy.context.evaluated_depsgraph_get()).object_names
    assert "Cube" not in names and "Plane" in names


def test_sixteen_bit_and_float_masks_read_as_eight_bit_ones(scene, tmp_path):
    from PIL import Image

    from multiscale_camera.adapters.scene import rig_from_scene

    want = disk(48, 36, 7)
    Image.fromarray(np.where(want, 65535, 0).astype(np.uint16)).save(tmp_path / "m16.png")
    scene.multiscale.cameras[1].mask = bpy.data.images.load(str(tmp_path / "m16.png"))
    assert scene.multiscale.cameras[1].mask.is_float  # Blender reads 16 bits as float
    np.testing.assert_array_equal(rig_from_scene(scene).masks[1], want)
    img = bpy.data.images.new("float mask", 48, 36, float_buffer=True)
    rgba = np.ones((36, 48, 4), np.float32)
    rgba[..., :3] = np.where(want, 4.0, -1.0)[::-1, :, None]  # out of [0, 1], as floats may be
    img.pixels.foreach_set(rgba.ravel())
    scene.multiscale.cameras[1].mask = img
    np.testing.assert_array_equal(rig_from_scene(scene).masks[1], want)


def test_identical_camera_objects_render_with_the_order_warning(scene, output, capfd):
    twin = scene.objects["C1"].copy()
    twin.data = scene.objects["C1"].data.copy()
    twin.name = "C1 twin"
    scene.collection.objects.link(twin)
    item = scene.multiscale.cameras.add()
    item.camera = twin
    item.mask = mask_image("twin mask", disk(48, 36, 3))
    scene.multiscale.cameras[1].mask = mask_image("C2 ring", disk(48, 36, 7) & ~disk(48, 36, 4))
    bpy.ops.render.render(write_still=True)
    assert (
        "The near plane of 'C1 twin' lies before the near plane of 'C2': the list should "
        "run from the largest scale to the smallest"
    ) in capfd.readouterr().out
    assert output.read_bytes() != KEEP
    report = json.loads(  # strict JSON even for twins
        scene.multiscale.report, parse_constant=lambda c: pytest.fail(f"{c} in the report")
    )
    assert [c["name"] for c in report["cameras"]] == ["C1", "C2", "C1 twin"]


def test_compute_field_and_export_rays_say_an_unexpected_error(scene, tmp_path, monkeypatch):
    scene.multiscale.report = '{"version": 1}'

    def broken(*_a, **_k):
        raise KeyError("lost")

    monkeypatch.setattr(fields, "prepare", broken)
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.compute_field()
    assert str(info.value).startswith("Error: Compute Field failed (KeyError: 'lost'); nothing")
    assert scene.multiscale.report == ""  # the old report is not left standing
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.export_rays(filepath=str(tmp_path / "rays.exr"))
    assert str(info.value).startswith("Error: Export Rays failed (KeyError: 'lost'); nothing")
    assert not (tmp_path / "rays.exr").exists()


def test_rig_check_leaves_out_instances_of_a_hide_render_instancer(scene):
    inner = bpy.data.collections.new("Inner")
    inner.objects.link(scene.objects["Cube"])
    scene.collection.objects.unlink(scene.objects["Cube"])
    holder = bpy.data.objects.new("Holder", None)
    holder.instance_type, holder.instance_collection = "COLLECTION", inner
    scene.collection.objects.link(holder)
    bpy.context.view_layer.update()
    assert "Cube" in scene_geometry(bpy.context.evaluated_depsgraph_get()).object_names
    holder.hide_render = True
    bpy.context.view_layer.update()
    assert "Cube" not in scene_geometry(bpy.context.evaluated_depsgraph_get()).object_names


def test_viewport_picture_says_a_bad_rig_or_a_defect_instead_of_a_traceback(scene, monkeypatch):
    from multiscale_camera.render import viewport

    view = viewport.ViewDraw()
    scene.objects["C2"].scale = (0, 0, 0)
    assert viewport.frame_for_view(bpy.context.evaluated_depsgraph_get(), view) is None
    assert view.message == (
        "Multiscale: Camera 'C2' has a scale of zero on an axis (world scale (0, 0, 0)): "
        f"give it a non-zero scale, 1 is best, in {FIX}"
    )
    scene.objects["C2"].scale = (1, 1, 1)

    def broken(*_a, **_k):
        raise IndexError("a defect")

    monkeypatch.setattr(fields.SERVICE, "request", broken)
    assert viewport.frame_for_view(bpy.context.evaluated_depsgraph_get(), view) is None
    assert view.message.startswith(
        "Multiscale: The viewport picture failed (IndexError: a defect); nothing was written"
    )


def test_viewport_picture_refuses_a_build_past_the_memory_budget(scene, monkeypatch):
    """Rendered shading starts no build whose estimate passes the budget, and says so on
    the picture; its own small picture is not weighed as a full-size render."""
    from multiscale_camera.render import viewport

    started = []
    monkeypatch.setattr(fields.SERVICE, "start", lambda request: started.append(request))
    view = viewport.ViewDraw()
    scene.render.resolution_x = scene.render.resolution_y = 4000
    scene.multiscale.memory_budget_mb = 64
    assert viewport.frame_for_view(bpy.context.evaluated_depsgraph_get(), view) is None
    assert view.message.startswith("Multiscale: The field build would need about "), view.message
    assert "more than the budget of 64 MB (the scene's Memory Budget)" in view.message
    assert not started

    # a cached field: the frame goes on to the field, not refused as a 4000x4000 render
    def reached(*_a, **_k):
        raise LookupError("reached the field")

    monkeypatch.setattr(fields.SERVICE, "cached", lambda _request: object())
    monkeypatch.setattr(fields.SERVICE, "get", reached)
    scene.multiscale.memory_budget_mb = 512  # a 4000x4000 render would need 1.1 GB
    assert viewport.frame_for_view(bpy.context.evaluated_depsgraph_get(), view) is None
    assert "(LookupError: reached the field)" in view.message, view.message


def test_export_rays_is_not_refused_as_a_render(scene, monkeypatch, tmp_path):
    """Export Rays renders nothing: only its build is weighed, not a full-size render."""

    def reached(*_a, **_k):
        raise LookupError("reached the field")

    monkeypatch.setattr(fields.SERVICE, "cached", lambda _request: object())
    monkeypatch.setattr(fields.SERVICE, "get", reached)
    scene.render.resolution_x = scene.render.resolution_y = 4000
    scene.multiscale.memory_budget_mb = 512  # a 4000x4000 render would need 1.1 GB
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.export_rays(filepath=str(tmp_path / "rays.exr"))
    assert "(LookupError: reached the field)" in str(info.value), str(info.value)
    assert not (tmp_path / "rays.exr").exists()


def render_passes(scene, path):
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_passes(path)


def test_rig_check_leaves_out_collections_disabled_in_renders(scene, tmp_path):
    hidden = bpy.data.collections.new("Hidden")
    scene.collection.children.link(hidden)
    inner = bpy.data.collections.new("Inner")  # inside it: hidden too
    hidden.children.link(inner)
    inner.objects.link(scene.objects["Cube"])
    scene.collection.objects.unlink(scene.objects["Cube"])
    bpy.context.view_layer.update()
    assert "Cube" in scene_geometry(bpy.context.evaluated_depsgraph_get()).object_names
    hidden.hide_render = True
    bpy.context.view_layer.update()
    assert "Cube" not in scene_geometry(bpy.context.evaluated_depsgraph_get()).object_names
    index = render_passes(scene, tmp_path / "hidden.exr")["IndexOB"]
    assert 1 in index and 2 not in index  # the render leaves the cube (pass index 2) out too
    scene.collection.objects.link(bpy.data.objects["Cube"])  # also shown elsewhere: kept
    bpy.context.view_layer.update()
    assert "Cube" in scene_geometry(bpy.context.evaluated_depsgraph_get()).object_names
