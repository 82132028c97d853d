"""Cycles hand-off (shading = 'CYCLES'): against plain Cycles renders of the rig's cameras."""

import os
import tempfile
import time
import types

import bpy
import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from fixtures.blender.handoff import cycles_settings, handoff_reports
from fixtures.blender.objects import add_camera, add_mesh, mask_image
from fixtures.blender.scenes import shapes_and_sun, three_camera_scene, two_camera_scene
from multiscale_camera.io.exr import read_channels
from multiscale_camera.render import cycles, cycles_rays, cycles_shader, workers
from tests.exr import read_passes

pytestmark = pytest.mark.skipif(
    cycles.unsupported_reason() is not None, reason="needs Blender 4.5+ with Cycles and OSL"
)


def render(scene, path, engine, camera=None, seed=0):
    """Render ``scene`` with ``engine`` (from ``camera``), return its passes."""
    scene.render.engine = engine
    scene.cycles.seed = seed
    if camera is not None:
        scene.camera = camera
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_passes(path)


def rms(a, b):
    """RMS difference of the Combined colour of two renders' passes."""
    return float(np.sqrt(np.mean((a["Combined"][..., :3] - b["Combined"][..., :3]) ** 2)))


def test_one_camera_full_mask_matches_plain_cycles(empty_scene, tmp_path):
    """One camera, every pixel preserved: the hand-off is a plain Cycles render of that
    camera, up to Cycles' own noise (measured between two seeds)."""
    scene = empty_scene
    width, height = 64, 48
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    shapes_and_sun(scene)
    cam = add_camera(scene, "C1", (1.0, -9.0, 5.0), (0, 0, 0.6), clip_start=3.0)
    item = scene.multiscale.cameras.add()
    item.camera = cam
    item.mask = mask_image("full", np.ones((height, width), bool))
    scene.camera = cam
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=16)
    bpy.context.view_layer.update()
    plain0 = render(scene, tmp_path / "plain0.exr", "CYCLES", seed=0)
    plain1 = render(scene, tmp_path / "plain1.exr", "CYCLES", seed=1)
    with handoff_reports() as reports:
        handoff0 = render(scene, tmp_path / "handoff0.exr", "MULTISCALE", seed=0)
        handoff1 = render(scene, tmp_path / "handoff1.exr", "MULTISCALE", seed=1)
    noise = rms(plain0, plain1)
    print("noise", noise, rms(handoff0, plain1), rms(handoff1, plain0), rms(handoff0, plain0))
    assert noise > 1e-4  # the scene is noisy enough for the comparison to mean something
    # against the other seed, the hand-off differs by Cycles' noise and no more
    assert rms(handoff0, plain1) <= 1.1 * noise
    assert rms(handoff1, plain0) <= 1.1 * noise
    # with the same seed (same sub-pixel jitter) it is the same image: every block of
    # pixels shows camera 1's own rays, which the custom camera computes at each jittered
    # sub-pixel position as Cycles' own camera does (the table's interpolated rays alone
    # gave a difference of up to a tenth of the noise)
    assert len(reports) == 2 and all(report.share == 1.0 for report in reports)
    assert list(reports[0].seconds()) == ["march", "tables", "cycles", "passes"]
    assert rms(handoff0, plain0) <= 1e-3 * noise
    mean_gap = abs(handoff0["Combined"][..., :3].mean() - plain1["Combined"][..., :3].mean())
    assert mean_gap <= 0.01 * plain1["Combined"][..., :3].mean()
    print("idx agree", (handoff0["IndexOB"] == plain0["IndexOB"]).mean())
    assert (handoff0["IndexOB"] == plain0["IndexOB"]).mean() >= 0.99


