"""Wall seconds and folded quads of the report's fold count on IMAGE_BLEND's rays.

    nice -n 10 .venv/bin/python bench/fold_count.py demo_rig three_camera_rig \
        [--width 1920 --height 1080] [--raw-weights] [--save DIR]

For each rig (a function of fixtures/rigs.py) builds IMAGE_BLEND at STANDARD, then
times ``fold_map(fld, processes=0)`` (one worker per core) and prints one JSON line:
the rig, the size, the wall seconds, the CPU seconds (this process's and its workers',
read in /proc: on a shared machine the wall says little), the folded quads and the
map's shape. ``--save``
writes each map to DIR/<rig>_<w>x<h>.npy, to compare maps between two commits.
``--raw-weights`` renders with the mask weights un-eased (``mask_weights(masks).x``,
what IMAGE_BLEND used before easing them), whose rays fold along the masks' edges.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fixtures import rigs  # noqa: E402
from multiscale_camera.core.field import mask_weights  # noqa: E402
from multiscale_camera.core.geometry import Rig  # noqa: E402
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from multiscale_camera.core.quality import fold_map  # noqa: E402
from multiscale_camera.core.runtime import runtime  # noqa: E402


def cpu_seconds():
    """CPU seconds of this process and of the runtime's live worker processes."""
    total = time.process_time()
    for pid in runtime().pids():
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rigs", nargs="+")
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--raw-weights", action="store_true")
    parser.add_argument("--save", type=Path)
    args = parser.parse_args()
    for name in args.rigs:
        cams, masks = getattr(rigs, name)(args.width, args.height)
        fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
        if args.raw_weights:
            fld.weights = mask_weights(masks).x.astype(np.float32)
        start, cpu = time.perf_counter(), cpu_seconds()
        folds = fold_map(fld, processes=0)
        wall, cpu = time.perf_counter() - start, cpu_seconds() - cpu
        folds = folds[0] if isinstance(folds, tuple) else folds
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            raw = "_raw" if args.raw_weights else ""
            np.save(args.save / f"{name}{raw}_{args.width}x{args.height}.npy", folds)
        row = {"rig": name, "size": [args.width, args.height], "raw_weights": args.raw_weights}
        row.update(fold_map_wall_s=round(wall, 2), fold_map_cpu_s=round(cpu, 2))
        row.update(folds=int(folds.sum()), shape=list(folds.shape))
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
