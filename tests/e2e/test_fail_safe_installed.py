"""A command-line render that fails (``blender -b file.blend -f 1``) exits non-zero,
says why, and leaves the existing output file as it was: the installed extension, on
$BLENDER (tools/blender by default, a real Blender alike)."""

import pytest

pytestmark = pytest.mark.e2e

MAKE = """
import bpy, numpy as np
bpy.ops.extensions.package_install_files(
    filepath={zip!r}, repo="user_default", enable_on_install=True)
bpy.ops.wm.save_userpref()
bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
bpy.ops.mesh.primitive_cube_add(size=2)
cam = bpy.data.objects.new("Zero", bpy.data.cameras.new("Zero"))
cam.location = (0.0, -8.0, 0.0)
cam.rotation_euler = (np.pi / 2, 0.0, 0.0)
cam.scale = (0.0, 0.0, 0.0)
scene.collection.objects.link(cam)
scene.camera = cam
mask = bpy.data.images.new("m", 16, 12)
mask.pixels.foreach_set(np.ones(16 * 12 * 4, dtype=np.float32))
mask.pack()
item = scene.multiscale.cameras.add()
item.camera, item.mask = cam, mask
scene.render.resolution_x, scene.render.resolution_y = 16, 12
scene.render.resolution_percentage = 100
scene.render.engine = "MULTISCALE"
scene.render.image_settings.file_format = "PNG"
bpy.ops.wm.save_as_mainfile(filepath={blend!r})
"""

MESSAGE = (
    "Multiscale: Camera 'Zero' has a scale of zero on an axis (world scale (0, 0, 0)): "
    "give it a non-zero scale, 1 is best, in Object Properties > Transform"
)


def test_failed_command_line_render_exits_non_zero_and_keeps_the_output(
    run_blender, linux_zip, tmp_path
):
    env = {"BLENDER_USER_RESOURCES": str(tmp_path / "user")}
    blend = tmp_path / "zero.blend"
    code = MAKE.format(zip=str(linux_zip), blend=str(blend))
    run_blender(
        ["-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", code], env=env
    )
    out = tmp_path / "frame_0001.png"
    out.write_bytes(b"the user's own image")
    proc = run_blender(
        ["-b", str(blend), "-o", str(tmp_path / "frame_####"), "-f", "1"], env=env, check=False
    )
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert MESSAGE in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert out.read_bytes() == b"the user's own image"
