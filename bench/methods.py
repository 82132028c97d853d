"""Benchmark: every ray-generation method at every quality on a set of rigs.

    .venv/bin/python bench/methods.py [--width 960 --height 540] [--rigs ...]

Each configuration runs in a fresh process (so its peak memory is its own) and builds
the field and its report: seconds per stage, preserved-ray error per camera (p50, p95,
max, in that camera's pixels), folds, stalled rays, peak memory. SCALAR_FIELD runs on
one uniform grid (the paper's) and on nested grids. Prints a table and writes
bench/results.json, the speed-accuracy chart docs/figures/speed_accuracy.png and the
failure table in docs/methods.md (between its GENERATED markers).
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "bench" / "results.json"
CHART = ROOT / "docs" / "figures" / "speed_accuracy.png"
TABLE = ROOT / "docs" / "methods.md"
RIGS = {
    "zoom_rig": "2 cameras, 4x, turned 20 degrees",
    "three_camera_rig": "3 cameras, 6x overall",
    "zoom25_rig": "3 cameras, 25x",
    "zoom1000_rig": "3 cameras, 1000x",
    "turn100_rig": "2 cameras turned 100 degrees",
    "contradictory_rig": "2 cameras, overlapping masks",
}
# SCALAR_FIELD_NESTED is SCALAR_FIELD with Settings.nested forced on, SCALAR_FIELD
# here with it forced off (one uniform grid); the add-on chooses between them.
FIELD_METHODS = ("VECTOR_FIELD", "SCALAR_FIELD", "SCALAR_FIELD_NESTED")
IMAGE_METHODS = ("IMAGE_BLEND", "LINEAR")
# AUTO, the default: what it builds (IMAGE_BLEND unless its rays fold) and its figures.
DEFAULT_METHODS = ("AUTO",)
QUALITIES = ("PREVIEW", "STANDARD", "HIGH")
# A configuration that runs longer than this is recorded as timed out.
TIMEOUT_S = 900


def _commit():
    """The measured tree's commit (with "+" if it has changes), or None outside git."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT,
            capture_output=True,
            text=True,
        ).stdout.strip()
    except OSError:
        return None
    return (head + ("+" if dirty else "")) or None


def _workers_peak_mb():
    """The largest peak resident size of a worker process, MB: the runtime's workers stay
    alive (Linux's /proc tells their peaks), ended ones are counted by rusage."""
    from multiscale_camera.core.runtime import runtime

    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # kB
    for pid in runtime().pids():
        try:
            with open(f"/proc/{pid}/status") as status:
                for line in status:
                    if line.startswith("VmHWM:"):
                        peak = max(peak, int(line.split()[1]))
        except OSError:
            pass
    return round(peak / 1024, 1)


def run_one(rig_name, method, quality, width, height):
    """Build one field in this process; return its row (a dict)."""
    from fixtures import rigs
    from multiscale_camera.core.errors import RigError
    from multiscale_camera.core.geometry import Rig
    from multiscale_camera.core.methods import prepare, settings_for
    from multiscale_camera.core.quality import build_report
    from multiscale_camera.core.runtime import cores

    cams, masks = getattr(rigs, rig_name)(width, height)
    settings = settings_for(quality)
    if method.startswith("SCALAR_FIELD"):
        settings = replace(settings, nested=method.endswith("NESTED"))
    start = time.perf_counter()
    try:
        fld = prepare(Rig(cams, masks), method.replace("_NESTED", ""), settings)
    except RigError as err:
        return {"rig": rig_name, "method": method, "quality": quality, "refused": str(err)}
    build = time.perf_counter() - start
    report = build_report(fld, quality, build)
    return {
        "rig": rig_name,
        "method": method,
        "quality": quality,
        "built": fld.method,
        "size": [width, height],
        "build_seconds": round(build, 3),
        "report_seconds": round(time.perf_counter() - start - build, 3),
        "seconds": {k: round(v, 3) for k, v in report["seconds"].items()},
        "grids": report["grids"],
        "traced_rays": int(fld.stats.get("traced", 0)),
        "processes": settings.processes or cores(),
        "commit": _commit(),
        "load_1min": round(os.getloadavg()[0], 2),
        "cameras": report["cameras"],
        "worst_p95_px": max(
            c["preserved_px"]["p95"]
            for c in report["cameras"]
            if c["preserved_px"]["p95"] is not None
        ),
        "folds": report["folds"],
        "stalled": report["stalled"],
        "newton_lost": report.get("newton_lost", 0),
        "unfinished": report.get("unfinished", 0),
        "report_version": report["version"],
        "conflicts": report["conflicts"],
        "warnings": report["warnings"],
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        # the largest worker process that shared the trace (its own interpreter and
        # numpy, and the shared memory of the tracer's grids it mapped)
        "peak_mb_worker": _workers_peak_mb(),
    }


