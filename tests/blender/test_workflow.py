"""The artist's workflow headless: camera list buttons, masks and their guides, the full
report, the field cache on disk, the ray preview and the background build job."""

import json
import struct
import zlib

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import mask_image
from fixtures.blender.scenes import two_camera_scene
from fixtures.masks import disk
from multiscale_camera.core.diagnostics import Diagnostics
from multiscale_camera.io import cache
from multiscale_camera.render import fields, pipeline
from multiscale_camera.ui import preview
from multiscale_camera.ui.mask_ops import _white


def operator_error(op, **kw):
    with pytest.raises(RuntimeError) as info:
        op(**kw)
    return str(info.value)


@pytest.fixture()
def cache_dir(tmp_path, monkeypatch):
    """A fresh disk cache for the test."""
    folder = tmp_path / "cache"
    monkeypatch.setattr(fields.SERVICE, "cache", cache.FieldCache(str(folder)))
    return folder


# --- camera list ----------------------------------------------------------------------


def test_select_and_look_through_a_listed_camera(empty_scene):
    scene = empty_scene
    c1, c2 = two_camera_scene(scene)
    scene.camera = c1
    assert bpy.ops.multiscale.camera_select(index=1) == {"FINISHED"}
    assert c2.select_get() and not c1.select_get()
    assert bpy.context.view_layer.objects.active == c2
    assert scene.multiscale.active_index == 1
    assert bpy.ops.multiscale.camera_view(index=1) == {"FINISHED"}
    assert scene.camera == c2
    scene.multiscale.cameras.add()  # an empty item
    msg = "This list item has no camera: pick one first"
    assert msg in operator_error(bpy.ops.multiscale.camera_select, index=2)
    assert msg in operator_error(bpy.ops.multiscale.camera_view, index=2)


# --- masks -------------------------------------------------------------------------------


def test_mask_new_makes_a_black_packed_mask_and_a_guide_of_the_cameras_view(empty_scene):
    scene = empty_scene
    c1, c2 = two_camera_scene(scene)
    scene.render.resolution_percentage = 50  # masks are made at the final size
    scene.multiscale.active_index = 1
    assert bpy.ops.multiscale.mask_new() == {"FINISHED"}
    item = scene.multiscale.cameras[1]
    mask = item.mask
    assert mask.name == "C2 mask" and tuple(mask.size) == (24, 18)
    assert mask.packed_file is not None
    px = np.empty(24 * 18 * 4, np.float32)
    mask.pixels.foreach_get(px)
    assert px.reshape(-1, 4)[:, :3].max() == 0.0
    guide = item.guide
    assert guide.name == "C2 guide" and guide.packed_file is not None
    gw, gh = guide.size
    rgba = np.empty(gw * gh * 4, np.float32)
    guide.pixels.foreach_get(rgba)
    rgba = rgba.reshape(gh, gw, 4)[::-1]  # row 0 at the top
    # independent check: Blender's own scene.ray_cast through the camera's view frame
    depsgraph = bpy.context.evaluated_depsgraph_get()
    frame = [c2.matrix_world @ v for v in c2.data.view_frame(scene=scene)]
    tr, br, bl, tl = frame  # view_frame: top-right, bottom-right, bottom-left, top-left
    eye = c2.matrix_world.translation
    colours = {
        o.name: np.array(
            o.data.materials[0].node_tree.nodes["Principled BSDF"].inputs[0].default_value[:3]
        )
        for o in scene.objects
        if o.type == "MESH"
    }
    agree = total = 0
    seen = set()
    for y in range(gh):
        for x in range(gw):
            u, v = (x + 0.5) / gw, (y + 0.5) / gh
            point = tl.lerp(tr, u).lerp(bl.lerp(br, u), v)
            hit, _loc, _n, _i, obj, _m = scene.ray_cast(depsgraph, eye, (point - eye).normalized())
            if not hit:
                continue
            total += 1
            seen.add(obj.name)
            want = colours[obj.name] / colours[obj.name].sum()
            got = rgba[y, x, :3] / max(rgba[y, x, :3].sum(), 1e-9)
            agree += np.abs(got - want).max() < 0.02
    assert total > 300 and len(seen) == 3 and agree / total > 0.97, (agree, total, seen)


