"""Benchmark: multigrid-preconditioned CG against the paper's explicit diffusion.

    .venv/bin/python bench/solvers.py [--sizes 64 128 256] [--diffusion-sizes 64 128]
                                      [--cap 60]

The problem imitates a membership field: three cone segments along z with constraint
values 1, 2, 3 (about 18% of the voxels). For each size it times ``solve_membership``
and, where asked, how long ``explicit_diffusion`` needs to come as close to the
converged answer (a float64 solve to 1e-10) as the solver's default answer does, by
max abs error. Diffusion runs are capped; a capped run gives a lower bound on the
ratio. Prints a table and writes bench/solvers.json.
"""

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from multiscale_camera.core.field import (  # noqa: E402
    explicit_diffusion,
    solve_membership,
)

OUT = Path(__file__).with_suffix(".json")
# Diffusion steps between error checks; the checks are not timed.
CHUNK = 200


def cones(n):
    """(n, n, n) float64 values and bool constraints: three cone segments along z,
    valued 1 (outer shell near z = 0), 2 (a band in the middle), 3 (the tip)."""
    c = (np.arange(n) + 0.5) / n
    x, y, z = np.meshgrid(c, c, c, indexing="ij", sparse=True)
    r = np.hypot(x - 0.5, y - 0.5)
    radius = 0.55 - 0.4 * z
    values = np.zeros((n, n, n))
    constrained = np.zeros((n, n, n), bool)
    for value, (z0, z1), (r0, r1) in (
        (1, (0.0, 0.3), (0.55, 1.0)),
        (2, (0.4, 0.6), (0.25, 0.6)),
        (3, (0.75, 1.0), (0.0, 0.35)),
    ):
        m = (z >= z0) & (z < z1) & (r >= r0 * radius) & (r < r1 * radius)
        constrained |= m
        values[m] = value
    return values, constrained


def diffusion_time(values, constrained, reference, target, cap, dtype):
    """Seconds and steps explicit diffusion needs to reach max abs error <= target."""
    x, steps, seconds, error = None, 0, 0.0, np.inf
    while seconds < cap:
        start = time.perf_counter()
        x = explicit_diffusion(values, constrained, CHUNK, x0=x, dtype=dtype).x
        seconds += time.perf_counter() - start
        steps += CHUNK
        error = float(np.abs(x - reference).max())
        if error <= target:
            return seconds, steps, error, False
    return seconds, steps, error, True


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--diffusion-sizes", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--cap", type=float, default=60.0, help="seconds per diffusion run")
    parser.add_argument(
        "--diffusion-dtype",
        default="float64",
        help="float32 stalls before the solver's accuracy on large grids",
    )
    args = parser.parse_args()
    dtype = np.dtype(args.diffusion_dtype)

    rows = []
    for n in args.sizes:
        values, constrained = cones(n)
        start = time.perf_counter()
        result = solve_membership(values, constrained)
        seconds = time.perf_counter() - start
        row = {
            "n": n,
            "constrained": round(float(constrained.mean()), 3),
            "pcg_iterations": result.iterations,
            "pcg_seconds": round(seconds, 3),
            "pcg_residual": result.residuals[-1],
            "converged": result.converged,
        }
        if n in args.diffusion_sizes:
            reference = solve_membership(values, constrained, tol=1e-10, dtype=np.float64).x
            target = float(np.abs(result.x - reference).max())
            d_seconds, steps, error, capped = diffusion_time(
                values, constrained, reference, target, args.cap, dtype
            )
            row.update(
                {
                    "max_error": target,
                    "diffusion_seconds": round(d_seconds, 2),
                    "diffusion_steps": steps,
                    "diffusion_error": error,
                    "diffusion_capped": capped,
                    "ratio": round(d_seconds / seconds, 1),
                    "ratio_is_lower_bound": capped,
                }
            )
        rows.append(row)
        print_row(row)

    OUT.write_text(
        json.dumps(
            {
                "problem": "three cone segments valued 1, 2, 3 along z",
                "tolerance": "relative residual 1e-6 (solve_membership default)",
                "diffusion_dtype": dtype.name,
                "diffusion_cap_seconds": args.cap,
                "machine": {
                    "python": platform.python_version(),
                    "numpy": np.__version__,
                    "processor": platform.processor() or platform.machine(),
                },
                "rows": rows,
            },
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {OUT}")


def print_row(row):
    if not hasattr(print_row, "header"):
        print_row.header = True
        print(
            f"{'n':>5} {'constr':>6} {'iters':>5} {'pcg s':>7} {'max err':>9} "
            f"{'diff s':>8} {'steps':>7} {'diff err':>9} {'ratio':>9}"
        )
    line = (
        f"{row['n']:>5} {row['constrained']:>6.3f} {row['pcg_iterations']:>5} "
        f"{row['pcg_seconds']:>7.2f}"
    )
    if "ratio" in row:
        bound = ">" if row["ratio_is_lower_bound"] else ""
        line += (
            f" {row['max_error']:>9.1e} {row['diffusion_seconds']:>8.1f} "
            f"{row['diffusion_steps']:>7} {row['diffusion_error']:>9.1e} "
            f"{bound + format(row['ratio'], '.0f'):>9}"
        )
    print(line, flush=True)


if __name__ == "__main__":
    main()
