"""Install the built extension, render a sample scene with it, save EXR and PNG.

    BLENDER_USER_RESOURCES=out/blender-user blender -b --factory-startup \
        --python-exit-code 1 --python tools/demo.py -- \
        --zip dist/multiscale_camera-0.1.0-linux_x64.zip --blend sample_blends/demo.blend --out out

(`make demo` runs exactly this.) Writes OUT/demo.exr (multilayer, every pass) and
OUT/demo.png (Combined, sRGB, 8 bit), and prints the seconds each step took.
Set BLENDER_USER_RESOURCES to a throwaway folder: the extension is installed there.
"""

import argparse
import os
import sys
import time

import bpy
import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODULE = "bl_ext.user_default.multiscale_camera"


def srgb_encode(linear):
    """Linear values in [0, 1] -> sRGB-encoded values (the sRGB transfer function)."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def save_png(rgba, path):
    """Write a (H, W, 4) linear float image, row 0 at the top, as an 8-bit sRGB PNG."""
    height, width = rgba.shape[:2]
    pixels = rgba.copy()
    pixels[..., :3] = srgb_encode(pixels[..., :3])
    pixels[..., 3] = np.clip(pixels[..., 3], 0.0, 1.0)
    image = bpy.data.images.new("demo", width, height, alpha=True)
    image.pixels.foreach_set(pixels[::-1].astype(np.float32).ravel())  # bpy rows: bottom up
    image.filepath_raw = path
    image.file_format = "PNG"
    image.save()
    bpy.data.images.remove(image)


def main(argv):
    parser = argparse.ArgumentParser(prog="demo.py")
    parser.add_argument("--zip", required=True, help="the built linux-x64 extension zip")
    parser.add_argument("--blend", default=os.path.join(REPO, "sample_blends", "demo.blend"))
    parser.add_argument("--out", default=os.path.join(REPO, "out"))
    args = parser.parse_args(argv)
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    print(f"user folder: {bpy.utils.resource_path('USER')}")

    started = time.perf_counter()
    bpy.ops.extensions.package_install_files(
        filepath=os.path.abspath(args.zip), repo="user_default", enable_on_install=True
    )
    installed = time.perf_counter()
    if MODULE not in bpy.context.preferences.addons:
        raise SystemExit(f"{MODULE} is not enabled after installing {args.zip}")

    # Preferences (and so the enabled extension) survive loading a file.
    bpy.ops.wm.open_mainfile(filepath=os.path.abspath(args.blend), load_ui=False)
    scene = bpy.context.scene
    scene.render.engine = "MULTISCALE"
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.color_depth = "32"
    for layer in scene.view_layers:
        layer.use_pass_z = layer.use_pass_normal = layer.use_pass_object_index = True
    exr = os.path.join(out, "demo.exr")
    scene.render.filepath = exr
    opened = time.perf_counter()

    bpy.ops.render.render(write_still=True)
    rendered = time.perf_counter()

    sys.path.insert(0, REPO)
    from tests.exr import read_passes

    png = os.path.join(out, "demo.png")
    save_png(read_passes(exr)["Combined"], png)
    finished = time.perf_counter()

    print(f"wrote {exr}\nwrote {png}")
    print(
        f"seconds: install {installed - started:.2f}, open {opened - installed:.2f}, "
        f"render {rendered - opened:.2f}, png {finished - rendered:.2f}, "
        f"total {finished - started:.2f}"
    )


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else [])