def test_mask_new_needs_a_listed_camera(empty_scene):
    assert not bpy.ops.multiscale.mask_new.poll()
    msg = "Pick a camera in the Multiscale list first"
    assert msg in operator_error(bpy.ops.multiscale.mask_new)


def test_mask_paint_refuses_clearly_without_a_window(empty_scene):
    two_camera_scene(empty_scene)
    assert not bpy.ops.multiscale.mask_paint.poll()
    msg = "Painting needs a Blender window (not available in background)"
    assert msg in operator_error(bpy.ops.multiscale.mask_paint)


def test_masks_survive_save_and_reload(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.active_index = 1
    bpy.ops.multiscale.mask_new(guide=False)
    mask = scene.multiscale.cameras[1].mask
    white = disk(48, 36, 6)
    rgba = np.ones((36, 48, 4), np.float32)
    rgba[..., :3] = white[::-1, :, None]
    mask.pixels.foreach_set(rgba.ravel())
    mask.pack()
    path = tmp_path / "masks.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    bpy.ops.wm.open_mainfile(filepath=str(path))
    from multiscale_camera.adapters.scene import rig_from_scene

    rig = rig_from_scene(bpy.context.scene)
    np.testing.assert_array_equal(rig.masks[1], white)
    assert bpy.context.scene.multiscale.cameras[1].mask.packed_file is not None


def _png(path, grey):
    """A greyscale 8-bit PNG written by hand (zlib), as another tool would."""
    h, w = grey.shape
    raw = b"".join(b"\x00" + bytes(row) for row in grey.astype(np.uint8))

    def chunk(tag, data):
        body = tag + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def test_png_and_exr_masks_from_other_tools_load(empty_scene, tmp_path):
    import OpenEXR

    from multiscale_camera.adapters.scene import rig_from_scene

    scene = empty_scene
    two_camera_scene(scene)
    want = disk(48, 36, 7)
    _png(tmp_path / "m.png", np.where(want, 255, 0))
    scene.multiscale.cameras[1].mask = bpy.data.images.load(str(tmp_path / "m.png"))
    np.testing.assert_array_equal(rig_from_scene(scene).masks[1], want)
    grey = np.where(want, 1.0, 0.0).astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {"R": grey, "G": grey, "B": grey}
    with OpenEXR.File(header, channels) as f:
        f.write(str(tmp_path / "m.exr"))
    scene.multiscale.cameras[1].mask = bpy.data.images.load(str(tmp_path / "m.exr"))
    np.testing.assert_array_equal(rig_from_scene(scene).masks[1], want)
    # a mask from a file is packed: the .blend keeps working without the file
    assert scene.multiscale.cameras[1].mask.packed_file is not None
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "m.blend"))
    (tmp_path / "m.exr").unlink()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "m.blend"))
    np.testing.assert_array_equal(rig_from_scene(bpy.context.scene).masks[1], want)


# --- report ----------------------------------------------------------------------------


@pytest.mark.slow
def test_full_report_is_written_to_a_text(empty_scene, cache_dir):
    scene = empty_scene
    two_camera_scene(scene)
    assert not bpy.ops.multiscale.report_show.poll()
    bpy.ops.multiscale.compute_field()
    assert bpy.ops.multiscale.report_show() == {"FINISHED"}
    text = bpy.data.texts["Multiscale Report"].as_string()
    report = json.loads(scene.multiscale.report)
    assert text.startswith(
        f"SCALAR_FIELD: p95 error {max(c['preserved_px']['p95'] for c in report['cameras']):.2f} px"
    )
    for cam in report["cameras"]:
        assert f"'{cam['name']}': {cam['pixels']} preserved pixels measured" in text
    assert json.loads(text[text.index("{") :]) == report


# --- cache ----------------------------------------------------------------------------