@pytest.mark.slow
def test_three_cameras_object_index_agrees_in_preserved_regions(empty_scene, tmp_path):
    """In each camera's eroded mask, Cycles' Object Index through the bent rays equals
    the object a plain Cycles render of that camera sees, for >= 99% of the pixels, and
    the colour there is that render's, up to Cycles' noise between two seeds."""
    scene = empty_scene
    width, height = 160, 90
    cams, masks = three_camera_scene(scene, width, height)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=16)
    handoff = render(scene, tmp_path / "handoff.exr", "MULTISCALE", camera=cams[0])
    index = handoff["IndexOB"][..., 0]
    for i, (cam, mask) in enumerate(zip(cams, masks, strict=True)):
        plain = render(scene, tmp_path / f"plain{i}.exr", "CYCLES", camera=cam)
        other_seed = render(scene, tmp_path / f"seed{i}.exr", "CYCLES", camera=cam, seed=1)
        eroded = binary_erosion(mask, iterations=2)
        assert eroded.sum() > 100
        agree = (index == plain["IndexOB"][..., 0])[eroded]
        print(f"{cam.name}: IndexOB agreement {agree.mean():.4f} of {eroded.sum()} px")
        assert agree.mean() >= 0.99, f"{cam.name}: {agree.mean():.4f}"
        # the comparison sees several objects, not only one
        assert len(np.unique(plain["IndexOB"][..., 0][eroded])) >= 2

        def colour(passes, eroded=eroded):
            return passes["Combined"][..., :3][eroded]

        noise = np.sqrt(np.mean((colour(plain) - colour(other_seed)) ** 2))
        gap = np.sqrt(np.mean((colour(handoff) - colour(other_seed)) ** 2))
        print(f"{cam.name}: colour RMS {gap:.5f} against seed noise {noise:.5f}")
        assert gap <= 1.1 * noise, f"{cam.name}: {gap} > 1.1 x {noise}"
    assert set(np.unique(index)) >= {0.0, 1.0, 2.0, 3.0, 4.0, 5.0}
    assert handoff["Depth"].min() > 0 and handoff["Membership"].max() > 2.5


@pytest.mark.slow
def test_rays_blocked_before_the_plane_come_from_the_origin_and_direction_tables(
    empty_scene, tmp_path, monkeypatch
):
    """A small box around camera 2's eye, well inside its clip distance (camera 2 never
    sees it), lies on every camera 2 ray's line between the two-plane table's plane and
    the ray's origin: those rays are marked in the two-plane table and read from the
    origin and direction tables. Camera 2's region shows what our march found there,
    which is what a plain render of camera 2 shows wherever the bent rays do not
    themselves pass through the box."""
    scene = empty_scene
    width, height = 160, 90
    cams, masks = three_camera_scene(scene, width, height)
    add_mesh("cube", tuple(cams[1].location), 9, (1.0, 1.0, 1.0), size=0.4)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=16)
    written = []
    write_tables = cycles.write_tables

    def recording(folder, tables, *args, **kw):
        params = write_tables(folder, tables, *args, **kw)
        channels, _ = read_channels(params["ray_table"])
        inner = (slice(cycles_rays.PAD, -cycles_rays.PAD),) * 2
        limit = cycles_rays.UNUSABLE_LIMIT
        marked = np.abs(np.stack([channels[c][inner] for c in "RGBA"])) > limit
        written.append((dict(params), marked.all(axis=0), tables.object_index))
        return params

    monkeypatch.setattr(cycles, "write_tables", recording)
    handoff = render(scene, tmp_path / "handoff.exr", "MULTISCALE", camera=cams[0])
    params, marked, marched = written[0]
    assert params["origin_table"] and params["direction_table"]
    eroded = binary_erosion(masks[1], iterations=2)
    print(f"marked: {marked.mean():.3f} of all pixels, {marked[eroded].mean():.3f} of C2's")
    assert marked[eroded].mean() > 0.9 and marked[masks[0]].mean() < 0.1
    index = handoff["IndexOB"][..., 0]
    assert (index == marched)[eroded].mean() >= 0.99
    plain = render(scene, tmp_path / "plain.exr", "CYCLES", camera=cams[1])
    clear = eroded & (marched != 9)
    agree = (index == plain["IndexOB"][..., 0])[clear]
    print(f"C2: IndexOB agreement {agree.mean():.4f} of {clear.sum()} px")
    assert clear.sum() > 0.9 * eroded.sum() and agree.mean() >= 0.99


