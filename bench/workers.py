"""Benchmark: the worker runtime, and the demo scene's first Compute Field and renders.

    tools/blender -b sample_blends/demo.blend --python bench/workers.py -- [--out FILE]
    blender -b demo.blend --python bench/workers.py -- \
        --installed bl_ext.user_default.multiscale_camera
    tools/blender -b sample_blends/demo.blend --python bench/workers.py -- --repo OLD --demo-only

Reports the start-up of the field workers (plain Pythons) and of the render workers
(background Blenders, or Pythons that import bpy), a run of two no-op items on warm
workers, the cost an item in a stream of 2000, and a 256^3 float32 grid sent to two
workers (copied into shared memory, mapped there, read through); then the open scene
as saved (the demo: 640x360, HIGH): Compute Field with the field cache empty, a render
(its render workers started if none are up), and the same render again. ``--demo-only``
times the scene alone, which code without the runtime runs too (``--repo`` names the
checkout whose package is registered). The 1-minute load average before and after
goes with every figure: the machine may be shared. Writes bench/workers.json (or --out).
"""

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = Path(__file__).with_suffix(".json")


def package(args):
    """The registered package (this checkout's, ``--repo``'s, or the installed one)."""
    import bpy

    if args.installed:
        return sys.modules[args.installed]
    sys.path.insert(0, str(Path(args.repo).resolve()))
    import multiscale_camera

    if not hasattr(bpy.types.Scene, "multiscale"):
        multiscale_camera.register()
    return multiscale_camera


def runtime_figures(pkg):
    """Start-up, round trip, per-item cost and a 256^3 grid, on a Runtime of its own."""
    import importlib

    import numpy as np

    rt_module = importlib.import_module(pkg.__name__ + ".core.runtime")
    worker = importlib.import_module(pkg.__name__ + ".core.runtime.worker")
    processes = importlib.import_module(pkg.__name__ + ".render.processes")
    rt = rt_module.Runtime()
    out = {"cores": rt_module.cores()}
    try:
        n = rt_module.cores()
        t = time.perf_counter()
        started = rt.warm(n)
        out["python_start_seconds"] = round(time.perf_counter() - t, 3)
        out["python_started"] = len(started)
        launcher = processes.blender_launcher()
        out["render_worker_command"] = launcher.prefix[0]
        t = time.perf_counter()
        started = rt.warm(n, launcher=launcher)
        out["render_start_seconds"] = round(time.perf_counter() - t, 3)
        out["render_started"] = len(started)
        laps = []
        for _ in range(200):
            t = time.perf_counter()
            rt.map(worker.probe, [0, 1], 2)
            laps.append(time.perf_counter() - t)
        out["round_trip_ms_median"] = round(statistics.median(laps) * 1e3, 3)
        t = time.perf_counter()
        rt.map(worker.probe, range(2000), n)
        out["stream_item_us"] = round((time.perf_counter() - t) / 2000 * 1e6, 1)
        grid = np.random.default_rng(0).random((256, 256, 256), dtype=np.float32)
        laps = []
        for _ in range(5):
            t = time.perf_counter()
            sums = rt.map(partial(worker.touch, (grid,)), [0, 1], 2).results
            laps.append(time.perf_counter() - t)
        assert sums[0] == sums[1] == worker.touch((grid,), 0, None)
        out["grid_256_seconds_median"] = round(statistics.median(laps), 3)
        t = time.perf_counter()
        worker.touch((grid,), 0, None)
        out["grid_256_read_here_seconds"] = round(time.perf_counter() - t, 3)
    finally:
        rt.shutdown()
    return out


def demo_figures(pkg):
    """The open scene: Compute Field (cache empty), a render, the render again."""
    import importlib

    import bpy

    pipeline = importlib.import_module(pkg.__name__ + ".render.pipeline")
    scene = bpy.context.scene
    render = scene.render
    out = {
        "size": [
            render.resolution_x * render.resolution_percentage // 100,
            render.resolution_y * render.resolution_percentage // 100,
        ],
        "quality": scene.multiscale.quality,
        "threads_mode": render.threads_mode,
    }
    render.filepath = os.path.join(tempfile.mkdtemp(prefix="bench-workers-"), "render.png")
    pipeline.clear_fields()
    t = time.perf_counter()
    out["compute_field"] = sorted(bpy.ops.multiscale.compute_field())
    out["compute_field_seconds"] = round(time.perf_counter() - t, 2)
    stages = json.loads(scene.multiscale.report).get("seconds", {})
    out["field_stages"] = {k: round(v, 2) for k, v in stages.items()}
    t = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    out["render_seconds"] = round(time.perf_counter() - t, 2)
    t = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    out["render_again_seconds"] = round(time.perf_counter() - t, 2)
    return out


def main(argv):
    parser = argparse.ArgumentParser(prog="bench/workers.py")
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--repo", default=str(ROOT))
    parser.add_argument("--installed", default=None, help="an enabled extension's module")
    parser.add_argument("--demo-only", action="store_true")
    args = parser.parse_args(argv)
    os.environ.setdefault("MULTISCALE_CACHE_DIR", tempfile.mkdtemp(prefix="bench-cache-"))
    import bpy

    pkg = package(args)
    result = {
        "blender": bpy.app.version_string,
        "background": bool(bpy.app.background),
        "package": pkg.__name__,
        "load_before": round(os.getloadavg()[0], 2),
    }
    if not args.demo_only:
        result["runtime"] = runtime_figures(pkg)
    result["demo"] = demo_figures(pkg)
    result["load_after"] = round(os.getloadavg()[0], 2)
    print("BENCH_WORKERS", json.dumps(result))
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


main(sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else [])
