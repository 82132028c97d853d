"""Animated rigs: every frame of an animation render is rendered with that frame's
cameras (transform and lens as the render's depsgraph evaluates them), in
``render(animation=True)`` and in ``blender -b file -s A -e B -a``; a static rig renders
identical frames.

The reference is written here, independently of the extension: for each frame and each
camera, Blender's own ``view_frame`` of the camera evaluated at that frame and
``scene.ray_cast`` along its straight pinhole rays from the near plane, one pixel at a
time; the object it hits is compared with the render's IndexOB in the camera's mask
eroded by 2 px (the hidden-surface agreement of docs/report.md's metrics)."""

import json
import math
from dataclasses import replace

import bpy
import numpy as np
import pytest
from mathutils import Vector

from fixtures.blender import samples
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.scene import rig_from_scene
from multiscale_camera.core.field import choose_grid, steady_grid, steady_levels
from multiscale_camera.core.methods import FrameReuse, frame_levels, plan_shot
from multiscale_camera.core.quality import erode
from multiscale_camera.render import fields, pipeline
from multiscale_camera.render.raycast import march
from tests.conftest import REPO
from tests.exr import read_passes

WIDTH, HEIGHT = 48, 36
FRAMES = (1, 2, 3)
REGISTER = (
    f"import sys; sys.path.insert(0, {str(REPO)!r}); import multiscale_camera; "
    "multiscale_camera.register()"
)


def animated_rig(scene):
    """The two-camera scene with both cameras keyframed over ``FRAMES``: C1 slides
    sideways, C2 moves, turns and zooms (lens 50 -> 65), so every frame sees a
    different picture."""
    c1, c2 = two_camera_scene(scene, WIDTH, HEIGHT)
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    first, last = FRAMES[0], FRAMES[-1]
    for obj, frame in ((c1, first), (c2, first)):
        obj.keyframe_insert("location", frame=frame)
        obj.keyframe_insert("rotation_euler", frame=frame)
    c2.data.keyframe_insert("lens", frame=first)
    c1.location.x += 1.5
    c2.location += Vector((0.6, 0.4, -0.3))
    c2.rotation_euler.z += 0.12
    c2.data.lens = 65.0
    for obj in (c1, c2):
        obj.keyframe_insert("location", frame=last)
        obj.keyframe_insert("rotation_euler", frame=last)
    c2.data.keyframe_insert("lens", frame=last)
    scene.frame_set(first)
    return c1, c2