def snapshot(scene):
    """What the user made that the hand-off could touch."""
    cams = [o for o in scene.objects if o.type == "CAMERA"]
    return {
        "cameras": [
            (
                o.name,
                o.data.type,
                o.data.clip_start,
                o.data.clip_end,
                o.data.custom_mode,
                o.data.custom_shader,
                o.data.custom_bytecode,
                dict(o.data.cycles_custom),
                tuple(map(tuple, o.matrix_world)),
            )
            for o in cams
        ],
        "camera": scene.camera.name,
        "engine": scene.render.engine,
        "device": scene.cycles.device,
        "denoise": scene.cycles.use_denoising,
        "samples": scene.cycles.samples,
        "texts": sorted(bpy.data.texts.keys()),
        "objects": sorted(bpy.data.objects.keys()),
        "cameras_data": sorted(bpy.data.cameras.keys()),
        "index_pass": bpy.context.view_layer.use_pass_object_index,
        "z_pass": bpy.context.view_layer.use_pass_z,
    }


def leftover_tables():
    return [n for n in os.listdir(tempfile.gettempdir()) if n.startswith("multiscale-cycles-")]


def test_handoff_leaves_the_users_scene_as_it_was(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=2)
    scene.cycles.use_denoising = True
    scene.cycles.device = "GPU"
    before_tables = leftover_tables()
    before = snapshot(scene)
    passes = render(scene, tmp_path / "a.exr", "MULTISCALE")
    assert snapshot(scene) == before
    assert leftover_tables() == before_tables
    assert passes["Combined"][..., 3].min() == 1.0
    assert set(np.unique(passes["IndexOB"])) >= {1.0, 2.0, 3.0}


def test_handoff_failure_is_reported_and_leaves_the_scene(empty_scene, tmp_path, monkeypatch):
    """A shader that does not compile: the render fails with a message; nothing changed."""
    scene = empty_scene
    two_camera_scene(scene)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=1)
    before = snapshot(scene)
    before_tables = leftover_tables()
    broken = tmp_path / "broken.osl"
    broken.write_text("shader broken( {")
    monkeypatch.setattr(cycles_shader, "OSL_PATH", str(broken))
    scene.render.filepath = str(tmp_path / "b.exr")
    with pytest.raises(RuntimeError) as info:
        bpy.ops.render.render(write_still=True)
    assert (
        "Multiscale: Cycles hand-off failed: the custom camera's OSL shader did not compile"
        in str(info.value)
    )
    assert snapshot(scene) == before
    assert leftover_tables() == before_tables


@pytest.mark.slow
def test_handoff_cancelled_during_the_march_leaves_the_scene(empty_scene, tmp_path, monkeypatch):
    """Esc while the rays are marched: Cycles never starts, the tables are removed."""
    scene = empty_scene
    two_camera_scene(scene, 96, 72)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=1)
    before = snapshot(scene)
    before_tables = leftover_tables()
    started = []
    monkeypatch.setattr(cycles, "_run_cycles", lambda *a: started.append(a))
    calls = []
    march_tables = cycles.ray_tables

    def stop_at_second_check():
        calls.append(1)
        return len(calls) >= 2

    def tables_with_esc(frame, _should_stop, progress=None):
        return march_tables(frame, stop_at_second_check, progress)

    monkeypatch.setattr(cycles, "ray_tables", tables_with_esc)
    scene.render.engine = "MULTISCALE"
    with handoff_reports() as reports:
        bpy.ops.render.render()
    assert len(calls) == 2 and not started
    assert reports == [cycles.HandoffReport()]  # no stage finished
    assert snapshot(scene) == before
    assert leftover_tables() == before_tables


def test_unsupported_blender_says_why():
    assert cycles.unsupported_reason((4, 2, 0)) == (
        "Cycles shading needs Blender 4.5 or later (OSL custom cameras); this is Blender 4.2.0"
    )
    assert cycles.unsupported_reason((4, 5, 0)) is None
    assert cycles.index_pass_name((4, 5, 0)) == "IndexOB"
    assert cycles.index_pass_name((5, 0, 1)) == "Object Index"


