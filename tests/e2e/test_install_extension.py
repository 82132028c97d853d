"""Install the built zip as a user extension and render a tiny scene with the engine."""

import numpy as np
import pytest

from tests.exr import read_passes

pytestmark = pytest.mark.e2e

WIDTH, HEIGHT = 32, 24

SCENE = """
import bpy, numpy as np
bpy.ops.extensions.package_install_files(
    filepath={zip!r}, repo="user_default", enable_on_install=True)
import bl_ext.user_default.multiscale_camera
assert "bl_ext.user_default.multiscale_camera" in bpy.context.preferences.addons

bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
bpy.ops.mesh.primitive_cube_add(size=2)
bpy.context.object.pass_index = 3
sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
sun.rotation_euler = (0.6, 0.2, 0.3)
scene.collection.objects.link(sun)
cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
cam.location = (0.0, -8.0, 0.0)
cam.rotation_euler = (np.pi / 2, 0.0, 0.0)  # looking along +Y, at the cube
scene.collection.objects.link(cam)
scene.camera = cam

mask = bpy.data.images.new("m", {w}, {h})
mask.pixels.foreach_set(np.ones({w} * {h} * 4, dtype=np.float32))
item = scene.multiscale.cameras.add()
item.camera = cam
item.mask = mask

render = scene.render
render.resolution_x, render.resolution_y, render.resolution_percentage = {w}, {h}, 100
render.engine = "MULTISCALE"
render.image_settings.media_type = "MULTI_LAYER_IMAGE"
render.image_settings.color_depth = "32"
layer = scene.view_layers[0]
layer.use_pass_z = layer.use_pass_normal = layer.use_pass_object_index = True
render.filepath = {exr!r}
bpy.ops.render.render(write_still=True)
"""


def test_install_and_render(run_blender, linux_zip, tmp_path):
    exr = tmp_path / "render.exr"
    code = SCENE.format(zip=str(linux_zip), exr=str(exr), w=WIDTH, h=HEIGHT)
    run_blender(
        ["-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", code],
        env={"BLENDER_USER_RESOURCES": str(tmp_path / "user")},
    )
    assert (tmp_path / "user" / "extensions" / "user_default" / "multiscale_camera").is_dir()

    passes = read_passes(exr)
    combined, index = passes["Combined"], passes["IndexOB"]
    assert combined.shape == (HEIGHT, WIDTH, 4)
    assert index[HEIGHT // 2, WIDTH // 2, 0] == 3
    assert np.any(combined[..., :3] != 0)