def straight_index(scene, cam):
    """(HEIGHT, WIDTH) int: pass index of the object ``cam``'s straight pinhole ray
    through each pixel centre hits (0: none), at the scene's current frame; the ray
    starts on the near plane, as the camera's own does."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    cam = cam.evaluated_get(depsgraph)
    tr, br, bl, tl = (cam.matrix_world @ v for v in cam.data.view_frame(scene=scene))
    eye = cam.matrix_world.translation
    axis = (cam.matrix_world.to_quaternion() @ Vector((0, 0, -1))).normalized()
    index = np.zeros((HEIGHT, WIDTH), dtype=np.float32)
    for y in range(HEIGHT):
        fy = (y + 0.5) / HEIGHT
        left, right = tl.lerp(bl, fy), tr.lerp(br, fy)
        for x in range(WIDTH):
            d = (left.lerp(right, (x + 0.5) / WIDTH) - eye).normalized()
            origin = eye + d * (cam.data.clip_start / d.dot(axis))
            hit, _loc, _nor, _face, obj, _m = scene.ray_cast(depsgraph, origin, d)
            index[y, x] = obj.pass_index if hit else 0
    return index


def agreement(scene, cams, frame, index):
    """{camera name: (share of eroded-mask pixels whose IndexOB is the object the
    camera's own straight ray hits at ``frame``, pixels compared)}."""
    scene.frame_set(frame)
    masks = rig_from_scene(scene).masks  # the masks as the rig resolves them
    out = {}
    for cam, mask in zip(cams, masks, strict=True):
        kept = erode(mask, 2)
        out[cam.name] = (
            float((index[kept] == straight_index(scene, cam)[kept]).mean()),
            int(kept.sum()),
        )
    return out


def assert_each_frame_its_cameras(scene, cams, renders):
    """``renders`` {frame: passes}: >= 99% hidden-surface agreement everywhere, and the
    check has teeth: the frames differ, and frame 1's cameras do not explain the last."""
    for frame, passes in renders.items():
        for name, (agree, pixels) in agreement(
            scene, cams, frame, passes["IndexOB"][..., 0]
        ).items():
            print(f"frame {frame} {name}: {agree:.4f} of {pixels} px")
            assert pixels >= 40, f"frame {frame} {name}: only {pixels} px to compare"
            assert agree >= 0.99, f"frame {frame} {name}: {agree:.2%} of the mask agrees"
    first, last = renders[FRAMES[0]], renders[FRAMES[-1]]
    assert not np.array_equal(first["IndexOB"], last["IndexOB"])
    stale = agreement(scene, cams, FRAMES[0], last["IndexOB"][..., 0])
    assert min(a for a, _n in stale.values()) < 0.97, stale


def render_animation(scene, folder):
    """{frame: passes} of ``render(animation=True)`` into ``folder``."""
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(folder / "frame_####")
    bpy.ops.render.render(animation=True)
    return {f: read_passes(folder / f"frame_{f:04d}.exr") for f in FRAMES}


@pytest.mark.slow
@pytest.mark.parametrize("method", ["SCALAR_FIELD", "AUTO"])
def test_animation_render_reads_each_frames_cameras(empty_scene, tmp_path, method):
    """render(animation=True) with keyframed cameras once gave frames 1 and 2 the same
    picture: the render read the cameras' original objects, not the frame's. With AUTO
    the shot's one method (IMAGE_BLEND here) too."""
    scene = empty_scene
    cams = animated_rig(scene)
    scene.multiscale.method = method
    renders = render_animation(scene, tmp_path)
    assert_each_frame_its_cameras(scene, cams, renders)
    if method == "AUTO":
        report = json.loads(scene.multiscale.report)
        print(report["auto"])
        assert report["method"] == "IMAGE_BLEND", report["auto"]
        assert report["auto"].endswith("at frames 1, 2, 3 of the shot"), report["auto"]


@pytest.mark.slow
def test_static_rig_renders_identical_frames(empty_scene, tmp_path):
    """...and its second frame builds nothing: the field comes from the cache, the BVH
    is the first frame's, and its first hits did not move (the report's ``frame``)."""
    scene = empty_scene
    two_camera_scene(scene, WIDTH, HEIGHT)
    scene.frame_start, scene.frame_end = 1, 2
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(tmp_path / "frame_####")
    bpy.ops.render.render(animation=True)
    one, two = (read_passes(tmp_path / f"frame_{f:04d}.exr") for f in (1, 2))
    for name in ("Combined", "Depth", "Normal", "IndexOB", "Membership"):
        np.testing.assert_array_equal(one[name], two[name], err_msg=name)
    frame = json.loads(scene.multiscale.report)["frame"]
    assert frame["number"] == 2
    assert frame["built"] == []
    assert frame["reused"] == ["field", "BVH"]
    assert frame["jump_p95_px"] == 0.0


def nudged_rig(scene):
    """The two-camera scene on SCALAR_FIELD with camera 2 keyed to move 2 mm a frame
    over ``FRAMES`` (camera 1 holds still): a rig in motion whose steady layout holds."""
    c1, c2 = two_camera_scene(scene, WIDTH, HEIGHT)
    scene.multiscale.method = "SCALAR_FIELD"
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    for frame in FRAMES:
        c2.location.x = 0.5 + 0.002 * (frame - FRAMES[0])
        c2.keyframe_insert("location", frame=frame)
    scene.frame_set(FRAMES[0])
    return c1, c2


@pytest.mark.slow
def test_a_frame_rendered_after_others_matches_it_rendered_cold(empty_scene, tmp_path):
    """The last frame of a sequence (its field built after the frame before, taking
    camera 1's claims and a warm start) against the same frame rendered alone by a
    process that kept nothing: the image within 1e-3."""
    scene = empty_scene
    nudged_rig(scene)
    scene.multiscale.cache_folder = str(tmp_path / "cache")
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(tmp_path / "seq" / "frame_####")
    fields.SERVICE.reuse = FrameReuse()
    bpy.ops.render.render(animation=True)
    last = FRAMES[-1]
    frame = json.loads(scene.multiscale.report)["frame"]
    assert frame["number"] == last
    assert frame["reused"] == ["claims of 'C1'", "BVH"], frame
    assert "membership solve (warm start)" in frame["built"], frame
    assert frame["worst_jump_p95_px"] is not None
    warm = read_passes(tmp_path / "seq" / f"frame_{last:04d}.exr")
    fields.SERVICE.clear()  # the cache's fields, memory and disk
    fields.SERVICE.reuse = FrameReuse()  # and what the sequence kept
    scene.frame_set(last)
    scene.render.filepath = str(tmp_path / "cold.exr")
    bpy.ops.render.render(write_still=True)
    cold_frame = json.loads(scene.multiscale.report)["frame"]
    assert "membership solve" in cold_frame["built"], cold_frame
    cold = read_passes(tmp_path / "cold.exr")
    for name in ("Combined", "Depth", "Normal", "Membership"):
        gap = np.abs(warm[name] - cold[name])
        if name == "Depth":
            gap = gap / np.maximum(np.abs(cold[name]), 1.0)
        print(f"{name}: worst {gap.max():.2e}")
        assert gap.max() <= 1e-3, name
    np.testing.assert_array_equal(warm["IndexOB"], cold["IndexOB"])


@pytest.mark.slow
@pytest.mark.e2e
def test_command_line_animation_reads_each_frames_cameras(empty_scene, tmp_path, run_blender):
    """``blender -b file.blend -s 1 -e 3 -a``, as render farms run it."""
    scene = empty_scene
    cams = animated_rig(scene)
    scene.frame_start, scene.frame_end = 7, 9  # -s and -e set the range to render
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    blend = tmp_path / "animated.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    out = tmp_path / "out"
    run_blender(
        [
            "-b",
            blend,
            "--python-exit-code",
            "1",
            "--python-expr",
            REGISTER,
            "-o",
            out / "frame_####",
            "-s",
            str(FRAMES[0]),
            "-e",
            str(FRAMES[-1]),
            "-a",
        ]
    )
    assert sorted(p.name for p in out.iterdir()) == [f"frame_{f:04d}.exr" for f in FRAMES]
    renders = {f: read_passes(out / f"frame_{f:04d}.exr") for f in FRAMES}
    assert_each_frame_its_cameras(scene, cams, renders)


def first_hits(scene):
    """(object index (H*W,), first-hit points (H*W, 3), eye distance (H*W,)) of every
    pixel centre's multiscale ray at the scene's current state."""
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    width, height = frame.size
    iy, ix = np.mgrid[0:height, 0:width]
    ix, iy = ix.ravel(), iy.ravel()
    seg = frame.sampler.segments(ix + 0.5, iy + 0.5, ix, iy)
    hits = march(frame.tree, seg, None, frame.bounds, frame.geometry, frame.occupancy)
    index = np.where(hits.hit, frame.geometry.pass_index[np.maximum(hits.triangle, 0)], 0)
    return index, hits.location, seg.start_depth + hits.distance


def move_ratios(scene, states, pixel_camera, moving):
    """{region: (pixels, p95 move t -> t + d/2, p95 move t -> t + d, ratio)} of the
    first hits of three states of ``scene`` (``states``: callables that set t, t + d/2
    and t + d), over the pixels that see the same object in all three: camera
    ``moving``'s preserved region (its mask eroded by 2 px) and the transitions (no
    camera's mask). Moves are in ``pixel_camera``'s pixels at the hit's distance at t
    (the unit cancels in the ratio)."""
    runs = []
    for state in states:
        state()
        runs.append(first_hits(scene))
    states[0]()
    rig = rig_from_scene(scene)
    preserved = erode(rig.masks[moving], 2).ravel()
    transition = ~rig.masks.any(axis=0).ravel()
    (i0, p0, z0), (ih, ph, _), (i1, p1, _) = runs
    same = (i0 == ih) & (ih == i1) & (i0 > 0)
    data = pixel_camera.data
    pixel = z0 * (data.sensor_width / data.lens) / rig.size[0]
    half = np.linalg.norm(ph - p0, axis=1) / pixel
    full = np.linalg.norm(p1 - p0, axis=1) / pixel
    out = {}
    for name, region in (("preserved", preserved), ("transition", transition)):
        chosen = same & region & (full > 0)
        h95, f95 = np.percentile(half[chosen], 95), np.percentile(full[chosen], 95)
        out[name] = (int(chosen.sum()), float(h95), float(f95), float(f95 / h95))
        print(f"{name}: {chosen.sum()} px, p95 {h95:.3f} / {f95:.3f} px, ratio {f95 / h95:.3f}")
    return out


def assert_moves_linearly(ratios):
    """The p95 move to t + d is 1.6 to 2.4 times that to t + d/2 in every region (a
    field that re-snapped its layout between the states would jump instead)."""
    for name, (pixels, _half, _full, ratio) in ratios.items():
        assert pixels >= 30, f"{name}: {pixels} pixels"
        assert 1.6 <= ratio <= 2.4, f"{name}: ratio {ratio:.3f}"


@pytest.mark.slow
def test_moving_camera_moves_rays_continuously(empty_scene):
    """Camera 2 moves on a straight line at constant speed: at t, t + d/2 and t + d, over
    the pixels that see the same object in all three, the p95 move of the first hit
    from t to t + d is 1.6 to 2.4 times the one from t to t + d/2, both in camera 2's
    preserved region and in the transition between the cameras."""
    scene = empty_scene
    c1, c2 = two_camera_scene(scene, 64, 48)
    start, velocity = Vector(c2.location), Vector((0.16, 0.1, -0.06))

    def at(t):
        def state():
            c2.location = start + velocity * t
            bpy.context.view_layer.update()

        return state

    assert_moves_linearly(move_ratios(scene, [at(0.0), at(0.5), at(1.0)], c1, 1))


# Frames of the dolly for its flicker test: t, t + d/2, t + d (its keys move both
# cameras uniformly, so these are equal steps of the motion).
DOLLY_FLICKER_FRAMES = (1, 7, 13)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["SCALAR_FIELD", "AUTO"])
def test_dolly_moves_rays_continuously(empty_scene, method):
    """The flicker test on sample_blends/dolly.blend's scene (160x90, its own HIGH
    quality): camera 3 dollies in and camera 2 pans, uniformly; over frames t, t + d/2
    and t + d the p95 first-hit move to t + d is 1.6 to 2.4 times that to t + d/2, in
    camera 3's preserved region and in the transitions. With the sample's SCALAR_FIELD
    and with AUTO, which keeps IMAGE_BLEND for the dolly's shot."""
    scene = empty_scene
    samples.build_dolly(scene)
    scene.render.resolution_percentage = 25
    scene.multiscale.method = method
    cam1 = scene.objects["Cam1 Square"]

    def at(frame):
        return lambda: scene.frame_set(frame)

    ratios = move_ratios(scene, [at(f) for f in DOLLY_FLICKER_FRAMES], cam1, 2)
    assert_moves_linearly(ratios)
    built = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get()).field.method
    assert built == {"SCALAR_FIELD": "SCALAR_FIELD", "AUTO": "IMAGE_BLEND"}[method]