def test_disabled_cycles_addon_says_why():
    import addon_utils

    addon_utils.disable("cycles")
    try:
        assert cycles.unsupported_reason() == (
            "Cycles shading needs the Cycles add-on: enable it in Preferences > Add-ons"
        )
    finally:
        addon_utils.enable("cycles", default_set=True)
    assert cycles.unsupported_reason() is None


def test_without_the_handoff_the_engine_renders_solid(empty_scene, tmp_path, monkeypatch):
    """Where the hand-off cannot run (older Blender), CYCLES renders as SOLID does."""
    scene = empty_scene
    two_camera_scene(scene)
    cycles_settings(scene, samples=1)
    solid = render(scene, tmp_path / "solid.exr", "MULTISCALE")
    scene.multiscale.shading = "CYCLES"
    monkeypatch.setattr(cycles, "unsupported_reason", lambda version=None: "too old")
    fallback = render(scene, tmp_path / "fallback.exr", "MULTISCALE")
    assert np.array_equal(solid["Combined"], fallback["Combined"])


@pytest.mark.slow
@pytest.mark.parametrize("crop", [True, False])
def test_border_render_keeps_our_depth_in_the_border(empty_scene, tmp_path, crop):
    """A render border: the result is the border's pixels; Depth and Membership there
    are the full render's (the write-back used to assume the whole image)."""
    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=1)
    full = render(scene, tmp_path / "full.exr", "MULTISCALE")
    render_settings = scene.render
    render_settings.use_border, render_settings.use_crop_to_border = True, crop
    render_settings.border_min_x, render_settings.border_max_x = 0.25, 0.75
    render_settings.border_min_y, render_settings.border_max_y = 0.1, 0.6
    part = render(scene, tmp_path / "part.exr", "MULTISCALE")
    # x 16..47; y 4..27 counted from the bottom, so rows 48-28 .. 48-5 from the top
    window = (slice(20, 44), slice(16, 48))
    if crop:
        assert part["Depth"].shape == (24, 32, 1)
    else:
        assert part["Depth"].shape == (48, 64, 1)
        part = {name: data[window] for name, data in part.items()}
    for name in ("Depth", "Membership", "IndexOB"):
        np.testing.assert_array_equal(part[name], full[name][window], err_msg=name)


class RecordingLayout:
    """Stands in for a panel's UILayout: records prop and label calls."""

    def __init__(self, calls=None):
        self.calls = [] if calls is None else calls

    def prop(self, data, name, **kw):
        self.calls.append(("prop", name))

    def label(self, text="", **kw):
        self.calls.append(("label", text))

    def operator(self, idname, **kw):
        self.calls.append(("operator", idname))
        return type("Props", (), {})()

    def __getattr__(self, name):  # row, column, box, template_*, separator, scale_y ...
        return lambda *a, **kw: RecordingLayout(self.calls)


def draw_panel(context):
    from multiscale_camera.ui.panels import MULTISCALE_PT_main

    panel = type("Panel", (), {"layout": RecordingLayout()})()
    MULTISCALE_PT_main.draw(panel, context)
    return panel.layout.calls


def test_panel_offers_cycles_only_where_supported(empty_scene, monkeypatch):
    calls = draw_panel(bpy.context)
    assert ("prop", "shading") in calls
    assert ("operator", "multiscale.export_rays") in calls
    reason = "Cycles shading needs Blender 4.5 or later (OSL custom cameras); this is Blender 4.2.0"
    monkeypatch.setattr(cycles, "unsupported_reason", lambda version=None: reason)
    calls = draw_panel(bpy.context)
    assert ("prop", "shading") not in calls and ("label", reason) in calls


def test_tiled_cycles_render_is_not_lost(empty_scene, tmp_path):
    """An image larger than Cycles' tile size (auto tiling): Cycles keeps the tiles on
    disk until render_frame_finish; the hand-off must call it or the image is black."""
    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=2)
    whole = render(scene, tmp_path / "whole.exr", "MULTISCALE")
    scene.cycles.use_auto_tile, scene.cycles.tile_size = True, 16
    tiled = render(scene, tmp_path / "tiled.exr", "MULTISCALE")
    assert whole["Combined"][..., :3].mean() > 0.01
    np.testing.assert_array_equal(tiled["Combined"], whole["Combined"])
    np.testing.assert_array_equal(tiled["IndexOB"], whole["IndexOB"])


