"""Benchmark: from the end of a stroke on a mask to the live picture updated.

    nice -n 10 .venv/bin/python bench/live_picture.py [--strokes 20 --out bench/live_picture.json]

The demo scene (``fixtures.blender.samples.build_demo``, rendered at 640x360: the live
picture is 480x270), live picture on. Each simulated stroke paints a white disc of
radius 5 px into camera 2's mask, at a new place on its ring each time (so every
stroke asks for a new field), as a brush's stroke leaves the image: written into its
pixels, ``image.update()``. The clock starts when the stroke is written and stops when
the picture is in the image "Multiscale Live"; in between the live picture's timer is
called as Blender calls it (``LivePicture.tick``, sleeping the interval it returns), so
the figure includes the change's detection, the settling time, the PREVIEW build, the
simplification and the render. One stroke is made and waited for first (the worker
processes start, the BVH tree is built), outside the figures. Fields are cached in a
temporary folder.

Writes JSON: seconds per stroke, median, p95 (nearest rank), the seconds of each
stage (field, simplify, render), the CPU seconds of this process per stroke (with
``--threads 1`` the whole work: no worker processes), the load average before and
after, the cores, the commit.
"""

import argparse
import atexit
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the repository, not bench/ (whose cycles.py would hide Blender's add-on of that name)
sys.path[0] = str(ROOT)
# fields go to a folder of their own, not the user's cache
os.environ["MULTISCALE_CACHE_DIR"] = tempfile.mkdtemp(prefix="multiscale-live-bench-")
atexit.register(shutil.rmtree, os.environ["MULTISCALE_CACHE_DIR"], ignore_errors=True)

import bpy  # noqa: E402
import numpy as np  # noqa: E402

import multiscale_camera  # noqa: E402
from fixtures.blender.samples import build_demo  # noqa: E402
from multiscale_camera.render.fields import SERVICE  # noqa: E402
from multiscale_camera.ui.live_picture import IMAGE_NAME  # noqa: E402


def stroke(image, cx, cy, radius=5.0):
    """Paint a white disc centred at pixel (cx, cy) (row 0 at the top) into ``image``."""
    w, h = image.size
    buf = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(buf)
    rgba = buf.reshape(h, w, 4)
    yy, xx = np.mgrid[0:h, 0:w]
    inside = (xx + 0.5 - cx) ** 2 + (h - 1 - yy + 0.5 - cy) ** 2 <= radius**2
    rgba[inside, :3] = 1.0
    image.pixels.foreach_set(buf)
    image.update()


def wait_for_picture(live, updates, timeout=60.0):
    """Call the timer as Blender does until ``live.updates`` exceeds ``updates``; the
    seconds until the call that showed the picture returned (not the interval it then
    asks for)."""
    t0 = time.perf_counter()
    while True:
        delay = live.tick()
        if live.updates > updates:
            return time.perf_counter() - t0
        if live.message:
            raise RuntimeError(live.message)
        if time.perf_counter() - t0 > timeout:
            raise RuntimeError("no live picture within the timeout")
        time.sleep(delay)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--strokes", type=int, default=20)
    ap.add_argument("--out", default=str(ROOT / "bench" / "live_picture.json"))
    ap.add_argument(
        "--threads",
        type=int,
        default=0,
        help="Render > Performance > Threads (0: one worker per core; 1: all in this "
        "process, so its CPU seconds are the whole work's)",
    )
    args = ap.parse_args()
    load_before = os.getloadavg()
    multiscale_camera.register()
    try:
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        build_demo(scene)
        if args.threads:
            scene.render.threads_mode, scene.render.threads = "FIXED", args.threads
        live = SERVICE.live
        mask = scene.multiscale.cameras[1].mask
        w, h = mask.size
        seconds, cpu, stages = [], [], []
        for k in range(args.strokes + 1):
            angle = 2 * math.pi * k / (args.strokes + 1)
            r = 0.3 * min(w, h)
            stroke(mask, w / 2 + r * math.cos(angle), h / 2 + r * math.sin(angle))
            c0 = time.process_time()
            took = wait_for_picture(live, live.updates)
            if k:  # the first starts the workers and builds the tree
                seconds.append(round(took, 3))
                cpu.append(round(time.process_time() - c0, 3))
                stages.append({n: round(float(v), 3) for n, v in live.stages.items()})
        image = bpy.data.images[IMAGE_NAME]
        size = list(image.size)
    finally:
        multiscale_camera.unregister()
    ranked = sorted(seconds)
    p95 = ranked[max(0, math.ceil(0.95 * len(ranked)) - 1)]
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()
    result = {
        "what": "end of a stroke on camera 2's mask to the live picture updated, demo",
        "live_size": size,
        "strokes": len(seconds),
        "seconds": seconds,
        "median_s": round(float(np.median(seconds)), 3),
        "p95_s": p95,
        "threads": args.threads,
        "cpu_s_this_process": cpu,
        "median_cpu_s_this_process": round(float(np.median(cpu)), 3),
        "stages_s": stages,
        "cores": os.cpu_count(),
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
        "commit": commit,
        "command": "nice -n 10 .venv/bin/python bench/live_picture.py "
        f"--strokes {args.strokes} --threads {args.threads}",
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
