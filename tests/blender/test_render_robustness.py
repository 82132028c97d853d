"""Scenes that are odd but legitimate render (or explain), never crash; Esc is heard often;
culling against the scene's box drops only what cannot hit."""

import dataclasses

import bpy
import numpy as np

from fixtures.blender.objects import add_mesh
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.core.errors import Cancelled
from multiscale_camera.core.sampling import footprint
from multiscale_camera.render import pipeline, raycast
from tests.exr import read_passes

NO_MESH = "The scene has no visible mesh: only the world is rendered"
NO_LIGHTS = "The scene has no lights: surfaces are lit by the world colour alone"


def render_to(scene, path):
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_passes(path)


def remove(types):
    for obj in [o for o in bpy.context.scene.objects if o.type in types]:
        bpy.data.objects.remove(obj)


def ground_pixel(passes):
    """(row, col) of a pixel that shows the ground (pass index 1), camera 1's region."""
    rows, cols = np.nonzero(passes["IndexOB"][..., 0] == 1)
    return rows[0], cols[0]


def test_empty_scene_renders_black_with_notice(empty_scene, tmp_path, capfd):
    scene = empty_scene
    two_camera_scene(scene)
    remove({"MESH", "LIGHT"})
    assert scene.world is None
    passes = render_to(scene, tmp_path / "empty.exr")
    assert NO_MESH in capfd.readouterr().out
    np.testing.assert_array_equal(passes["Combined"][..., :3], 0.0)
    np.testing.assert_array_equal(passes["Combined"][..., 3], 1.0)
    np.testing.assert_array_equal(passes["Depth"], pipeline.MISS_DEPTH)


def test_scene_without_lights_is_lit_by_the_world(empty_scene, tmp_path, capfd):
    scene = empty_scene
    two_camera_scene(scene)
    remove({"LIGHT"})
    scene.world = bpy.data.worlds.new("grey")
    if bpy.app.version < (5, 0, 0):
        scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.5, 0.5, 0.5, 1)
    passes = render_to(scene, tmp_path / "unlit.exr")
    assert NO_LIGHTS in capfd.readouterr().out
    y, x = ground_pixel(passes)
    # ground albedo (0.2, 0.6, 0.2) under a uniform world of 0.5
    np.testing.assert_allclose(passes["Combined"][y, x, :3], [0.1, 0.3, 0.1], atol=1e-6)


def faceless_mesh(scene):
    mesh = bpy.data.meshes.new("points")
    mesh.from_pydata([(0, 0, 1), (1, 0, 1), (0, 1, 1)], [(0, 1), (1, 2)], [])
    obj = bpy.data.objects.new("points", mesh)
    scene.collection.objects.link(obj)
    return obj


def test_mesh_without_faces_renders(empty_scene, tmp_path, capfd):
    scene = empty_scene
    two_camera_scene(scene)
    before = render_to(scene, tmp_path / "before.exr")["Combined"]
    faceless_mesh(scene)
    after = render_to(scene, tmp_path / "after.exr")["Combined"]
    np.testing.assert_array_equal(before, after)
    remove({"MESH"})
    faceless_mesh(scene)
    capfd.readouterr()
    alone = render_to(scene, tmp_path / "alone.exr")
    assert NO_MESH in capfd.readouterr().out
    np.testing.assert_array_equal(alone["IndexOB"], 0.0)


def test_missing_texture_file_renders_pink_with_notice(empty_scene, tmp_path, capfd):
    scene = empty_scene
    two_camera_scene(scene)
    ground = scene.objects["Plane"]
    image = bpy.data.images.new("lost", 4, 4)
    image.source = "FILE"
    image.filepath = str(tmp_path / "no such file.png")
    image.reload()
    mat = ground.data.materials[0]
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    mat.node_tree.links.new(
        tex.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"]
    )
    passes = render_to(scene, tmp_path / "lost.exr")
    out = capfd.readouterr().out
    assert "Image 'lost' could not be read (file" in out
    assert "missing or unreadable): it renders pink, as in Cycles" in out
    y, x = ground_pixel(passes)
    r, g, b = passes["Combined"][y, x, :3]
    assert g == 0.0 and r > 0.05 and r == b