@pytest.mark.slow
def test_disk_cache_hit_on_light_and_material_miss_on_mask_and_camera(empty_scene, cache_dir):
    scene = empty_scene
    c1, _c2 = two_camera_scene(scene)
    c = fields.SERVICE.cache
    assert pipeline.build_field(scene)[1] and (c.hits, c.misses) == (0, 1)
    assert len(list(cache_dir.glob("*.npz"))) == 1
    c.memory.clear()  # as after a restart: only the disk has it
    light = next(o for o in scene.objects if o.type == "LIGHT")
    light.rotation_euler.x += 0.3
    light.data.energy = 10.0
    bpy.data.materials[0].diffuse_color = (1, 0, 0, 1)
    bpy.context.view_layer.update()
    fld, built = pipeline.build_field(scene)
    assert not built and (c.hits, c.disk_hits, c.misses) == (1, 1, 1)
    assert not pipeline.build_field(scene)[1] and (c.hits, c.disk_hits) == (2, 1)
    scene.multiscale.cameras[1].mask = mask_image("other", disk(48, 36, 5))
    assert pipeline.build_field(scene)[1] and c.misses == 2
    c1.location.x += 0.05
    bpy.context.view_layer.update()
    assert pipeline.build_field(scene)[1] and c.misses == 3
    assert len(list(cache_dir.glob("*.npz"))) == 3
    assert bpy.ops.multiscale.cache_clear() == {"FINISHED"}
    assert list(cache_dir.glob("*.npz")) == [] and c.memory == {}


@pytest.mark.slow
def test_cache_folder_limit_comes_from_the_scene(empty_scene, cache_dir):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.cache_limit_mb = 16
    pipeline.build_field(scene)
    assert fields.SERVICE.cache.limit_mb == 16.0


# --- preview and background build ----------------------------------------------------------


@pytest.mark.slow
def test_preview_toggle_headless_computes_lines_without_drawing(empty_scene, cache_dir):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.show_preview = True
    shown = preview.PREVIEW
    assert shown.lines["count"] == 0  # no field yet: frusta only
    assert preview.note() == "Compute the field to see the rays; the frusta are shown"
    assert len(shown.lines["frusta"]) == 2 * (2 * 8 + 4)
    bpy.ops.multiscale.compute_field()  # the preview updates after the build
    lines = shown.lines
    assert lines["count"] == 12 * 9 and len(lines["rays"]) > 2 * lines["count"]
    assert shown.view_handler is None  # no GPU in background: nothing drawn
    scene.multiscale.show_preview = False
    assert shown.lines is None


@pytest.mark.slow
def test_background_build_hands_the_field_back_and_cancels(empty_scene, cache_dir):
    scene = empty_scene
    two_camera_scene(scene)
    service = fields.SERVICE
    request = service.request(scene)
    told = []
    service.add_listener(lambda _scene, fld: told.append(fld))
    try:
        job = fields.FieldBuild(request, measure=True)
        job.cancel()  # Esc before the first check: the build stops, nothing is stored
        job.launch()
        job._thread.join(60)
        assert job.cancelled and job.field is None
        assert service.finish(job) is None and told == []
        assert list(cache_dir.glob("*.npz")) == []
        job = service.start(request, measure=True)
        assert service.start(request) is job  # the same field: joined, not built twice
        job._thread.join(120)
        assert not job.cancelled and job.error is None
        result = service.finish(job)
        assert result.built and result.report["cameras"][1]["name"] == "C2"
        assert service.finish(job) is result and told == [result.field]  # once
        assert len(list(cache_dir.glob("*.npz"))) == 1 and service.running() is None
        again = service.get(service.request(scene))
        assert again.field is result.field and not again.built  # a cache hit needs no job
    finally:
        service._listeners.clear()
        service._listeners.append(preview.update)


@pytest.mark.slow
def test_two_callers_of_one_cached_field_keep_their_own_notices(empty_scene, cache_dir):
    """A cached field is shared: what one caller is told never reaches another, and
    nothing is written onto the field."""
    scene = empty_scene
    two_camera_scene(scene)
    service = fields.SERVICE
    first, second = Diagnostics(), Diagnostics()
    first.warn("only the first caller's")
    a = service.get(service.request(scene), first)
    b = service.get(service.request(scene), second)
    assert a.field is b.field and b.built is False
    assert "only the first caller's" in first.texts()
    assert "only the first caller's" not in second.texts()
    assert not hasattr(a.field, "notices")


def test_compute_field_checks_the_rig_first(empty_scene, cache_dir):
    scene = empty_scene
    _c1, c2 = two_camera_scene(scene)
    c2.data.type = "ORTHO"
    msg = (
        "Camera 'C2' is orthographic; multiscale rays need perspective cameras "
        "(Camera Properties > Lens > Type: Perspective)"
    )
    assert msg in operator_error(bpy.ops.multiscale.compute_field)
    assert json.loads(scene.multiscale.validation) == [{"level": "ERROR", "text": msg}]
    assert list(cache_dir.glob("*.npz")) == []


