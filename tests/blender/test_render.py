"""The renderer against an independent reference: Blender's own scene.ray_cast along each
camera's straight pinhole rays, shaded by the same formulas written out plainly here
(one pixel at a time, mathutils for the geometry), compared in linear colour."""

import math

import bpy
import numpy as np
import pytest
from mathutils import Vector
from mathutils.geometry import barycentric_transform, intersect_point_tri

from fixtures.blender.objects import add_camera, add_mesh, mask_image
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.masks import mask_from_image
from multiscale_camera.core.quality import erode
from multiscale_camera.render.engine import ShownRows
from multiscale_camera.render.pipeline import MISS_DEPTH
from tests.exr import read_passes

WORLD = (0.05, 0.07, 0.1)


def render_to(scene, path):
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_passes(path)


def checker_image(name, size=16):
    """A float (linear) checker image with a colour gradient, so texture lookups show."""
    img = bpy.data.images.new(name, size, size, float_buffer=True)
    yy, xx = np.mgrid[0:size, 0:size]
    rgba = np.ones((size, size, 4), np.float32)
    check = ((xx // 2 + yy // 2) % 2).astype(np.float32)
    rgba[..., 0] = 0.2 + 0.6 * check
    rgba[..., 1] = 0.1 + 0.5 * xx / size
    rgba[..., 2] = 0.1 + 0.5 * yy / size
    img.pixels.foreach_set(rgba.ravel())  # row 0 is the bottom, as Blender stores it
    img.pack()
    return img


def textured(obj, image):
    mat = obj.data.materials[0]
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    tex = nodes.new("ShaderNodeTexImage")
    tex.image = image
    links.new(tex.outputs["Color"], nodes["Principled BSDF"].inputs["Base Color"])


def shaded_scene(scene, width=96, height=72):
    """two_camera_scene with a textured ground, an emissive cube, a smooth sphere, a sun
    and a point light, and a world colour."""
    two_camera_scene(scene, width, height)
    ground, cube, sphere = (scene.objects[n] for n in ("Plane", "Cube", "Sphere"))
    textured(ground, checker_image("checker"))
    bsdf = cube.data.materials[0].node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Emission Color"].default_value = (0.3, 0.1, 0.0, 1.0)
    bsdf.inputs["Emission Strength"].default_value = 1.5
    sphere.data.polygons.foreach_set("use_smooth", [True] * len(sphere.data.polygons))
    sphere.data.update()
    bpy.ops.object.light_add(type="POINT", location=(2.0, -3.0, 4.0))
    bpy.context.object.data.energy = 400.0
    bpy.context.object.data.color = (1.0, 0.9, 0.8)
    scene.world = bpy.data.worlds.new("sky")
    if bpy.app.version < (5, 0, 0):
        scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (*WORLD, 1)
    scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 1.0
    bpy.context.view_layer.update()


# --- the reference ----------------------------------------------------------------


def texture_lookup(image, u, v):
    """Bilinear lookup, repeat, pixel centres at (i + 0.5) / size: plain Python."""
    w, h = image.size
    px = list(image.pixels)
    x, y = u * w - 0.5, v * h - 0.5
    x0, y0 = math.floor(x), math.floor(y)
    fx, fy = x - x0, y - y0
    out = [0.0, 0.0, 0.0]
    for dx, dy, wt in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):
        i = ((y0 + dy) % h) * w + (x0 + dx) % w
        for c in range(3):
            out[c] += wt * px[4 * i + c]
    return Vector(out)


class Reference:
    """Straight pinhole renders of one camera, shaded plainly."""

    def __init__(self, scene, depsgraph):
        self.scene, self.depsgraph = scene, depsgraph
        self.lights = [o for o in scene.objects if o.type == "LIGHT"]
        self.meshes = {}

    def mesh_data(self, obj):
        if obj.name not in self.meshes:
            mesh = obj.evaluated_get(self.depsgraph).data
            mesh.calc_loop_triangles()
            by_poly = {}
            for lt in mesh.loop_triangles:
                by_poly.setdefault(lt.polygon_index, []).append(lt)
            self.meshes[obj.name] = (mesh, by_poly)
        return self.meshes[obj.name]

    def surface(self, obj, matrix, face, location):
        """(smooth world normal, uv) at a hit, from the hit polygon's loop triangles."""
        mesh, by_poly = self.mesh_data(obj)
        local = matrix.inverted() @ location
        best = None
        for lt in by_poly[face]:
            a, b, c = (mesh.vertices[i].co for i in lt.vertices)
            if intersect_point_tri(local, a, b, c) is not None or best is None:
                best = (lt, a, b, c)
        lt, a, b, c = best
        w = barycentric_transform(
            local, a, b, c, Vector((1, 0, 0)), Vector((0, 1, 0)), Vector((0, 0, 1))
        )
        normal = sum(
            (mesh.corner_normals[lp].vector * w[k] for k, lp in enumerate(lt.loops)), Vector()
        )
        normal = (matrix.to_3x3().inverted().transposed() @ normal).normalized()
        uv = None
        if mesh.uv_layers.active is not None:
            data = mesh.uv_layers.active.data
            uv = sum((data[lp].uv * w[k] for k, lp in enumerate(lt.loops)), Vector((0, 0)))
        return normal, uv

    def material(self, obj, uv):
        bsdf = obj.material_slots[0].material.node_tree.nodes["Principled BSDF"]
        links = bsdf.inputs["Base Color"].links
        if links:
            albedo = texture_lookup(links[0].from_node.image, uv.x, uv.y)
        else:
            albedo = Vector(bsdf.inputs["Base Color"].default_value[:3])
        emission = Vector(bsdf.inputs["Emission Color"].default_value[:3]) * float(
            bsdf.inputs["Emission Strength"].default_value
        )
        return albedo, emission

    def visible(self, origin, direction, distance):
        hit, *_ = self.scene.ray_cast(self.depsgraph, origin, direction, distance=distance)
        return not hit

    def shade(self, direction, location, geo, face, obj, matrix):
        smooth, uv = self.surface(obj, matrix, face, location)
        if geo.dot(direction) > 0:
            geo, smooth = -geo, -smooth
        albedo, emission = self.material(obj, uv)
        lifted = location + geo * 1e-4
        total = Vector((0, 0, 0))
        for light in self.lights:
            data = light.data
            if data.type == "SUN":
                to_light = (light.matrix_world.to_3x3() @ Vector((0, 0, 1))).normalized()
                e, far = Vector(data.color) * data.energy, 1e30
            else:
                vec = light.matrix_world.translation - location
                far = vec.length
                to_light = vec / far
                e = Vector(data.color) * data.energy / (4 * math.pi * far * far)
            cos = smooth.dot(to_light)
            if cos <= 0 or geo.dot(to_light) <= 0:
                continue
            if self.visible(lifted, to_light, far):
                total += e * cos
        ambient = Vector(WORLD)
        return albedo * (ambient + total / math.pi) + emission

    def render(self, cam, width, height, pixels):
        """{(x, y): colour} for the given pixels of camera ``cam``'s straight rays; the
        distances from the eye to the hits go to ``self.depth`` {(x, y): float}."""
        self.depth = {}
        tr, br, bl, tl = (cam.matrix_world @ v for v in cam.data.view_frame(scene=self.scene))
        eye = cam.matrix_world.translation
        axis = (cam.matrix_world.to_quaternion() @ Vector((0, 0, -1))).normalized()
        out = {}
        for x, y in pixels:
            fy = (y + 0.5) / height
            left, right = tl.lerp(bl, fy), tr.lerp(br, fy)
            d = (left.lerp(right, (x + 0.5) / width) - eye).normalized()
            origin = eye + d * (cam.data.clip_start / d.dot(axis))
            hit, loc, nor, face, obj, matrix = self.scene.ray_cast(self.depsgraph, origin, d)
            out[x, y] = self.shade(d, loc, nor, face, obj, matrix) if hit else Vector(WORLD)
            self.depth[x, y] = (loc - eye).length if hit else MISS_DEPTH
        return out


def psnr(image, reference):
    mse = float(((image - reference) ** 2).mean())
    return math.inf if mse == 0 else 10 * math.log10(float(reference.max()) ** 2 / mse)


@pytest.mark.slow
def test_one_sample_matches_each_cameras_straight_render(empty_scene, tmp_path):
    scene = empty_scene
    width, height = 96, 72
    shaded_scene(scene, width, height)
    passes = render_to(scene, tmp_path / "shaded.exr")
    combined = passes["Combined"][..., :3]
    reference = Reference(scene, bpy.context.evaluated_depsgraph_get())
    for item in scene.multiscale.cameras:
        kept = erode(mask_from_image(item.mask, width, height)[0])
        ys, xs = np.nonzero(kept)
        ref = reference.render(item.camera, width, height, list(zip(xs.tolist(), ys.tolist())))
        ref = np.array([ref[x, y] for x, y in zip(xs.tolist(), ys.tolist())])
        got = combined[ys, xs]
        score = psnr(got, ref)
        print(f"{item.camera.name}: PSNR {score:.1f} dB over {len(xs)} pixels")
        assert len(xs) > 300
        # the scene exercises texture, emission, smooth normals, shadows and both lights
        assert np.ptp(ref, axis=0).min() > 0.05
        assert score >= 40.0, f"{item.camera.name}: PSNR {score:.1f} dB"
        if item.camera.name == "C1":
            # camera 1's preserved rays are straight from its eye: Depth is the distance
            depth = np.array([reference.depth[x, y] for x, y in zip(xs.tolist(), ys.tolist())])
            np.testing.assert_allclose(passes["Depth"][ys, xs, 0], depth, rtol=1e-4)


EDGE_PLANE = 20.0


def edge_scene(scene, width=64, height=48):
    """One camera with a full mask over a white emissive plane whose straight edge
    crosses the view at a slant, against a black world."""
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    plane = add_mesh("plane", (0, 0, 0), 1, (0.0, 0.0, 0.0), size=EDGE_PLANE)
    bsdf = plane.data.materials[0].node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Emission Color"].default_value = (1, 1, 1, 1)
    bsdf.inputs["Emission Strength"].default_value = 1.0
    plane.location = (EDGE_PLANE / 2, 0.0, 0.0)  # its left edge is the line x = 0
    plane.rotation_euler = (0, 0, math.radians(12))
    cam = add_camera(scene, "C1", (0.3, 0.1, 6), (0.3, 0.1, 0), clip_start=1.0)
    item = scene.multiscale.cameras.add()
    item.camera = cam
    item.mask = mask_image("all", np.ones((height, width), bool))
    scene.camera = cam
    scene.render.engine = "MULTISCALE"
    bpy.context.view_layer.update()
    return plane, cam


def edge_distance(plane, cam, scene, width, height):
    """(H, W) signed distance in pixels from each pixel centre to the plane's left edge
    in the image (positive on the plane's side), by projecting the edge's endpoints."""
    from bpy_extras.object_utils import world_to_camera_view

    m = plane.matrix_world
    h = EDGE_PLANE / 2
    a, b = m @ Vector((-h, -h, 0)), m @ Vector((-h, h, 0))
    centre = m @ Vector((0, 0, 0))

    def image(p):
        v = world_to_camera_view(scene, cam, p)
        return np.array([v.x * width, (1 - v.y) * height])

    pa, pb, pc = image(a), image(b), image(centre)
    t = (pb - pa) / np.linalg.norm(pb - pa)
    n = np.array([-t[1], t[0]])
    if np.dot(pc - pa, n) < 0:
        n = -n
    yy, xx = np.mgrid[0:height, 0:width] + 0.5
    return (xx - pa[0]) * n[0] + (yy - pa[1]) * n[1]


def rise_width(dist, value):
    """10%-90% rise distance (pixels) of ``value`` against ``dist``: the medians of the
    values in 0.1-pixel bins, linearly interpolated."""
    bins = np.arange(-2.0, 2.0001, 0.1)
    centres, medians = [], []
    for lo, hi in zip(bins[:-1], bins[1:]):
        sel = (dist >= lo) & (dist < hi)
        if sel.sum() >= 2:
            centres.append(0.5 * (lo + hi))
            medians.append(np.median(value[sel]))
    medians = np.maximum.accumulate(np.array(medians))
    return float(np.interp(0.9, medians, centres) - np.interp(0.1, medians, centres))


def test_sixteen_samples_antialias_edges(empty_scene, tmp_path):
    scene = empty_scene
    width, height = 64, 48
    plane, cam = edge_scene(scene, width, height)
    dist = edge_distance(plane, cam, scene, width, height)
    one = render_to(scene, tmp_path / "one.exr")["Combined"][..., 0]
    # one sample: each pixel shows what its centre's ray hits, so the edge is a hard step
    assert set(np.unique(one).round(6).tolist()) <= {0.0, 1.0}
    np.testing.assert_array_equal(one[np.abs(dist) > 0.05] > 0.5, dist[np.abs(dist) > 0.05] > 0)
    scene.multiscale.samples = 16
    many = render_to(scene, tmp_path / "many.exr")["Combined"][..., 0]
    near = np.abs(dist) < 0.35
    assert near.sum() >= 30
    # pixels the edge crosses take in-between values
    assert ((many[near] > 0.05) & (many[near] < 0.95)).mean() > 0.9
    # far from the edge nothing is blurred (the filter is 1.5 px wide)
    far = np.abs(dist) > 0.8
    np.testing.assert_array_equal(many[far], (dist[far] > 0).astype(np.float32))
    width_16 = rise_width(dist, many)
    width_1 = rise_width(dist, one)
    print(f"10-90% edge width: {width_1:.2f} px at 1 sample, {width_16:.2f} px at 16")
    # Blackman-Harris of 1.5 px: a 10-90% rise of about 0.55 px across the edge
    assert 0.35 <= width_16 <= 0.9
    assert width_1 <= 0.2


@pytest.mark.parametrize("samples", [1, 4])
def test_film_transparency_premultiplies_misses(empty_scene, tmp_path, samples):
    scene = empty_scene
    plane, cam = edge_scene(scene)
    scene.render.film_transparent = True
    scene.multiscale.samples = samples
    rgba = render_to(scene, tmp_path / "alpha.exr")["Combined"]
    np.testing.assert_allclose(rgba[..., 0], rgba[..., 3], atol=1e-6)
    assert rgba[..., 3].min() == 0.0 and rgba[..., 3].max() == 1.0


def gradient_image(name, width=32, height=16):
    """A float equirectangular image whose colour encodes its own pixel position."""
    img = bpy.data.images.new(name, width, height, float_buffer=True)
    yy, xx = np.mgrid[0:height, 0:width]
    rgba = np.ones((height, width, 4), np.float32)
    rgba[..., 0] = xx / width
    rgba[..., 1] = yy / height
    rgba[..., 2] = 0.25 + 0.5 * ((xx + yy) % 2)
    img.pixels.foreach_set(rgba.ravel())
    img.pack()
    return img


def test_misses_show_the_world_texture_along_the_ray(empty_scene, tmp_path):
    scene = empty_scene
    width, height = 48, 36
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    cam = add_camera(scene, "C1", (0, 0, 0), (1.0, 0.4, 0.3), clip_start=0.5, lens=20.0)
    item = scene.multiscale.cameras.add()
    item.camera = cam
    item.mask = mask_image("all", np.ones((height, width), bool))
    scene.camera = cam
    scene.render.engine = "MULTISCALE"
    scene.world = bpy.data.worlds.new("env")
    if bpy.app.version < (5, 0, 0):
        scene.world.use_nodes = True
    nodes, links = scene.world.node_tree.nodes, scene.world.node_tree.links
    env = nodes.new("ShaderNodeTexEnvironment")
    env.image = gradient_image("sky")
    links.new(env.outputs["Color"], nodes["Background"].inputs["Color"])
    nodes["Background"].inputs["Strength"].default_value = 2.0
    bpy.context.view_layer.update()
    combined = render_to(scene, tmp_path / "env.exr")["Combined"][..., :3]
    tr, br, bl, tl = (cam.matrix_world @ v for v in cam.data.view_frame(scene=scene))
    eye = cam.matrix_world.translation
    ref = np.zeros((height, width, 3))
    for y in range(height):
        left, right = tl.lerp(bl, (y + 0.5) / height), tr.lerp(br, (y + 0.5) / height)
        for x in range(width):
            d = (left.lerp(right, (x + 0.5) / width) - eye).normalized()
            u = -math.atan2(d.y, d.x) / (2 * math.pi) + 0.5
            v = math.atan2(d.z, math.hypot(d.x, d.y)) / math.pi + 0.5
            ref[y, x] = texture_lookup(env.image, u, v) * 2.0
    assert np.ptp(ref[..., 0]) > 0.3 and np.ptp(ref[..., 1]) > 0.3
    assert psnr(combined, ref) >= 40.0


def test_srgb_byte_images_are_read_as_linear(empty_scene):
    from multiscale_camera.adapters.textures import read_image

    img = bpy.data.images.new("paint", 2, 2)
    img.pixels.foreach_set(np.full(16, 0.5, np.float32))
    assert img.colorspace_settings.name == "sRGB" and not img.is_float
    stored = np.empty(16, np.float32)
    img.pixels.foreach_get(stored)
    expected = ((stored[0] + 0.055) / 1.055) ** 2.4
    np.testing.assert_allclose(read_image(img), expected, rtol=1e-5)
    data = bpy.data.images.new("data", 2, 2)
    data.colorspace_settings.name = "Non-Color"  # (regenerates a generated image's pixels)
    data.pixels.foreach_set(np.full(16, 0.5, np.float32))
    data.pixels.foreach_get(stored)
    np.testing.assert_allclose(read_image(data), stored[0], rtol=1e-6)


def test_default_simplification_is_invisible(empty_scene, tmp_path):
    scene = empty_scene
    two_camera_scene(scene, 96, 72)
    exact_settings = scene.multiscale
    exact_settings.simplify_px = 0.0  # every bending vertex kept: the polylines as traced
    exact = render_to(scene, tmp_path / "exact.exr")
    exact_settings.property_unset("simplify_px")
    assert scene.multiscale.simplify_px == 0.25
    default = render_to(scene, tmp_path / "default.exr")
    score = psnr(default["Combined"][..., :3], exact["Combined"][..., :3])
    agree = (default["IndexOB"] == exact["IndexOB"]).mean()
    print(f"default simplification: PSNR {score:.1f} dB, IndexOB agreement {agree:.4f}")
    assert score >= 40.0
    assert agree >= 0.999
    # the comparison can tell: a coarse tolerance does change the picture
    scene.multiscale.simplify_px = 8.0
    coarse = render_to(scene, tmp_path / "coarse.exr")
    print(f"8 px: PSNR {psnr(coarse['Combined'][..., :3], exact['Combined'][..., :3]):.1f} dB")
    assert psnr(coarse["Combined"][..., :3], exact["Combined"][..., :3]) < score


def test_scene_tree_is_reused_only_for_the_same_triangles(empty_scene):
    """The BVH tree and occupancy grid are kept across frames while the triangles stay the
    same, and rebuilt when a mesh moves."""
    from multiscale_camera.render import pipeline

    two_camera_scene(empty_scene)
    first = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    again = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    assert again.tree is first.tree and again.occupancy is first.occupancy
    empty_scene.objects["Cube"].location.z += 0.5
    bpy.context.view_layer.update()
    moved = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    assert moved.tree is not first.tree
    hit = moved.tree.ray_cast((0.0, 0.0, 10.0), (0.0, 0.0, -1.0))
    assert abs(hit[0][2] - 2.5) < 1e-5  # the cube's top, moved up by 0.5


def test_result_updates_are_joined_tiles_in_order():
    """The engine shows tiles at most once a second: what it holds in between is written
    as one block covering exactly the held rows, in order."""
    rng = np.random.default_rng(3)
    image = rng.random((10, 4, 3)).astype(np.float32)
    tiles = [(0, 3), (3, 5), (5, 9), (9, 10)]
    shown = ShownRows(10, 4, seconds=3600.0)
    due = [shown.add(r0, r1, {"Combined": image[r0:r1]}) for r0, r1 in tiles[:1]]
    assert due == [True]  # the first tile at once
    first = shown.take()
    assert first[:2] == (0, 3) and np.array_equal(first[2]["Combined"], image[0:3])
    due = [shown.add(r0, r1, {"Combined": image[r0:r1]}) for r0, r1 in tiles[1:]]
    assert due == [False, False, False]  # within the hour: held
    row0, row1, passes = shown.take()
    assert (row0, row1) == (3, 10)
    assert np.array_equal(passes["Combined"], image[3:10])
    assert shown.take() is None
    eager = ShownRows(10, 4, seconds=0.0)
    assert all(eager.add(r0, r1, {"Combined": image[r0:r1]}) for r0, r1 in tiles)