def test_dolly_sample_moves_uniformly(empty_scene):
    """sample_blends/dolly.blend's scene: camera 3 from 2.4 m to 1.8 m from the teapot
    in equal steps, camera 2 panning 6 degrees, so every frame asks for its own field."""
    scene = empty_scene
    samples.build_dolly(scene)
    cam2, cam3 = scene.objects["Cam2 Stall"], scene.objects["Cam3 Object"]
    teapot = Vector(samples.TEAPOT)
    distance, yaw, keys = {}, {}, set()
    for frame in (1, 2, 48):
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        distance[frame] = (cam3.evaluated_get(depsgraph).matrix_world.translation - teapot).length
        yaw[frame] = math.degrees(cam2.evaluated_get(depsgraph).matrix_world.to_euler().z)
        keys.add(fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph).key)
    assert (scene.frame_start, scene.frame_end) == (1, 48)
    assert distance[1] == pytest.approx(2.4, abs=1e-5)
    assert distance[48] == pytest.approx(1.8, abs=1e-5)
    assert distance[1] - distance[2] == pytest.approx(0.6 / 47, abs=1e-5)
    assert yaw[48] - yaw[1] == pytest.approx(6.0, abs=1e-3)
    assert len(keys) == 3


def own_grids(rig, settings, nested):
    """The grids frame ``rig`` alone asks for (``choose_levels`` or ``choose_grid``)."""
    if nested:
        return frame_levels(rig, settings).grids
    return (choose_grid(rig, settings.accuracy_px, settings.max_voxels).grid,)


