"""Benchmark: the memory guard's estimate against the measured peak of a field build.

    .venv/bin/python bench/memory.py [--rows zoom_rig:SCALAR_FIELD:PREVIEW:480x270 ...]

Each row builds one field in a fresh process (so its peak is its own) and measures the
peak resident size of that process (``VmHWM``) plus the peak of each worker process
of the runtime (``VmHWM``, read every 0.25 s during the build and at its end, so a
worker given up on the way counts too; summed: each peak counted as if they came at
once, as the guard must assume). The estimate (``core.quality.memory``) is
made from the rig's shapes before the build; its main-process part is added to the
process's resident size before the build (the interpreter, numpy and the rig, already
held when a render starts). Each row also records the rounds of the lattice's trace
(``rounds``: rays, and of them preserved pixels'), the rounds the workers share.
Prints a table and writes bench/memory.json. ``--re-estimate`` makes the estimate
columns of every row in --out again with the model as it is, without building.
"""

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "bench" / "memory.json"
# rig:method:quality:WxH[:pN]; SCALAR_FIELD_NESTED forces nested grids, SCALAR_FIELD one
# uniform grid (as bench/methods.py); pN sets the worker processes (default: one per
# core). ROWS calibrated the constants of core/quality/memory.py; HELD_OUT rows were
# measured after the constants were frozen, to check them on rows they were not fitted to.
ROWS = (
    "zoom_rig:IMAGE_BLEND:STANDARD:1920x1080",
    "three_camera_rig:IMAGE_BLEND:STANDARD:1920x1080",
    "zoom_rig:SCALAR_FIELD:PREVIEW:480x270",
    "zoom_rig:SCALAR_FIELD:STANDARD:480x270",
    "three_camera_rig:SCALAR_FIELD:STANDARD:480x270",
    "zoom25_rig:SCALAR_FIELD:PREVIEW:480x270",
    "contradictory_rig:SCALAR_FIELD:STANDARD:480x270",
    "zoom_rig:SCALAR_FIELD:PREVIEW:960x540",
    "zoom_rig:SCALAR_FIELD_NESTED:PREVIEW:480x270",
    "zoom_rig:SCALAR_FIELD_NESTED:STANDARD:480x270",
    "zoom25_rig:SCALAR_FIELD_NESTED:PREVIEW:480x270",
    "zoom1000_rig:SCALAR_FIELD_NESTED:PREVIEW:480x270",
)
HELD_OUT = (
    "three_camera_rig:SCALAR_FIELD:PREVIEW:960x540",
    "zoom25_rig:SCALAR_FIELD:STANDARD:480x270",
    "zoom_rig:SCALAR_FIELD:PREVIEW:480x270:p1",
    "zoom_rig:SCALAR_FIELD:STANDARD:480x270:p3",
    # the default build (AUTO: IMAGE_BLEND built and measured, its fold count's bands in
    # workers at 1920x1080, in the main process at 480x270)
    "zoom_rig:AUTO:STANDARD:1920x1080",
    "three_camera_rig:AUTO:STANDARD:1920x1080",
    "zoom25_rig:AUTO:STANDARD:1920x1080",
    "zoom25_rig:AUTO:PREVIEW:480x270",
)


