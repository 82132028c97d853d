"""Benchmark: field seconds per frame of the dolly sample, built in sequence against cold.

    .venv/bin/python bench/anim.py [--width 960 --height 540] [--frames 1 2 3]
        [--quality PREVIEW] [--method AUTO] [--scalar-reference]

Builds sample_blends/dolly.blend's scene (``fixtures.blender.samples.build_dolly``) with
the bpy module, reads its rig and settings (with the shot's layout, and with AUTO the
shot's one method: ``FieldService.shot_choice``, timed) at each frame as a render does
(the field service's request on the evaluated depsgraph), then builds the fields of
``--frames`` in order, each taking what the one before left valid
(``core.methods.FrameReuse``, as the field service does for an animated rig), and then
each of those frames again cold (the same method, nothing kept). Writes, per frame,
both times, what the sequential build took and rebuilt, and the seconds the frame's
rays for every pixel take from the field (``rays_s``: the render's share, which
IMAGE_BLEND's curves leave to it); the mean seconds of the frames after the first, the
ratio to cold (the target: 1/3 or less), the shot choice's seconds (once per shot and
process), with ``--scalar-reference`` a cold SCALAR_FIELD build of the second frame,
the machine's load and the commit, to bench/anim.json.
"""

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# bench/ itself off the path: its cycles.py would stand in for Blender's Cycles add-on
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "bench"]
sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402  (bench/ off the path and the repository on it first)
import numpy as np  # noqa: E402

import multiscale_camera  # noqa: E402
from bench.methods import _commit  # noqa: E402
from fixtures.blender import samples  # noqa: E402
from multiscale_camera.core.diagnostics import Diagnostics  # noqa: E402
from multiscale_camera.core.methods import FrameReuse, prepare  # noqa: E402
from multiscale_camera.render.fields import SERVICE  # noqa: E402

OUT = ROOT / "bench" / "anim.json"
# The frames after the first must build in at most this share of a cold build.
TARGET_RATIO = 1 / 3


def dolly_rigs(width, height, frames, quality, method=None):
    """{frame: Rig} of the dolly at ``width`` x ``height``, its Settings (the shot's,
    the same at every frame), SCALAR_FIELD's Settings (the shot's layout) and (method,
    quality, seconds of its first request: the shot's layout, or AUTO's choice)."""
    multiscale_camera.register()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    samples.build_dolly(scene)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    if quality:
        scene.multiscale.quality = quality
    if method:
        scene.multiscale.method = method
    rigs, settings, first_s = {}, set(), None
    for frame in frames:
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        start = time.perf_counter()
        request = SERVICE.request(depsgraph.scene, depsgraph=depsgraph)
        first_s = time.perf_counter() - start if first_s is None else first_s
        rigs[frame] = request.rig
        settings.add(request.settings)
    assert len(settings) == 1, "a shot's frames share their settings, layout and method"
    method = scene.multiscale.method
    scene.multiscale.method = "SCALAR_FIELD"  # its settings (the shot's layout), for reference
    scalar = SERVICE.request(depsgraph.scene, depsgraph=depsgraph).settings
    scene.multiscale.method = method
    return rigs, settings.pop(), scalar, (method, scene.multiscale.quality, first_s)


def rays_seconds(fld, width, height, rows=64):
    """Seconds to take every pixel's ray from ``fld``, ``rows`` image rows at a time
    (as the render's tiles do)."""
    iy, ix = np.mgrid[0:height, 0:width]
    start = time.perf_counter()
    for top in range(0, height, rows):
        fld.rays(ix[top : top + rows].ravel(), iy[top : top + rows].ravel())
    return time.perf_counter() - start


def build(rig, method, settings, reuse=None):
    """(seconds, field) of one build."""
    start = time.perf_counter()
    fld = prepare(rig, method, settings, Diagnostics(), reuse=reuse)
    return time.perf_counter() - start, fld


def main():
    parser = argparse.ArgumentParser(prog="anim.py")
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--frames", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--quality", default="PREVIEW", help="the dolly's own is HIGH")
    parser.add_argument("--method", default=None, help="the dolly's own is SCALAR_FIELD")
    parser.add_argument(
        "--scalar-reference",
        action="store_true",
        help="also build the second frame cold with SCALAR_FIELD, for comparison",
    )
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args()
    load_before = os.getloadavg()
    rigs, settings, scalar_settings, (method, quality, request_s) = dolly_rigs(
        args.width, args.height, args.frames, args.quality, args.method
    )
    assert settings.steady, "the dolly's rig is animated: its settings ask for a steady layout"
    reuse = FrameReuse()
    rows = []
    for frame in args.frames:
        seconds, fld = build(rigs[frame], method, settings, reuse)
        rays_s = rays_seconds(fld, args.width, args.height)
        row = {"frame": frame, "built": fld.method, "sequence_s": round(seconds, 3)}
        rows.append({**row, **fld.stats["reuse"], "rays_s": round(rays_s, 2)})
        print(f"frame {frame}: {seconds:.3f} s in sequence, {fld.stats['reuse']}", flush=True)
    for row in rows[1:]:
        seconds, _fld = build(rigs[row["frame"]], method, replace(settings), None)
        row["cold_s"] = round(seconds, 3)
        row["ratio"] = round(row["sequence_s"] / seconds, 4)
        print(f"frame {row['frame']}: {seconds:.3f} s cold, ratio {row['ratio']}", flush=True)
    scalar = None
    if args.scalar_reference:
        second = rows[1]["frame"]
        seconds, _fld = build(rigs[second], "SCALAR_FIELD", scalar_settings, None)
        scalar = {"frame": second, "cold_s": round(seconds, 2)}
        print(f"frame {second}: {seconds:.1f} s cold with SCALAR_FIELD", flush=True)
    later = rows[1:]
    mean_seq = sum(r["sequence_s"] for r in later) / len(later)
    mean_cold = sum(r["cold_s"] for r in later) / len(later)
    choice = settings.shot
    result = {
        "command": "make bench-anim: .venv/bin/python bench/anim.py " + " ".join(sys.argv[1:]),
        "scene": "sample_blends/dolly.blend (fixtures.blender.samples.build_dolly)",
        "size": [args.width, args.height],
        "method": method,
        "built": rows[0]["built"],
        "auto": choice.why if choice is not None else None,
        "quality": quality,
        "frames": args.frames,
        "first_request_s": round(request_s, 2),
        "rows": rows,
        "mean_sequence_s": round(mean_seq, 3),
        "mean_cold_s": round(mean_cold, 3),
        "mean_rays_s": round(sum(r["rays_s"] for r in later) / len(later), 2),
        "scalar_field_cold": scalar,
        "ratio": round(mean_seq / mean_cold, 4),
        "target_ratio": round(TARGET_RATIO, 3),
        "met": bool(mean_seq <= TARGET_RATIO * mean_cold),
        "load": {"before": [round(x, 2) for x in load_before], "after": list(os.getloadavg())},
        "cores": os.cpu_count(),
        "commit": _commit(),
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(
        f"mean field seconds per frame after the first: {mean_seq:.3f} s in sequence, "
        f"{mean_cold:.3f} s cold: {result['ratio']:.4f} (target {TARGET_RATIO:.2f}) -> {args.out}"
    )


if __name__ == "__main__":
    main()