@pytest.mark.slow
def test_viewport_picture_is_the_render_at_sampled_pixels(empty_scene, cache_dir):
    from multiscale_camera.render import viewport

    scene = empty_scene
    two_camera_scene(scene)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    view = viewport.ViewDraw()
    assert viewport.frame_for_view(depsgraph, view) is None  # not cached: built in the background
    assert view.message == "Multiscale: building the ray field..."
    view.build._thread.join(120)
    assert fields.SERVICE._poll() is None and fields.SERVICE.running() is None
    frame = viewport.frame_for_view(depsgraph, view)
    assert frame is not None and "field (cached)" in frame.seconds
    small = viewport.preview_image(frame, max_width=20)
    ix, iy = viewport.preview_pixels(frame.size, 20)
    assert small.shape == (len(iy), 20, 4) and len(iy) == 15
    full = pipeline.render_rows(frame, 0, frame.size[1])["Combined"]
    np.testing.assert_allclose(small, full[np.ix_(iy, ix)], atol=1e-6)


@pytest.mark.slow
def test_a_cached_field_brings_its_report_back_from_disk(empty_scene, cache_dir, monkeypatch):
    scene = empty_scene
    two_camera_scene(scene)
    bpy.ops.multiscale.compute_field()
    first = json.loads(scene.multiscale.report)
    fields.SERVICE.cache.memory.clear()  # a new session: only the disk has the field

    def measure_again(*args, **kw):
        raise AssertionError("a cached field with its report is not measured again")

    monkeypatch.setattr(fields, "build_report", measure_again)
    bpy.ops.multiscale.compute_field()
    again = json.loads(scene.multiscale.report)
    assert fields.SERVICE.cache.disk_hits == 1 and again["cached"] is True
    assert again["cameras"] == first["cameras"] and again["folds"] == first["folds"]


def test_paint_colour_is_white_where_blender_5_keeps_it_per_paint_mode(empty_scene):
    ts = bpy.context.tool_settings
    holders = [
        h
        for h in (
            getattr(ts.image_paint, "unified_paint_settings", None),
            getattr(ts, "unified_paint_settings", None),
        )
        if h is not None
    ]
    assert holders  # one of the two exists in every Blender the extension supports
    for h in holders:
        h.color = (0.0, 0.0, 0.0)
    _white(ts)
    for h in holders:
        assert tuple(h.color) == (1.0, 1.0, 1.0) and tuple(h.secondary_color) == (0, 0, 0)


def test_painted_mask_survives_save_without_packing_by_hand(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.active_index = 1
    bpy.ops.multiscale.mask_new(guide=False)
    mask = scene.multiscale.cameras[1].mask
    white = disk(48, 36, 6)
    rgba = np.ones((36, 48, 4), np.float32)
    rgba[..., :3] = white[::-1, :, None]
    mask.pixels.foreach_set(rgba.ravel())  # as painting does: the packed copy is stale
    made = bpy.data.images.new("made here", 48, 36)  # painted, never saved anywhere
    ring = disk(48, 36, 0.3 * 48, inside=False)
    rgba[..., :3] = ring[::-1, :, None]
    made.pixels.foreach_set(rgba.ravel())
    scene.multiscale.cameras[0].mask = made
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "painted.blend"))
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "painted.blend"))
    from multiscale_camera.adapters.scene import rig_from_scene

    rig = rig_from_scene(bpy.context.scene)
    np.testing.assert_array_equal(rig.masks[1], white)
    np.testing.assert_array_equal(rig.masks[0], ring & ~white)


def test_preview_forgets_the_old_files_lines_on_load(empty_scene, cache_dir, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.show_preview = True
    assert preview.PREVIEW.lines is not None
    scene.multiscale.show_preview = False
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "off.blend"))
    scene.multiscale.show_preview = True
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "off.blend"))  # its preview is off
    assert preview.PREVIEW.lines is None
    bpy.context.scene.multiscale.show_preview = True
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "on.blend"))
    preview.PREVIEW.lines = None
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "on.blend"))  # on: drawn again
    assert preview.PREVIEW.lines["count"] == 0 and len(preview.PREVIEW.lines["frusta"])
