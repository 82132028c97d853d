"""The bpy -> numpy adapters against Blender's own answers."""

import bpy
import numpy as np
import pytest
from bpy_extras.object_utils import world_to_camera_view
from mathutils import Vector

from fixtures.blender.objects import add_camera, add_mesh, mask_image
from multiscale_camera.adapters.cameras import pinhole_from_object
from multiscale_camera.adapters.masks import mask_from_image
from multiscale_camera.adapters.meshes import scene_geometry


@pytest.mark.parametrize(
    "res, percent, fit, shift, aspect",
    [
        ((64, 48), 100, "AUTO", (0, 0), (1, 1)),
        ((48, 64), 50, "AUTO", (0.1, -0.05), (1, 1)),
        ((80, 40), 100, "VERTICAL", (0, 0.2), (1, 1)),
        ((60, 60), 100, "HORIZONTAL", (0, 0), (2, 1)),
    ],
)
def test_pinhole_matches_blender_projection(empty_scene, res, percent, fit, shift, aspect):
    scene = empty_scene
    scene.render.resolution_x, scene.render.resolution_y = res
    scene.render.resolution_percentage = percent
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = aspect
    obj = add_camera(scene, "C", (2, -6, 3), (0, 0, 0.5), clip_start=0.5)
    obj.data.sensor_fit = fit
    obj.data.shift_x, obj.data.shift_y = shift
    cam = pinhole_from_object(obj, scene)
    assert (cam.width, cam.height) == (res[0] * percent // 100, res[1] * percent // 100)
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, size=(20, 3))
    pix, depth = cam.project(points)
    for p, (x, y), d in zip(points, pix, depth):
        ndc = world_to_camera_view(scene, obj, Vector(p))
        assert x / cam.width == pytest.approx(ndc.x, abs=1e-5)
        assert 1 - y / cam.height == pytest.approx(ndc.y, abs=1e-5)
        assert d == pytest.approx(ndc.z, rel=1e-5)


def test_mask_rows_are_flipped_and_thresholded_on_luminance(empty_scene):
    mask = np.zeros((6, 8), bool)
    mask[0, 0] = True  # top-left
    img = mask_image("m", mask)
    got, notices = mask_from_image(img, 8, 6)
    assert got[0, 0] and got.sum() == 1 and notices == []
    # a dim green pixel: luminance 0.7152 * 0.6 = 0.43 is below 0.5
    px = np.ones((6, 8, 4), np.float32)
    px[..., :3] = (0.0, 0.6, 0.0)
    img.pixels.foreach_set(px.ravel())
    assert not mask_from_image(img, 8, 6)[0].any()


def test_scene_geometry_is_world_space_with_modifiers(empty_scene):
    obj = add_mesh("cube", (3, 0, 0), 7, (0.5, 0.25, 0.125))
    obj.scale = (2, 1, 1)
    obj.modifiers.new("sub", "SUBSURF").levels = 1
    depsgraph = bpy.context.evaluated_depsgraph_get()
    geo = scene_geometry(depsgraph)
    assert len(geo) == 6 * 4 * 2
    evaluated = obj.evaluated_get(depsgraph)
    expected = [evaluated.matrix_world @ v.co for v in evaluated.data.vertices]
    np.testing.assert_allclose(geo.vertices, np.array(expected), atol=1e-5)
    assert (geo.pass_index == 7).all()
    np.testing.assert_allclose(geo.colour[0], (0.5, 0.25, 0.125))