@pytest.mark.slow
def test_dolly_keeps_one_layout_over_its_frames(empty_scene):
    """The steady layout re-snapped inside the shot: on the dolly at 160x90 HIGH, each
    frame's own layout changed 11 times over frames 1-48 (every level at frames 16, 38
    and 41). The shot's layout is chosen once from all its frames: every frame's
    request carries the same one, it holds every frame's own grids, and SCALAR_FIELD
    builds on it at both ends of the shot."""
    scene = empty_scene
    samples.build_dolly(scene)
    scene.render.resolution_percentage = 25
    scene.multiscale.method = "SCALAR_FIELD"  # the sample's
    fields.SERVICE.clear()  # built here: a field read from disk keeps no nested domain
    layouts, own, keys = set(), [], set()
    for frame in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        request = fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph)
        assert scene.frame_current == frame  # the shot's frames were stepped and back
        layout = request.settings.layout
        layouts.add(layout)
        grids = own_grids(request.rig, request.settings, layout.nested)
        assert layout.covers(grids), frame
        budget = request.settings.max_voxels
        own.append(steady_levels(grids, budget) if layout.nested else steady_grid(grids[0], budget))
        keys.add(request.key)
    assert len(layouts) == 1
    assert sum(g.size for g in layout.grids) <= request.settings.max_voxels
    changes = sum(a != b for a, b in zip(own, own[1:]))
    print(f"frame by frame the layout would change {changes} times; the shot's: 0")
    assert changes > 0  # the dolly leaves a frame's own layout
    assert len(keys) == scene.frame_end - scene.frame_start + 1
    # built here: a field read back from the cache (an earlier test's of the same key)
    # keeps its traced rays but not its nested levels (io/fields.py)
    pipeline.clear_fields()
    for frame in (scene.frame_start, scene.frame_end):
        scene.frame_set(frame)
        ready = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
        assert ready.field.method == "SCALAR_FIELD", frame
        assert ready.field.stats["layout"] == "shot", frame
        used = ready.field.domain.grids if ready.field.domain else (ready.field.grid,)
        assert tuple(used) == layout.grids, frame