def proc_status_kb(field, pid="self"):
    """A field of /proc/<pid>/status in kB (0 when it cannot be read)."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def row_rig(spec):
    """(Rig, method, the core's Settings) of row ``spec``."""
    from fixtures import rigs
    from multiscale_camera.core.geometry import Rig
    from multiscale_camera.core.methods import settings_for

    rig_name, method, quality, size, *more = spec.split(":")
    width, height = (int(x) for x in size.split("x"))
    cams, masks = getattr(rigs, rig_name)(width, height)
    settings = settings_for(quality)
    if method.startswith("SCALAR_FIELD"):
        settings = replace(settings, nested=method.endswith("NESTED"))
    if more:
        settings = replace(settings, processes=int(more[0].lstrip("p")))
    return Rig(cams, masks), method.replace("_NESTED", ""), settings


def estimated(row, estimate, before):
    """``row``'s estimate columns for ``estimate`` (a MemoryEstimate) made in a process
    of ``before`` MB, against its measured peaks."""
    estimated_main = before + estimate.main / 2**20
    estimated_worker = estimate.worker / 2**20
    total = before + estimate.total / 2**20
    return {
        "estimated_traced_rays": estimate.shapes.get("traced_rays", 0),
        "estimated_vertices": estimate.shapes.get("vertices", 0),
        "estimated_mb": round(total, 1),
        "estimated_main_mb": round(estimated_main, 1),
        "estimated_worker_mb": round(estimated_worker, 1),
        "ratio": round(total / row["measured_mb"], 3),
        **ratios(row["peak_main_mb"], row["peak_workers_mb"], estimated_main, estimated_worker),
        "parts_mb": {k: round(v / 2**20, 1) for k, v in estimate.parts.items()},
    }


def guarded(rig, method, settings, built=None):
    """The estimate the memory guard checks for a build of ``method`` that built
    ``built``: AUTO's first candidate before the build and, when AUTO went on to
    another (``built``), that one's too before it is built: the larger of the two."""
    from multiscale_camera.core.quality import estimate_memory
    from multiscale_camera.core.runtime import worker_count

    workers = worker_count(settings.processes)
    estimate = estimate_memory(rig, method, settings, workers)
    if method == "AUTO" and built not in (None, "IMAGE_BLEND"):
        estimate = max(
            estimate, estimate_memory(rig, built, settings, workers), key=lambda e: e.total
        )
    return estimate


def re_estimate(row):
    """``row`` (measured before) with its estimate columns made again by the
    committed model, without building."""
    rig, method, settings = row_rig(row["row"])
    estimate = guarded(rig, method, settings, row.get("built"))
    return {**row, **estimated(row, estimate, row["before_mb"])}


def run_one(spec):
    """Build one field in this process; its row (a dict)."""
    from multiscale_camera.core.field.tracer import FieldTracer
    from multiscale_camera.core.methods import prepare
    from multiscale_camera.core.runtime import runtime

    rig, method, settings = row_rig(spec)
    before = proc_status_kb("VmRSS") / 1024
    estimate = guarded(rig, method, settings)
    peaks, done = {}, threading.Event()

    def watch():  # every worker's peak, also of one given up (ended) before the build ends
        while not done.wait(0.25):
            for pid in runtime().pids():
                peaks[pid] = max(peaks.get(pid, 0), proc_status_kb("VmHWM", pid) / 1024)

    rounds = []  # each round of the lattice's trace: [rays, of them preserved pixels']
    trace_pixels = FieldTracer.trace_pixels

    def counted(tracer, ix, iy, *args, **kwargs):
        preserved = int(np.any([m[iy, ix] for m in tracer.rig.masks], axis=0).sum())
        rounds.append([len(ix), preserved])
        return trace_pixels(tracer, ix, iy, *args, **kwargs)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    start = time.perf_counter()
    FieldTracer.trace_pixels = counted
    try:
        fld = prepare(rig, method, settings)
    finally:
        FieldTracer.trace_pixels = trace_pixels
    seconds = time.perf_counter() - start
    done.set()
    watcher.join()
    for pid in runtime().pids():
        peaks[pid] = max(peaks.get(pid, 0), proc_status_kb("VmHWM", pid) / 1024)
    # VmHWM, not ru_maxrss: Linux carries the maximum of the process that forked this
    # one across exec (from pytest with bpy imported: 940 MB before any work)
    main = proc_status_kb("VmHWM") / 1024
    workers = list(peaks.values())
    measured = main + sum(workers)
    row = {
        "row": spec,
        "built": fld.method,
        "traced_rays": int(fld.stats.get("traced", 0)),
        "vertices": int(fld.traced.vertices.shape[1]) if getattr(fld, "traced", None) else 0,
        "before_mb": round(before, 1),
        "peak_main_mb": round(main, 1),
        "peak_workers_mb": [round(w, 1) for w in workers],
        "measured_mb": round(measured, 1),
        "held_out": spec in HELD_OUT,
    }
    if fld.method != "IMAGE_BLEND":  # AUTO went on: the guard checked that one too
        estimate = guarded(rig, method, settings, fld.method)
    return {
        **row,
        **estimated(row, estimate, before),
        "rounds": rounds,
        "build_seconds": round(seconds, 2),
        "load_1min": round(os.getloadavg()[0], 2),
    }


def ratios(main, workers, estimated_main, estimated_worker):
    """The main process's and the largest worker's estimate over measured peak (MB);
    the worker's None when no worker ran or none was estimated."""
    worker = max(workers) if workers and estimated_worker else None
    return {
        "main_ratio": round(estimated_main / main, 3),
        "worker_ratio": round(estimated_worker / worker, 3) if worker else None,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", nargs="+", default=list(ROWS))
    parser.add_argument("--held-out", action="store_true", help="run the HELD_OUT rows")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument(
        "--merge", action="store_true", help="replace only these rows in --out, keep the rest"
    )
    parser.add_argument(
        "--re-estimate",
        action="store_true",
        help="make the estimate columns of every row in --out again, without building",
    )
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one)))
        return
    if args.re_estimate:
        rows = [re_estimate(r) for r in json.loads(args.out.read_text())["rows"]]
        args.out.write_text(json.dumps({"rows": rows}, indent=1) + "\n")
        return
    specs = list(HELD_OUT) if args.held_out else args.rows
    rows = []
    for spec in specs:
        done = subprocess.run(
            [sys.executable, __file__, "--one", spec], capture_output=True, text=True, cwd=ROOT
        )
        if done.returncode:
            print(done.stderr[-2000:], file=sys.stderr)
            continue
        row = json.loads(done.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"{spec:50s} measured {row['measured_mb']:7.1f} MB  estimated "
            f"{row['estimated_mb']:7.1f} MB  ratio {row['ratio']:.2f} (main "
            f"{row['main_ratio']:.2f}, worker {row['worker_ratio']})  "
            f"(rays {row['traced_rays']} est {row['estimated_traced_rays']}, "
            f"{row['build_seconds']} s, load {row['load_1min']})",
            flush=True,
        )
    if args.merge and args.out.exists():
        new = {row["row"] for row in rows}
        kept = [r for r in json.loads(args.out.read_text())["rows"] if r["row"] not in new]
        rows = kept + rows
    args.out.write_text(json.dumps({"rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