def test_handoff_says_when_its_march_workers_were_given_up(
    empty_scene, tmp_path, monkeypatch, capfd
):
    """The hand-off's tables, marched in workers that stalled, were marched again in
    Blender's process without a word; the render now says why it was slow."""
    from multiscale_camera.core.runtime import pool
    from multiscale_camera.render import pipeline, tables

    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=1)
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 2
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 8)
    monkeypatch.setattr(pool, "STALL_SECONDS", 0.5)
    # the workers' tiles hang without a beat (the tiles marched here do not)
    monkeypatch.setattr(tables, "_march_tile", _hang)
    start = time.perf_counter()
    passes = render(scene, tmp_path / "a.exr", "MULTISCALE")
    assert time.perf_counter() - start < 30.0
    assert f"Multiscale: {pipeline.WORKERS_GIVEN_UP}" in capfd.readouterr().out
    assert set(np.unique(passes["IndexOB"])) >= {1.0, 2.0, 3.0}


def _hang(*args):
    """A render worker's tile that neither ends for half a minute nor beats."""
    time.sleep(30)


@pytest.mark.parametrize("samples", [1, 16, 128, 1024, 4096, 1 << 20])
def test_cycles_tiles_are_small_enough_to_hear_esc_and_ctrl_c(samples):
    """Cycles hears Esc and Ctrl-C only between its batches, which never span a tile:
    the hand-off's tiles hold at most TILE_PIXEL_SAMPLES pixel samples (a tile a side
    larger would hold more), never less than MIN_TILE px a side."""
    tile = cycles.cancel_tile(samples)
    assert tile >= cycles.MIN_TILE
    if tile > cycles.MIN_TILE:
        assert tile * tile * samples <= cycles.TILE_PIXEL_SAMPLES
    assert (tile + 1) ** 2 * samples > cycles.TILE_PIXEL_SAMPLES
    assert cycles.cancel_tile(samples, tile_size=cycles.MIN_TILE) == cycles.MIN_TILE


class _WindowApp:
    """``bpy.app`` as a render in Blender's window sees it (not in background mode)."""

    background = False

    def __getattr__(self, name):
        return getattr(bpy.app, name)


def test_a_render_in_the_window_is_tiled_as_headless(empty_scene, tmp_path, monkeypatch):
    """In the window Cycles heard Esc only between batches of 1 to 2 s of work (15 s
    after the first 10 s of a render), untiled: the hand-off now tiles there too.

    The image is one tile (32 px at 128 samples). At 64x48, in four tiles, this was the
    only in-process render of several tiles, and the bpy wheel's Cycles crashed in it
    (a segmentation fault in the hand-off's call of Cycles) in 3 of about 20 runs of
    ``make test-quick``, never alone and never in a single-tile render. Renders of
    several tiles run in a process of their own (``tests/e2e/test_interrupt_stages.py``,
    1024 samples: 11 px tiles)."""
    scene = empty_scene
    two_camera_scene(scene, 32, 24)
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, samples=128)
    window = types.SimpleNamespace(**{k: getattr(bpy, k) for k in ("data", "types", "props")})
    window.app = _WindowApp()
    monkeypatch.setattr(cycles, "bpy", window)
    seen = []
    run = cycles._run_cycles

    def recording(engine, depsgraph, data):
        settings = depsgraph.scene_eval.cycles
        seen.append((settings.use_auto_tile, settings.tile_size))
        return run(engine, depsgraph, data)

    monkeypatch.setattr(cycles, "_run_cycles", recording)
    passes = render(scene, tmp_path / "window.exr", "MULTISCALE")
    assert seen == [(True, cycles.cancel_tile(128))]  # 32 px: 2^17 pixel samples
    assert scene.cycles.tile_size == 2048  # the user's own, kept
    assert passes["Combined"][..., :3].mean() > 0.01
