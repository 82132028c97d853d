"""Render the dolly sample as a short video with Blender's own FFmpeg output.

    blender -b sample_blends/dolly.blend --python-exit-code 1 --python tools/demo_anim.py \
        -- --out out/dolly.mp4 --percentage 25 --step 2

(`make demo-anim` runs this.) Registers the package from this checkout (as
sample_blends/make_samples.py does), renders frames start..end every --step-th at
--percentage of the sample's 640x360 into an H.264 MPEG-4 file, keeps the fields in
--cache (one per frame: the rig moves), and prints each frame's seconds and what its
field cost. With --stills DIR it also writes a few frames as PNG for the user guide.
"""

import argparse
import os
import sys
import time

import bpy

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def enable_multiscale():
    if hasattr(bpy.types.Scene, "multiscale"):
        return
    sys.path.insert(0, REPO)
    import multiscale_camera

    multiscale_camera.register()


def video_output(scene, path):
    render = scene.render
    settings = render.image_settings
    if hasattr(settings, "media_type"):  # Blender 5: the kind of output first
        settings.media_type = "VIDEO"
    settings.file_format = "FFMPEG"
    render.ffmpeg.format = "MPEG4"
    render.ffmpeg.codec = "H264"
    render.ffmpeg.constant_rate_factor = "MEDIUM"
    render.filepath = path
    render.use_file_extension = False


def main(argv):
    parser = argparse.ArgumentParser(prog="demo_anim.py")
    parser.add_argument("--out", required=True, help="the video file (.mp4)")
    parser.add_argument("--percentage", type=int, default=25)
    parser.add_argument("--step", type=int, default=1, help="render every step-th frame")
    parser.add_argument("--cache", default=None, help="field cache folder")
    parser.add_argument("--quality", default=None, help="the rig's quality (PREVIEW, ...)")
    parser.add_argument("--stills", default=None, help="folder for PNGs of a few frames")
    args = parser.parse_args(argv)
    enable_multiscale()
    scene = bpy.context.scene
    scene.render.resolution_percentage = args.percentage
    scene.frame_step = args.step
    if args.quality:
        scene.multiscale.quality = args.quality
    if args.cache:
        scene.multiscale.cache_folder = os.path.abspath(args.cache)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    video_output(scene, os.path.abspath(args.out))
    times = []
    bpy.app.handlers.render_pre.append(lambda *_: times.append(time.perf_counter()))
    bpy.app.handlers.render_post.append(
        lambda s, *_: print(
            f"DEMO_ANIM frame {s.frame_current}: {time.perf_counter() - times[-1]:.2f} s"
        )
    )
    start = time.perf_counter()
    bpy.ops.render.render(animation=True)
    frames = len(range(scene.frame_start, scene.frame_end + 1, scene.frame_step))
    print(
        f"DEMO_ANIM {frames} frames at {scene.render.resolution_x * args.percentage // 100}x"
        f"{scene.render.resolution_y * args.percentage // 100} in "
        f"{time.perf_counter() - start:.1f} s -> {args.out}"
    )
    if args.stills:
        stills(scene, args.stills)


def stills(scene, folder):
    """A PNG of the first, middle and last frame (the user guide shows them)."""
    os.makedirs(folder, exist_ok=True)
    settings = scene.render.image_settings
    if hasattr(settings, "media_type"):
        settings.media_type = "IMAGE"
    settings.file_format = "PNG"
    scene.render.use_file_extension = True
    first, last = scene.frame_start, scene.frame_end
    for frame in (first, (first + last) // 2, last):
        scene.frame_set(frame)
        scene.render.filepath = os.path.join(os.path.abspath(folder), f"dolly_{frame:02d}")
        bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else [])
