"""Benchmark: field seconds per frame of the dolly sample, built in sequence against cold.

    .venv/bin/python bench/anim.py [--width 960 --height 540] [--frames 1 2 3]
        [--quality PREVIEW]

Builds sample_blends/dolly.blend's scene (``fixtures.blender.samples.build_dolly``) with
the bpy module, reads its rig and settings (with the shot's layout) at each frame as a
render does (the field service's request on the evaluated depsgraph), then builds the
fields of ``--frames`` in order, each taking what the one before left valid
(``core.methods.FrameReuse``, as the field service does for an animated rig), and then
each of those frames again cold (nothing kept). Writes, per frame, both times and what
the sequential build took and rebuilt, the mean seconds of the frames after the first,
the ratio to cold (the target: 1/3 or less), the machine's load and the commit, to
bench/anim.json.
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

import multiscale_camera  # noqa: E402
from bench.methods import _commit  # noqa: E402
from fixtures.blender import samples  # noqa: E402
from multiscale_camera.core.diagnostics import Diagnostics  # noqa: E402
from multiscale_camera.core.methods import FrameReuse, prepare  # noqa: E402
from multiscale_camera.render.fields import SERVICE  # noqa: E402

OUT = ROOT / "bench" / "anim.json"
# The frames after the first must build in at most this share of a cold build.
TARGET_RATIO = 1 / 3


def dolly_rigs(width, height, frames, quality):
    """{frame: Rig} of the dolly at ``width`` x ``height``, its Settings (the shot's,
    the same at every frame), method and quality."""
    multiscale_camera.register()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    samples.build_dolly(scene)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    if quality:
        scene.multiscale.quality = quality
    rigs, settings = {}, set()
    for frame in frames:
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        request = SERVICE.request(depsgraph.scene, depsgraph=depsgraph)
        rigs[frame] = request.rig
        settings.add(request.settings)
    assert len(settings) == 1, "a shot's frames share their settings and layout"
    return rigs, settings.pop(), scene.multiscale.method, scene.multiscale.quality


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
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args()
    rigs, settings, method, quality = dolly_rigs(args.width, args.height, args.frames, args.quality)
    assert settings.steady, "the dolly's rig is animated: its settings ask for a steady layout"
    load_before = os.getloadavg()
    reuse = FrameReuse()
    rows = []
    for frame in args.frames:
        seconds, fld = build(rigs[frame], method, settings, reuse)
        rows.append({"frame": frame, "sequence_s": round(seconds, 2), **fld.stats["reuse"]})
        print(f"frame {frame}: {seconds:.1f} s in sequence, {fld.stats['reuse']}", flush=True)
    for row in rows[1:]:
        seconds, _fld = build(rigs[row["frame"]], method, replace(settings), None)
        row["cold_s"] = round(seconds, 2)
        row["ratio"] = round(row["sequence_s"] / seconds, 3)
        print(f"frame {row['frame']}: {seconds:.1f} s cold, ratio {row['ratio']}", flush=True)
    later = rows[1:]
    mean_seq = sum(r["sequence_s"] for r in later) / len(later)
    mean_cold = sum(r["cold_s"] for r in later) / len(later)
    result = {
        "command": "make bench-anim: .venv/bin/python bench/anim.py " + " ".join(sys.argv[1:]),
        "scene": "sample_blends/dolly.blend (fixtures.blender.samples.build_dolly)",
        "size": [args.width, args.height],
        "method": method,
        "quality": quality,
        "frames": args.frames,
        "rows": rows,
        "mean_sequence_s": round(mean_seq, 2),
        "mean_cold_s": round(mean_cold, 2),
        "ratio": round(mean_seq / mean_cold, 3),
        "target_ratio": round(TARGET_RATIO, 3),
        "met": bool(mean_seq <= TARGET_RATIO * mean_cold),
        "load": {"before": [round(x, 2) for x in load_before], "after": list(os.getloadavg())},
        "cores": os.cpu_count(),
        "commit": _commit(),
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(
        f"mean field seconds per frame after the first: {mean_seq:.1f} s in sequence, "
        f"{mean_cold:.1f} s cold: {result['ratio']:.2f} (target {TARGET_RATIO:.2f}) -> {args.out}"
    )


if __name__ == "__main__":
    main()
