"""Benchmark: what one trace worker holds, stage by stage (the memory guard's worker
model, core/quality/memory.py).

    nice -n 10 .venv/bin/python bench/worker_memory.py zoom25_rig:SCALAR_FIELD:STANDARD:480x270

Builds the row's field (as bench/memory.py, rows ``rig:method:quality:WxH``), keeps the
largest round of the lattice's trace (its pixels and the tracer, as a worker gets
them), then replays one worker's share of that round (every n-th ray, as
``FieldTracer._shared`` deals them) in a fresh process under ``tracemalloc``: for each
stage (each camera's preserved rays laid out and sampled, the transitions' streamlines,
the merge of the share's parts, its pickled copy for the trip back) the bytes held when
it starts, the peak during it, and the shapes (rays, vertices). Prints a table and
the share's composition: rays per camera, the step limit, the preserved rays' kept
length and the streamlines'. Writes nothing.

    nice -n 10 .venv/bin/python bench/worker_memory.py \
        zoom_rig:IMAGE_BLEND:STANDARD:1920x1080 --measure

With ``--measure``: AUTO's measure of the row's field instead (built in this process,
the row's method; core/quality/measure_memory.py), under ``tracemalloc``: three fold
bands from the middle of the image (``report._fold_bands``, as a worker counts them)
and the along-ray measure of each camera's measured pixels.
"""

