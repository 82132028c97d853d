"""CPU seconds per stage of one default build and its report, as Compute Field takes it.

    nice -n 10 .venv/bin/python bench/stage_cpu.py zoom_rig [--width 1920 --height 1080]

Runs ``bench/methods.run_one`` (AUTO at STANDARD, the properties' defaults) in this
process and prints one JSON line: the wall seconds (which on a shared machine say
little), this process's CPU seconds, each worker process's (read in /proc before they
end), and the CPU seconds of the stages an IMAGE_BLEND build spends them in: the mask
weights' solve, the along-ray measure of the preserved rays, the fold count after it
(this process's share and the workers'). With the cores to itself, Compute Field takes about
this process's CPU seconds plus the busiest worker's.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import methods  # noqa: E402  (bench/methods.py, this script's neighbour)

import multiscale_camera.core.methods.image_blend as image_blend  # noqa: E402
import multiscale_camera.core.quality.report as report  # noqa: E402
from multiscale_camera.core.runtime import runtime  # noqa: E402


def worker_cpu():
    """{pid: CPU seconds} of the runtime's live worker processes."""
    out = {}
    for pid in runtime().pids():
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[pid] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def timed(module, name, stage, cpu):
    """Wrap ``module.name`` so that its CPU seconds (here and in the workers) add up
    into ``cpu[stage]`` and ``cpu[stage + " workers"]``."""
    function = getattr(module, name)

    def wrapper(*args, **kwargs):
        start, workers = time.process_time(), sum(worker_cpu().values())
        try:
            return function(*args, **kwargs)
        finally:
            cpu[stage] = cpu.get(stage, 0.0) + time.process_time() - start
            spent = sum(worker_cpu().values()) - workers
            cpu[stage + " workers"] = cpu.get(stage + " workers", 0.0) + spent

    setattr(module, name, wrapper)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rig", choices=sorted(methods.RIGS))
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    args = parser.parse_args()
    cpu = {}
    timed(image_blend, "mask_weights", "mask weights", cpu)
    timed(report, "preserved_error_on_planes", "along-ray measure", cpu)
    # what is left of the count once the measure is done: this process's share of the
    # bands (``Run.help``) and the workers' CPU meanwhile (the workers' CPU during the
    # measure counts under the measure's "workers")
    timed(report.FoldCount, "result", "fold count", cpu)
    start = time.process_time()
    row = methods.run_one(args.rig, "AUTO", "STANDARD", args.width, args.height)
    main_cpu = time.process_time() - start
    workers = worker_cpu()
    print(
        json.dumps(
            {
                "rig": args.rig,
                "size": [args.width, args.height],
                "built": row.get("built"),
                "compute_field_wall_s": row.get("compute_field_seconds"),
                "load_1min": round(os.getloadavg()[0], 2),
                "cpu_s": round(main_cpu, 2),
                "worker_cpu_s": [round(v, 2) for v in workers.values()],
                "stage_cpu_s": {k: round(v, 2) for k, v in cpu.items()},
                "worst_p95_px": row.get("worst_p95_px"),
                "worst_max_px": row.get("worst_max_px"),
                "folds": row.get("folds"),
            }
        )
    )


if __name__ == "__main__":
    main()
