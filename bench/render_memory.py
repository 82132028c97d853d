"""Benchmark: the memory guard's render estimate against a render's measured peak.

    .venv/bin/python bench/render_memory.py [--rows IMAGE_BLEND:1920x1080 ...]

Each row, in a fresh process with the bpy module: the two-camera test scene
(``fixtures.blender.scenes.two_camera_scene``) at the row's size, its field built
first (Compute Field: the field is then cached, as for a second F12), then the peak
resident sizes of this process and of the runtime's workers are reset
(``/proc/<pid>/clear_refs``: 5) and one render (``bpy.ops.render.render``) is
measured: the main process's peak over its resident size before the render, plus each
worker's peak over its size before (summed: each counted as if they came at once, as
the guard must assume). The estimate is ``core.quality.render_memory`` of the frame's
shapes, as ``render.memory.guard_memory`` makes it. Linux only (/proc). Writes
bench/render_memory.json.
"""

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "bench" / "render_memory.json"

from bench.memory import proc_status_kb  # noqa: E402 (after the path)

# method:WxH[:pN] (pN: the render's worker processes, default one per core). ROWS set
# the render constants of core/quality/memory.py; HELD_OUT rows were measured after.
ROWS = (
    "IMAGE_BLEND:480x270",
    "IMAGE_BLEND:960x540",
    "IMAGE_BLEND:960x540:p1",
    "IMAGE_BLEND:1920x1080",
    "IMAGE_BLEND:1920x1080:p1",
)
HELD_OUT = ("IMAGE_BLEND:1280x720", "SCALAR_FIELD:960x540")


def _reset_peak(pid="self"):
    """Set the process's VmHWM to its resident size now (Linux >= 4.0)."""
    with open(f"/proc/{pid}/clear_refs", "w") as refs:
        refs.write("5")


def run_one(spec):
    """Render one row in this process; its row (a dict)."""
    import bpy

    import multiscale_camera
    from fixtures.blender.scenes import two_camera_scene
    from multiscale_camera.core.quality import render_memory
    from multiscale_camera.core.runtime import runtime, worker_count
    from multiscale_camera.render.fields import SERVICE

    method, size, *more = spec.split(":")
    width, height = (int(x) for x in size.split("x"))
    multiscale_camera.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    two_camera_scene(scene, width, height)
    scene.multiscale.method = method
    scene.multiscale.memory_budget_mb = 1 << 20  # measured, not guarded
    if more:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = int(more[0].lstrip("p"))
    bpy.ops.multiscale.compute_field()
    request = SERVICE.request(scene)
    fld = SERVICE.cached(request)
    traced = getattr(fld, "traced", None)
    rays, vertices = (0, 0) if traced is None else traced.vertices.shape[:2]
    processes = worker_count(scene.render.threads if more else 0)
    estimate = render_memory(
        width, height, max(1, int(scene.multiscale.samples)), rays, vertices, processes
    )
    before = {pid: proc_status_kb("VmRSS", pid) / 1024 for pid in runtime().pids()}
    for pid in before:
        _reset_peak(pid)
    _reset_peak()
    main_before = proc_status_kb("VmRSS") / 1024
    peaks, done = {}, threading.Event()

    def watch():  # workers started during the render count from 0
        while not done.wait(0.2):
            for pid in runtime().pids():
                peaks[pid] = max(peaks.get(pid, 0), proc_status_kb("VmHWM", pid) / 1024)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    start = time.perf_counter()
    bpy.ops.render.render()
    seconds = time.perf_counter() - start
    done.set()
    watcher.join()
    for pid in runtime().pids():
        peaks[pid] = max(peaks.get(pid, 0), proc_status_kb("VmHWM", pid) / 1024)
    main = proc_status_kb("VmHWM") / 1024 - main_before
    workers = [round(peak - before.get(pid, 0), 1) for pid, peak in peaks.items()]
    measured = main + sum(workers)
    return {
        "row": spec,
        "held_out": spec in HELD_OUT,
        "pixels": width * height,
        "traced_rays": int(rays),
        "vertices": int(vertices),
        "workers": estimate.workers,
        "main_before_mb": round(main_before, 1),
        "peak_main_added_mb": round(main, 1),
        "peak_workers_added_mb": workers,
        "measured_mb": round(measured, 1),
        "estimated_mb": round(estimate.total / 2**20, 1),
        "estimated_main_mb": round(estimate.main / 2**20, 1),
        "estimated_worker_mb": round(estimate.worker / 2**20, 1),
        "ratio": round(estimate.total / 2**20 / measured, 3),
        "main_bytes_per_pixel": round(main * 2**20 / (width * height), 1),
        "parts_mb": {k: round(v / 2**20, 1) for k, v in estimate.parts.items()},
        "render_seconds": round(seconds, 2),
        "load_1min": round(os.getloadavg()[0], 2),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", nargs="+", default=list(ROWS + HELD_OUT))
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print("ROW " + json.dumps(run_one(args.one)), flush=True)
        os._exit(0)  # the bpy module's atexit handlers are slow and say nothing here
    rows = []
    for spec in args.rows:
        done = subprocess.run(
            [sys.executable, __file__, "--one", spec], capture_output=True, text=True, cwd=ROOT
        )
        found = [line for line in done.stdout.splitlines() if line.startswith("ROW ")]
        if not found:
            print(done.stdout[-2000:], done.stderr[-2000:], file=sys.stderr)
            continue
        row = json.loads(found[-1][4:])
        rows.append(row)
        print(
            f"{spec:30s} measured {row['measured_mb']:7.1f} MB (main "
            f"{row['peak_main_added_mb']} MB, {row['main_bytes_per_pixel']} B/px; workers "
            f"{row['peak_workers_added_mb']})  estimated {row['estimated_mb']:7.1f} MB  "
            f"ratio {row['ratio']:.2f}  ({row['render_seconds']} s, load {row['load_1min']})",
            flush=True,
        )
    args.out.write_text(json.dumps({"rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