@pytest.mark.slow
def test_auto_keeps_image_blend_for_the_dollys_shot(empty_scene, monkeypatch):
    """AUTO built SCALAR_FIELD for every rig in motion. On the dolly (160x90, HIGH) it
    measures IMAGE_BLEND once, at frames 1, 24 and 48 (the first, middle and last of its
    keys), finds it meets the target there and keeps it for every frame: each request
    carries the same choice and no grid layout, no frame measures again, and a frame
    after another takes its mask weights (the masks hold still)."""
    scene = empty_scene
    samples.build_dolly(scene)
    scene.render.resolution_percentage = 25
    scene.multiscale.method = "AUTO"
    fields.SERVICE.clear()  # fields, reuse store, the shot's choice: nothing kept
    measured = []
    real = fields.choose_shot_method

    def choose(samples, *args):
        measured.append([f for f, _rig in samples])
        return real(samples, *args)

    monkeypatch.setattr(fields, "choose_shot_method", choose)
    choices = set()
    for frame in (1, 2, 30, 48):
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        request = fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph)
        assert request.settings.layout is None, frame
        choices.add(request.settings.shot)
    assert measured == [[1, 24, 48]]
    (choice,) = choices
    print(choice.why)
    assert choice.method == "IMAGE_BLEND" and choice.frames == (1, 24, 48)
    fields.SERVICE.reuse = FrameReuse()
    for frame, weights in ((1, "built"), (2, "reused")):
        scene.frame_set(frame)
        ready = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
        print(pipeline.rebuilt_line(ready.rebuilt))
        assert ready.field.method == "IMAGE_BLEND"
        assert ready.field.stats["auto"] == choice.why
        assert "mask weights" in ready.rebuilt[weights], ready.rebuilt
        assert "curves" in ready.rebuilt["built"], ready.rebuilt
    assert measured == [[1, 24, 48]]


def test_a_workers_frame_range_keeps_autos_method_for_the_shot(empty_scene):
    """AUTO's method for a shot is measured on frames picked from the cameras' keys, so
    farm workers given different ranges (each its own process: nothing kept) measure
    the same frames and choose alike; a rig that turns far within the shot gets
    SCALAR_FIELD for all of it, whichever of its frames a worker renders."""
    scene = empty_scene
    _c1, c2 = animated_rig(scene)  # keys on frames 1 and 3
    scene.multiscale.method = "AUTO"
    for turn, method in ((0.0, "IMAGE_BLEND"), (1.0, "SCALAR_FIELD")):
        if turn:  # camera 2 turns 57 degrees more by frame 3: IMAGE_BLEND folds there
            c2.rotation_euler.z += turn
            c2.keyframe_insert("rotation_euler", frame=FRAMES[-1])
        choices = []
        for start, end in ((1, 3), (2, 3), (3, 3), (1, 10)):
            fields.SERVICE.forget_sequence()
            scene.frame_start, scene.frame_end = start, end
            scene.frame_set(start)
            depsgraph = bpy.context.evaluated_depsgraph_get()
            choices.append(
                fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph).settings.shot
            )
        print(choices[0].why)
        assert all(c == choices[0] and c.why == choices[0].why for c in choices), choices
        assert choices[0].method == method
        assert choices[0].frames == (1, 2, 3)[: len(choices[0].frames)]
        if method == "IMAGE_BLEND":
            assert choices[0].frames == (1, 2, 3)