def test_material_without_nodes_uses_its_viewport_colour(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.world = None
    mat = scene.objects["Plane"].data.materials[0]
    mat.diffuse_color = (0.1, 0.2, 0.4, 1.0)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = False
    else:  # Blender 5 always shades by nodes: a tree without a BSDF is the same case
        mat.node_tree.nodes.clear()
    passes = render_to(scene, tmp_path / "nodeless.exr")
    y, x = ground_pixel(passes)
    rgb = passes["Combined"][y, x, :3]
    assert rgb.min() > 0
    np.testing.assert_allclose(rgb / rgb[2], [0.25, 0.5, 1.0], rtol=1e-5)


def test_material_slot_without_material_uses_the_object_colour(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene)
    scene.world = None
    ground = scene.objects["Plane"]
    ground.data.materials.clear()
    ground.color = (0.4, 0.2, 0.1, 1.0)
    passes = render_to(scene, tmp_path / "objcolour.exr")
    y, x = ground_pixel(passes)
    rgb = passes["Combined"][y, x, :3]
    np.testing.assert_allclose(rgb / rgb[0], [1.0, 0.5, 0.25], rtol=1e-5)


class CountingTree:
    """A BVHTree stand-in that counts ``ray_cast`` calls."""

    def __init__(self, tree):
        self.tree, self.casts = tree, 0

    def ray_cast(self, *args):
        self.casts += 1
        return self.tree.ray_cast(*args)


def test_should_stop_is_consulted_every_few_thousand_casts(empty_scene):
    scene = empty_scene
    two_camera_scene(scene, 96, 72)
    scene.multiscale.samples = 4
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    counter = CountingTree(frame.tree)
    frame.tree = counter
    seen = [0]

    def should_stop():
        seen.append(counter.casts)
        return False

    pipeline.render_rows(frame, 0, 72, should_stop)
    seen.append(counter.casts)
    gaps = np.diff(seen)
    assert counter.casts > 5 * raycast.CASTS_PER_CHECK
    assert counter.casts == frame.casts + frame.shadow_casts
    assert gaps.max() <= raycast.CASTS_PER_CHECK == 4096


def test_stop_request_ends_the_march(empty_scene):
    scene = empty_scene
    two_camera_scene(scene, 96, 72)
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    counter = CountingTree(frame.tree)
    frame.tree = counter
    calls = []

    def stop_on_second_call():
        calls.append(counter.casts)
        return len(calls) >= 2

    try:
        pipeline.render_rows(frame, 0, 72, stop_on_second_call)
    except Cancelled:
        pass
    else:
        raise AssertionError("render_rows did not stop")
    assert counter.casts == calls[-1] <= raycast.CASTS_PER_CHECK


def test_box_culling_agrees_with_dense_sampling():
    rng = np.random.default_rng(7)
    n = 400
    origin = rng.uniform(-1.6, 1.6, (n, 3))
    direction = rng.normal(size=(n, 3))
    direction[::7, 0] = 0.0  # rays parallel to a slab
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = rng.uniform(0.1, 5.0, n)
    lo, hi = np.array([-1.0, -0.5, -2.0]), np.array([1.0, 0.5, 0.0])
    inside, t0, t1 = raycast.clip_to_box(origin, direction, length, lo, hi)
    t = np.linspace(0, 1, 4001)[None, :] * length[:, None]
    pts = origin[:, None] + direction[:, None] * t[..., None]
    within = ((pts >= lo) & (pts <= hi)).all(-1)
    step = length / 4000
    assert inside.sum() > 50 and (~inside).sum() > 50
    for i in range(n):
        if within[i].any():
            assert inside[i]
            first, last = t[i][within[i]][[0, -1]]
            assert abs(t0[i] - first) <= step[i] + 1e-12
            assert abs(t1[i] - last) <= step[i] + 1e-12
        elif inside[i]:
            # a graze shorter than the sampling step
            assert t1[i] - t0[i] <= step[i]


def test_culled_render_equals_uncut_render(empty_scene):
    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    add_mesh("cube", (3, 3, 0.5), 5, (0.9, 0.9, 0.1))
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    culled = pipeline.render_rows(frame, 0, 48)
    casts = frame.casts
    frame.bounds = frame.occupancy = None
    frame.casts = 0
    uncut = pipeline.render_rows(frame, 0, 48)
    for name in ("Combined", "IndexOB", "Normal"):
        np.testing.assert_allclose(culled[name], uncut[name], atol=1e-5)
    np.testing.assert_allclose(culled["Depth"], uncut["Depth"], rtol=1e-5)
    assert casts < frame.casts


def test_march_on_exact_polylines_finds_the_same_hits(empty_scene):
    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    iy, ix = np.mgrid[0:48, 0:64]
    ix, iy = ix.ravel(), iy.ravel()
    exact = raycast.march(frame.tree, frame.field.rays(ix, iy))
    seg = frame.sampler.segments(ix + 0.5, iy + 0.5, ix, iy)
    simplified = raycast.march(frame.tree, seg, None, frame.bounds)
    assert (exact.triangle == simplified.triangle).mean() >= 0.999
    both = exact.hit & simplified.hit
    # within the 0.25 px tolerance, measured where the hits are
    miss = np.linalg.norm(simplified.location[both] - exact.location[both], axis=1)
    pixel = footprint(exact.location[both], frame.sampler.eyes, frame.sampler.angles)
    assert (miss / pixel).max() <= 0.25
    assert simplified.casts < exact.casts


def test_solved_distances_and_grid_culling_agree_with_ray_cast(empty_scene):
    """The renderer's march (hit distance solved on the hit triangle, occupancy-grid
    culling) finds what plain ``ray_cast`` answers find, with fewer casts."""
    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    iy, ix = np.mgrid[0:48, 0:64]
    ix, iy = ix.ravel(), iy.ravel()
    seg = frame.sampler.segments(ix + 0.5, iy + 0.5, ix, iy)
    plain = raycast.march(frame.tree, seg, None, frame.bounds)
    fast = raycast.march(frame.tree, seg, None, frame.bounds, frame.geometry, frame.occupancy)
    assert plain.hit.mean() > 0.5
    np.testing.assert_array_equal(fast.hit, plain.hit)
    np.testing.assert_array_equal(fast.triangle, plain.triangle)
    np.testing.assert_allclose(fast.distance[fast.hit], plain.distance[plain.hit], atol=1e-5)
    assert fast.casts < plain.casts


def test_leaf_culling_finds_the_same_hits(empty_scene):
    """Segments the sampler marks not castable (empty space for a whole lattice leaf)
    hold no hit: marching without the marks finds the same hits (with as many casts or
    more: the per-segment tests would skip most of them too); for
    pixel centres and for jittered samples, those beyond the border centres included."""
    scene = empty_scene
    two_camera_scene(scene, 64, 48)
    add_mesh("cube", (3, 3, 0.5), 5, (0.9, 0.9, 0.1))
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    iy, ix = np.mgrid[0:48, 0:64]
    ix, iy = ix.ravel(), iy.ravel()
    rng = np.random.default_rng(3)
    sx, sy = ix + rng.uniform(0, 1, ix.size), iy + rng.uniform(0, 1, iy.size)
    for seg in (
        frame.sampler.segments(ix + 0.5, iy + 0.5, ix, iy),
        frame.sampler.segments(sx, sy),
    ):
        assert seg.castable is not None and 0 < seg.castable.mean() < 0.9
        args = (None, frame.bounds, frame.geometry, frame.occupancy)
        marked = raycast.march(frame.tree, seg, *args)
        unmarked = raycast.march(frame.tree, dataclasses.replace(seg, castable=None), *args)
        assert marked.hit.mean() > 0.5
        np.testing.assert_array_equal(marked.hit, unmarked.hit)
        np.testing.assert_array_equal(marked.triangle, unmarked.triangle)
        np.testing.assert_array_equal(marked.distance, unmarked.distance)
        assert marked.casts <= unmarked.casts