import argparse
import json
import pickle
import subprocess
import sys
import tempfile
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def capture(spec, path):
    """Build ``spec``'s field; pickle its largest trace round (tracer, pixels, step,
    step limit, share count) to ``path``."""
    from memory import row_rig

    from multiscale_camera.core.field import tracer as tracer_module
    from multiscale_camera.core.methods import prepare

    rig, method, settings = row_rig(spec)
    FieldTracer = tracer_module.FieldTracer
    trace_pixels = FieldTracer.trace_pixels
    largest = {}

    def counted(tracer, ix, iy, step, max_steps, *args, **kwargs):
        if len(ix) > len(largest.get("ix", ())):
            workers = tracer._workers(len(ix))
            shares = max(workers, -(-len(ix) // tracer_module.MAX_RAYS_PER_SHARE))
            largest.update(
                tracer=pickle.dumps(tracer),
                ix=ix,
                iy=iy,
                step=step,
                max_steps=max_steps,
                shares=shares if workers >= 2 else 1,
            )
        return trace_pixels(tracer, ix, iy, step, max_steps, *args, **kwargs)

    FieldTracer.trace_pixels = counted
    try:
        prepare(rig, method, settings)
    finally:
        FieldTracer.trace_pixels = trace_pixels
    Path(path).write_bytes(pickle.dumps(largest))


def replay(path):
    """One share of the captured round under tracemalloc; the stages as a list of
    dict (name, rays, vertices, start and peak bytes above the share's start)."""
    from multiscale_camera.core.field import preserved_rays as layout
    from multiscale_camera.core.field import trace as trace_module
    from multiscale_camera.core.field import tracer as tracer_module

    got = pickle.loads(Path(path).read_bytes())
    tracer = pickle.loads(got["tracer"])
    ix, iy, n = got["ix"], got["iy"], got["shares"]
    rows = np.arange(0, len(ix), n)
    stages = []
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]

    open_peaks = []  # the peak so far of each stage under way (an inner one resets it)

    def staged(name, function, shape):
        def run(*args, **kwargs):
            current, peak = tracemalloc.get_traced_memory()
            if open_peaks:
                open_peaks[-1] = max(open_peaks[-1], peak)
            open_peaks.append(current)
            tracemalloc.reset_peak()
            out = function(*args, **kwargs)
            peak = max(open_peaks.pop(), tracemalloc.get_traced_memory()[1])
            if open_peaks:
                open_peaks[-1] = max(open_peaks[-1], peak)
            stages.append(
                dict(name=name, start=current - base, peak=peak - base, **shape(args, out))
            )
            return out

        return run

    FieldTracer = tracer_module.FieldTracer
    FieldTracer.preserved_rays = staged(
        "preserved rays",
        FieldTracer.preserved_rays,
        lambda a, out: dict(
            camera=int(a[1]),
            rays=len(a[2]),
            vertices=int(a[5]),
            kept=int(out[1].vertices.shape[1]),
        ),
    )
    FieldTracer._trace_here = staged(
        "streamlines",
        FieldTracer._trace_here,
        lambda a, out: dict(
            rays=len(a[1]),
            vertices=int(out.vertices.shape[1]),
            kept=int(out.counts.max()) if len(out.counts) else 0,
        ),
    )
    tracer_module.merge = staged(
        "merge",
        trace_module.merge,
        lambda a, out: dict(rays=int(a[2]), vertices=int(out.vertices.shape[1])),
    )
    layout_name = "scheduled_rays" if callable(got["step"]) else "arc_length_rays"
    setattr(
        tracer_module,
        layout_name,
        staged(
            "  layout",
            getattr(layout, layout_name),
            lambda a, out: dict(rays=len(a[1]), vertices=int(a[4])),
        ),
    )
    share = tracer_module._trace_share(
        tracer, "pixels", ix, iy, got["step"], got["max_steps"], len(ix), (0, n), lambda: None
    )
    start = tracemalloc.get_traced_memory()[0] - base
    tracemalloc.reset_peak()
    sent = pickle.dumps(share)
    stages.append(
        dict(
            name="pickled share",
            start=start,
            peak=tracemalloc.get_traced_memory()[1] - base,
            rays=len(rows),
            bytes=len(sent),
        )
    )
    masks = tracer.rig.masks
    per_camera = [int(m[iy[rows], ix[rows]].sum()) for m in masks]
    return dict(
        round_rays=len(ix),
        share_rays=len(rows),
        shares=n,
        step_limit=int(got["max_steps"]),
        preserved_per_camera=per_camera,
        stages=stages,
    )


def measure(spec):
    """Peak bytes (under tracemalloc, above the built field) of three fold bands and of
    each camera's along-ray measure for row ``spec``'s field, printed."""
    from memory import row_rig

    from multiscale_camera.core.methods import prepare
    from multiscale_camera.core.quality import metrics
    from multiscale_camera.core.quality import report as rep

    rig, method, settings = row_rig(spec)
    fld = prepare(rig, method, replace(settings, processes=1))
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    w, h = rig.size
    xs, ys = np.arange(w), np.arange(h)
    k = fld.rays(np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64)).vertices.shape[1]
    _workers, rows = rep.fold_plan(w, h, k, 1)  # full bands, as one process cuts them
    starts = list(range(0, h - 1, rows - 1))
    print(f"{len(starts)} fold bands of {rows} rows, {rows * w * k} vertices ({k} a ray)")
    for r0 in starts[len(starts) // 2 : len(starts) // 2 + 3]:
        tracemalloc.reset_peak()
        rep._fold_bands(fld, xs, ys, rows, [r0], None)
        peak = (tracemalloc.get_traced_memory()[1] - base) / 2**20
        print(f"fold band at row {r0}: peak {peak:.1f} MB")
    for i in range(len(rig.cameras)):
        tracemalloc.reset_peak()
        ix, iy = metrics.measured_pixels(rig.masks[i])
        if len(ix):  # as the report measures them (in blocks, on vertex planes)
            rep._preserved_in_blocks(fld, i, ix, iy, None)
        peak = (tracemalloc.get_traced_memory()[1] - base) / 2**20
        print(f"along-ray measure, camera {i + 1}: {len(ix)} rays, peak {peak:.1f} MB")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("row")
    parser.add_argument("--replay", help=argparse.SUPPRESS)
    parser.add_argument("--measure", action="store_true", help="AUTO's measure, not a share")
    args = parser.parse_args()
    if args.measure:
        measure(args.row)
        return
    if args.replay:
        print(json.dumps(replay(args.replay)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "round.pickle"
        capture(args.row, path)
        done = subprocess.run(
            [sys.executable, __file__, args.row, "--replay", str(path)],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
    if done.returncode:
        print(done.stderr[-3000:], file=sys.stderr)
        sys.exit(1)
    out = json.loads(done.stdout.strip().splitlines()[-1])
    print(json.dumps({k: v for k, v in out.items() if k != "stages"}))
    for s in out["stages"]:
        extra = {k: v for k, v in s.items() if k not in ("name", "start", "peak")}
        print(
            f"{s['name']:16s} start {s['start'] / 2**20:7.1f} MB  peak {s['peak'] / 2**20:7.1f} "
            f"MB  {extra}"
        )


if __name__ == "__main__":
    main()
