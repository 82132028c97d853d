"""Benchmark: every ray-generation method at every quality on a set of rigs.

    .venv/bin/python bench/methods.py [--width 1920 --height 1080] [--rigs ...]

Each configuration runs in a fresh process (so its peak memory is its own) and builds
the field and its report: seconds per stage, preserved-ray error per camera (p50, p95,
max, in that camera's pixels), folds, stalled rays, peak memory. Prints a table and
writes bench/methods.json.
"""

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = Path(__file__).with_suffix(".json")
RIGS = ("zoom_rig", "three_camera_rig")
FIELD_METHODS = ("VECTOR_FIELD", "SCALAR_FIELD")
IMAGE_METHODS = ("IMAGE_BLEND", "LINEAR")
QUALITIES = ("PREVIEW", "STANDARD", "HIGH")


def run_one(rig_name, method, quality, width, height):
    """Build one field in this process; return its row (a dict)."""
    from multiscale_camera.core.methods import prepare, settings_for
    from multiscale_camera.core.report import build_report
    from multiscale_camera.core.rig import Rig
    from tests.unit import rigs

    cams, masks = getattr(rigs, rig_name)(width, height)
    start = time.perf_counter()
    fld = prepare(Rig(cams, masks), method, settings_for(quality))
    build = time.perf_counter() - start
    report = build_report(fld, quality, build)
    return {
        "rig": rig_name,
        "method": method,
        "quality": quality,
        "size": [width, height],
        "build_seconds": round(build, 3),
        "report_seconds": round(time.perf_counter() - start - build, 3),
        "seconds": {k: round(v, 3) for k, v in report["seconds"].items()},
        "grids": report["grids"],
        "traced_rays": int(fld.stats.get("traced", 0)),
        "cameras": report["cameras"],
        "worst_p95_px": max(c["preserved_px"]["p95"] for c in report["cameras"]),
        "folds": report["folds"],
        "stalled": report["stalled"],
        "conflicts": report["conflicts"],
        "warnings": report["warnings"],
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def configurations(rigs):
    for rig in rigs:
        for method in IMAGE_METHODS:
            yield rig, method, "STANDARD"
        for method in FIELD_METHODS:
            for quality in QUALITIES:
                yield rig, method, quality


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--rigs", nargs="+", default=list(RIGS))
    parser.add_argument(
        "--one", nargs=3, metavar=("RIG", "METHOD", "QUALITY"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one, args.width, args.height)))
        return
    rows = []
    header = (
        f"{'rig':17} {'method':13} {'quality':9} {'fill':>6} {'solve':>6} {'tang':>6} "
        f"{'trace':>6} {'build s':>8} {'p95 px':>8} {'max px':>8} {'folds':>6} {'stall':>5} "
        f"{'MB':>6}"
    )
    print(header)
    for rig, method, quality in configurations(args.rigs):
        cmd = [
            sys.executable,
            __file__,
            "--width",
            str(args.width),
            "--height",
            str(args.height),
            "--one",
            rig,
            method,
            quality,
        ]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        if proc.returncode:
            print(
                f"{rig:17} {method:13} {quality:9} failed: {proc.stderr.strip().splitlines()[-1]}"
            )
            rows.append(
                {"rig": rig, "method": method, "quality": quality, "error": proc.stderr[-2000:]}
            )
            continue
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        worst_max = max(c["preserved_px"]["max"] for c in row["cameras"])
        st = row["seconds"]
        print(
            f"{rig:17} {method:13} {quality:9} {st['fill']:6.2f} {st['solve']:6.2f} "
            f"{st['tangents']:6.2f} {st['trace']:6.2f} {row['build_seconds']:8.2f} "
            f"{row['worst_p95_px']:8.3f} {worst_max:8.3f} {row['folds']:6d} {row['stalled']:5d} "
            f"{row['peak_mb']:6.0f}"
        )
    OUT.write_text(json.dumps({"size": [args.width, args.height], "rows": rows}, indent=1))
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