def configurations(rigs):
    """(rig, method, quality) triples: image methods at STANDARD, field methods at all."""
    for rig in rigs:
        for method in DEFAULT_METHODS + IMAGE_METHODS:
            yield rig, method, "STANDARD"
        for method in FIELD_METHODS:
            for quality in QUALITIES:
                yield rig, method, quality


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=540)
    parser.add_argument("--rigs", nargs="+", default=list(RIGS))
    parser.add_argument(
        "--redraw", action="store_true", help="only redraw the chart and table from results.json"
    )
    parser.add_argument("--methods", nargs="+", help="only these methods")
    parser.add_argument("--qualities", nargs="+", help="only these qualities")
    parser.add_argument(
        "--update",
        action="store_true",
        help="replace the rows run in results.json, keep the others (same size only)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=OUT,
        help="where the rows go (another file than bench/results.json leaves the chart and "
        "the failure table of docs/ alone)",
    )
    parser.add_argument(
        "--one", nargs=3, metavar=("RIG", "METHOD", "QUALITY"), help=argparse.SUPPRESS
    )
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one, args.width, args.height)))
        return
    out = args.out.resolve()
    if args.redraw:
        results = json.loads(out.read_text())
        chart(results)
        table(results)
        return
    rows = []
    header = (
        f"{'rig':17} {'method':13} {'quality':9} {'fill':>6} {'solve':>6} {'tang':>6} "
        f"{'trace':>6} {'build s':>8} {'p95 px':>8} {'max px':>8} {'folds':>6} {'stall':>5} "
        f"{'newton':>6} {'MB':>6}"
    )
    print(header)
    for rig, method, quality in configurations(args.rigs):
        if (args.methods and method not in args.methods) or (
            args.qualities and quality not in args.qualities
        ):
            continue
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
        try:
            proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            print(f"{rig:17} {method:13} {quality:9} timed out after {TIMEOUT_S} s")
            rows.append({"rig": rig, "method": method, "quality": quality, "timed_out": TIMEOUT_S})
            continue
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
        if "refused" in row:
            print(f"{rig:17} {method:13} {quality:9} refused: {row['refused'][:60]}")
            continue
        worst_max = max(
            c["preserved_px"]["max"] for c in row["cameras"] if c["preserved_px"]["max"] is not None
        )
        st = row["seconds"]
        print(
            f"{rig:17} {method:13} {quality:9} {st['fill']:6.2f} {st['solve']:6.2f} "
            f"{st['tangents']:6.2f} {st['trace']:6.2f} {row['build_seconds']:8.2f} "
            f"{row['worst_p95_px']:8.3f} {worst_max:8.3f} {row['folds']:6d} {row['stalled']:5d} "
            f"{row['newton_lost']:6d} {row['peak_mb']:6.0f}"
        )
    if args.update and out.exists():
        old = json.loads(out.read_text())
        if old["size"] != [args.width, args.height]:
            sys.exit(f"--update: {out.name} holds {old['size']}, not {args.width}x{args.height}")
        ran = {(r["rig"], r["method"], r["quality"]) for r in rows}
        kept = [r for r in old["rows"] if (r["rig"], r["method"], r["quality"]) not in ran]
        rows = sorted(kept + rows, key=_order)
    results = {"size": [args.width, args.height], "rows": rows}
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")
    if out == OUT.resolve():
        chart(results)
        table(results)


def _order(row):
    """Sort key: the order ``configurations`` runs rows in."""
    rigs, methods = list(RIGS), list(DEFAULT_METHODS + IMAGE_METHODS + FIELD_METHODS)
    return (
        rigs.index(row["rig"]) if row["rig"] in rigs else len(rigs),
        methods.index(row["method"]) if row["method"] in methods else len(methods),
        QUALITIES.index(row["quality"]) if row["quality"] in QUALITIES else len(QUALITIES),
    )


MARKERS = {
    "AUTO": "*",
    "LINEAR": "v",
    "IMAGE_BLEND": "s",
    "VECTOR_FIELD": "^",
    "SCALAR_FIELD": "o",
    "SCALAR_FIELD_NESTED": "D",
}
COLOURS = {"PREVIEW": "tab:orange", "STANDARD": "tab:blue", "HIGH": "tab:green"}