@pytest.mark.slow
def test_jump_is_reported_where_pass_indices_are_0(empty_scene, tmp_path):
    """The jump was measured on IndexOB (the objects' pass index, 0 = no hit), so in a
    scene whose pass indices were all 0, as in ordinary scenes, it was always null."""
    scene = empty_scene
    _c1, c2 = two_camera_scene(scene, WIDTH, HEIGHT)
    scene.multiscale.method = "IMAGE_BLEND"
    for obj in scene.objects:
        obj.pass_index = 0
    scene.frame_start, scene.frame_end = 1, 2
    for frame in (1, 2):
        c2.location.x = 0.5 + 0.01 * (frame - 1)
        c2.keyframe_insert("location", frame=frame)
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(tmp_path / "frame_####")
    bpy.ops.render.render(animation=True)
    frame = json.loads(scene.multiscale.report)["frame"]
    assert frame["number"] == 2
    assert frame["jump_p95_px"] is not None and frame["jump_p95_px"] > 0, frame
    assert frame["worst_jump_frame"] == 2


def test_clear_and_a_file_load_forget_the_sequence(empty_scene):
    """``FieldService.clear`` left the reuse store as it was; a loaded file's first
    frame continued the sequence of a same-named scene of the file before."""
    service = fields.SERVICE
    index, hits = np.ones((2, 2)), np.zeros((2, 2, 3))
    service.reuse.claims[("grid", "digest")] = (None, None)
    service.clear()
    assert service.reuse.claims == {} and service.shots == {} and service.choices == {}
    service.sequence.add(("", "Scene", "ViewLayer"), 1, 1, index, hits)
    service.reuse.solved[("grid", "tag")] = None
    bpy.ops.wm.read_homefile(use_empty=True)
    assert service.sequence.last == {}
    assert service.reuse.solved == {}


def test_a_workers_frame_range_keeps_the_shots_layout(empty_scene):
    """``blender -s A -e B`` sets the scene's frame range: a shot layout taken from it
    differed between farm workers given different ranges. It spans the cameras' keys."""
    scene = empty_scene
    animated_rig(scene)  # keys on frames 1 and 3: both cameras move, camera 2 zooms
    scene.multiscale.method = "SCALAR_FIELD"
    layouts = []
    for start, end in ((1, 3), (2, 3), (3, 3), (1, 10)):
        scene.frame_start, scene.frame_end = start, end
        scene.frame_set(3)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        layouts.append(fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph).settings.layout)
    assert layouts[0] is not None
    assert all(layout == layouts[0] for layout in layouts), layouts
    # frame 3 alone would ask for other grids: the range matters
    rig = rig_from_scene(scene, bpy.context.evaluated_depsgraph_get())
    settings = fields.SERVICE.request(scene).settings
    assert plan_shot([rig], replace(settings, layout=None)) != layouts[0]


def test_a_drawn_request_does_not_step_frames(empty_scene):
    """The viewport's picture and the ray preview ask while drawing: they take the
    shot's layout when a render or a build has worked it out, and never step the scene
    through its frames for it."""
    scene = empty_scene
    animated_rig(scene)
    scene.multiscale.method = "SCALAR_FIELD"
    scene.frame_set(2)
    fields.SERVICE.forget_sequence()
    stepped = []
    bpy.app.handlers.frame_change_pre.append(lambda *_a: stepped.append(1))
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        drawn = fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph, step_frames=False)
        assert drawn.settings.layout is None and stepped == []
        rendered = fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph)
        assert rendered.settings.layout is not None and len(stepped) > 0
        again = fields.SERVICE.request(depsgraph.scene, depsgraph=depsgraph, step_frames=False)
        assert again.key == rendered.key
    finally:
        bpy.app.handlers.frame_change_pre.pop()
    assert scene.frame_current == 2
