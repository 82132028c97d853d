"""Benchmark: the longest the live picture's timer holds Blender's main thread.

    nice -n 10 .venv/bin/python bench/live_tick.py [--seconds 40 --out bench/live_tick.json]

The demo scene (``fixtures.blender.samples.build_demo``) rendered at 1920x1080 with its
three masks scaled to 1920x1080, live picture on, camera 2's mask shown in an Image
Editor (as a window would show it: the timer is run as in a window, not as in
background Blender). The timer (``LivePicture.tick``) is called as Blender calls it,
sleeping the interval it returns, for ``--seconds``; a stroke (a white disc of radius
20 px) is written into camera 2's mask every 3 s, so jobs start and are cancelled.
Each call is timed; the figures are the worst call, the 95th percentile (nearest
rank) and the worst call that started a job, in milliseconds, with the load average
before and after. Fields are cached in a temporary folder.
"""

import argparse
import atexit
import json
import math
import os
import shutil
import sys
import tempfile
import time
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[0] = str(ROOT)
os.environ["MULTISCALE_CACHE_DIR"] = tempfile.mkdtemp(prefix="multiscale-tick-bench-")
atexit.register(shutil.rmtree, os.environ["MULTISCALE_CACHE_DIR"], ignore_errors=True)

import bpy  # noqa: E402
import numpy as np  # noqa: E402

import multiscale_camera  # noqa: E402
from fixtures.blender.samples import build_demo  # noqa: E402
from multiscale_camera.render.fields import SERVICE  # noqa: E402
from multiscale_camera.ui import live_picture  # noqa: E402

SIZE = (1920, 1080)


def stroke(image, cx, cy, radius=20.0):
    """A white disc centred at pixel (cx, cy) (row 0 at the bottom) in ``image``."""
    w, h = image.size
    buf = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(buf)
    rgba = buf.reshape(h, w, 4)
    y0, y1 = max(int(cy - radius), 0), min(int(cy + radius) + 1, h)
    x0, x1 = max(int(cx - radius), 0), min(int(cx + radius) + 1, w)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    inside = (xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2 <= radius**2
    rgba[y0:y1, x0:x1][inside, :3] = 1.0
    image.pixels.foreach_set(buf)
    image.update()


def as_in_a_window(shown):
    """Run the live picture's timer as in a window showing the images ``shown``."""
    app = types.SimpleNamespace(
        background=False,
        is_job_running=bpy.app.is_job_running,
        handlers=bpy.app.handlers,
        timers=bpy.app.timers,
    )
    live_picture.bpy = types.SimpleNamespace(
        app=app, context=bpy.context, data=bpy.data, types=bpy.types
    )
    live_picture.shown_images = lambda _wm: set(shown)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    load_before = os.getloadavg()
    multiscale_camera.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    build_demo(scene)
    scene.render.resolution_x, scene.render.resolution_y = SIZE
    scene.render.resolution_percentage = 100
    for item in scene.multiscale.cameras:
        item.mask.scale(*SIZE)
    mask = scene.multiscale.cameras[1].mask
    as_in_a_window({mask.name})
    live = SERVICE.live
    ticks, starting = [], []
    t_end = time.perf_counter() + args.seconds
    next_stroke, k = time.perf_counter() + 3.0, 0
    while time.perf_counter() < t_end:
        if time.perf_counter() >= next_stroke:
            angle = 0.7 * k
            stroke(mask, 960 + 300 * math.cos(angle), 540 + 200 * math.sin(angle))
            next_stroke, k = next_stroke + 3.0, k + 1
        had = live.job
        t0 = time.perf_counter()
        delay = live.tick()
        dt = time.perf_counter() - t0
        ticks.append(dt)
        if live.job is not None and live.job is not had:
            starting.append(dt)
        time.sleep(delay)
    if live.job is not None:
        live.job.cancel()
        live.job.join(60)
    ms = sorted(1e3 * t for t in ticks)
    result = {
        "size": list(SIZE),
        "ticks": len(ms),
        "worst_ms": round(ms[-1], 1),
        "p95_ms": round(ms[math.ceil(0.95 * len(ms)) - 1], 1),
        "median_ms": round(ms[len(ms) // 2], 1),
        "worst_start_ms": round(1e3 * max(starting), 1) if starting else None,
        "jobs_started": len(starting),
        "pictures": live.updates,
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in os.getloadavg()],
        "cores": os.cpu_count(),
    }
    print(json.dumps(result, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    multiscale_camera.unregister()


if __name__ == "__main__":
    main()
