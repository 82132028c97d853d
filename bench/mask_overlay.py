"""Benchmark: what the Image Editor's mask overlay costs each time it is recomputed
(about once a second while a listed mask is shown), and what Mask from Selected costs.

    .venv/bin/python bench/mask_overlay.py [--width 1920 --height 1080 --repeats 5]

The overlay: three cameras' masks (the rings of ``fixtures.masks.rings``) as Blender
images at the render size, read and resampled to the overlay's size (at most 480 px
wide) and turned into its picture (``ui.mask_overlay.rig_masks`` and
``ui.mask_shapes.overlay_rgba``); "painting": the refresh while one mask is painted,
which reads that mask alone (``MaskOverlay.masks_for``). The upload to the GPU is not
included (background Blender has none). Mask from Selected: the two-camera test scene
at the render size, the sphere selected, margin 4. Prints the median of the repeats,
milliseconds, as JSON.
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import bpy  # noqa: E402

import multiscale_camera  # noqa: E402
from fixtures.blender.objects import mask_image  # noqa: E402
from fixtures.blender.scenes import two_camera_scene  # noqa: E402
from fixtures.masks import rings  # noqa: E402
from multiscale_camera.render.guide import guide_size  # noqa: E402
from multiscale_camera.ui.mask_overlay import (  # noqa: E402
    OVERLAY_MAX_WIDTH,
    MaskOverlay,
    rig_masks,
)
from multiscale_camera.ui.mask_shapes import overlay_rgba  # noqa: E402


def median_ms(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0)
    return round(statistics.median(times), 1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    w, h = args.width, args.height
    multiscale_camera.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    c1, c2 = two_camera_scene(scene, w, h)
    items = scene.multiscale.cameras
    extra = items.add()
    extra.camera = c2
    for k, (item, mask) in enumerate(zip(items, rings(w, h))):
        item.mask = mask_image(f"ring {k + 1}", mask)
    size = guide_size(w, h, max_width=OVERLAY_MAX_WIDTH)
    overlay = median_ms(lambda: overlay_rgba(rig_masks(scene, size), 1), args.repeats)
    cached = MaskOverlay()
    cached.masks_for(scene, 1, size, 0.0)
    painting = median_ms(
        lambda: overlay_rgba(cached.masks_for(scene, 1, size, 1.0), 1), args.repeats
    )

    scene.multiscale.active_index = 1
    bpy.ops.object.select_all(action="DESELECT")
    bpy.data.objects["Sphere"].select_set(True)
    silhouette = median_ms(lambda: bpy.ops.multiscale.mask_from_selected(margin=4), args.repeats)
    print(
        json.dumps(
            {
                "render_size": [w, h],
                "overlay_size": list(size),
                "overlay_refresh_ms": overlay,
                "overlay_refresh_painting_ms": painting,
                "mask_from_selected_ms": silhouette,
                "repeats": args.repeats,
            }
        )
    )
    multiscale_camera.unregister()


if __name__ == "__main__":
    main()