def chart(results):
    """docs/figures/speed_accuracy.png: build time (log) against the worst camera's p95
    preserved error (log), one panel per rig, one marker per method and quality, the
    number of folded quads written beside markers that fold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in results["rows"] if "build_seconds" in r]
    rigs = [name for name in RIGS if any(r["rig"] == name for r in rows)]
    fig, axes = plt.subplots(1, len(rigs), figsize=(4.2 * len(rigs), 4.2), squeeze=False)
    for ax, rig in zip(axes[0], rigs):
        for r in (r for r in rows if r["rig"] == rig):
            x, y = r["build_seconds"], max(r["worst_p95_px"], 1e-3)
            ax.scatter(
                x, y, marker=MARKERS[r["method"]], color=COLOURS[r["quality"]], s=46, zorder=3
            )
            if r["folds"]:
                ax.annotate(
                    f"{r['folds']}",
                    (x, y),
                    textcoords="offset points",
                    xytext=(4, 4),
                    fontsize=7,
                    color="tab:red",
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.axhline(1.0, color="grey", lw=0.8, ls="--")
        ax.set_title(RIGS[rig], fontsize=10)
        ax.set_xlabel("build time, s")
        ax.grid(True, which="both", lw=0.3)
    axes[0][0].set_ylabel("worst camera's p95 preserved error, px (floor 0.001)")
    handles = [
        plt.Line2D([], [], marker=m, ls="", color="black", label=name)
        for name, m in MARKERS.items()
    ] + [plt.Line2D([], [], marker="o", ls="", color=c, label=q) for q, c in COLOURS.items()]
    fig.legend(handles=handles, loc="lower center", ncol=8, fontsize=8, frameon=False)
    w, h = results["size"]
    fig.suptitle(f"Speed against accuracy at {w}x{h} (red: folded quads)", fontsize=11)
    fig.tight_layout(rect=(0, 0.07, 1, 0.95))
    CHART.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(CHART, dpi=110)
    print(f"wrote {CHART.relative_to(ROOT)}")


def _verdict(r):
    """How one configuration fared, in a few words."""
    if "refused" in r:
        return "refused: " + r["refused"].split(":")[0].split(";")[0]
    if "timed_out" in r:
        return f"timed out (> {r['timed_out']} s)"
    if "error" in r:
        return "crashed"
    bad = []
    if r["worst_p95_px"] > 1.0:
        bad.append(f"p95 {r['worst_p95_px']:.3g} px")
    if r["folds"]:
        bad.append(f"{r['folds']} folds")
    if r["stalled"]:
        bad.append(f"{r['stalled']} stalled")
    if r.get("conflicts"):
        bad.append(f"{r['conflicts']} conflicting voxels")
    head = f"{r['build_seconds']:.3g} s"
    return head + (
        ": " + ", ".join(bad) if bad else ": holds (p95 " + f"{r['worst_p95_px']:.2g} px)"
    )


def table(results):
    """The failure table in docs/methods.md, between its GENERATED markers."""
    rows = results["rows"]
    rigs = [name for name in RIGS if any(r["rig"] == name for r in rows)]
    w, h = results["size"]
    lines = [
        f"Measured by `make bench` at {w}x{h} (`bench/results.json`). Each cell: build time",
        "and what went wrong (p95 over 1 px, folded quads, stalled rays, voxels two masks",
        "both claim), or that it holds.",
        "",
        "| method | quality | " + " | ".join(RIGS[r] for r in rigs) + " |",
        "|---|---|" + "---|" * len(rigs),
    ]
    for method in DEFAULT_METHODS + IMAGE_METHODS + FIELD_METHODS:
        for quality in QUALITIES:
            cells = [
                next(
                    (
                        r
                        for r in rows
                        if (r["rig"], r["method"], r["quality"]) == (g, method, quality)
                    ),
                    None,
                )
                for g in rigs
            ]
            if not any(cells):
                continue
            text = [_verdict(c) if c else "" for c in cells]
            lines.append(f"| `{method}` | {quality} | " + " | ".join(text) + " |")
    body = "\n".join(lines)
    start, end = "<!-- GENERATED: failure table -->", "<!-- END GENERATED -->"
    doc = TABLE.read_text()
    a, b = doc.index(start) + len(start), doc.index(end)
    TABLE.write_text(doc[:a] + "\n" + body + "\n" + doc[b:])
    print(f"wrote the table in {TABLE.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
