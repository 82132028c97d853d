"""Build one field of a fixture rig in plain Python and print what docs/architecture.md's
*Field prototypes* table holds: build time (wall and CPU of this process), peak memory,
along-ray p95 and max per camera, folds, Newton failures.

    .venv/bin/python tools/field_prototype.py RIG WIDTH HEIGHT METHOD QUALITY [key=value ...]

RIG names a ``fixtures.rigs.<RIG>_rig`` (zoom1000, turned, three_camera, ...). Keys:
``nested=0|1`` forces one uniform grid or nested grids (SCALAR_FIELD); ``proc=N`` worker
processes (default 1, so that CPU and memory are this process's); ``cells_per_px=X``
cells across the smallest camera's near plane per pixel of the accuracy target (the
build's constant is 8: 16 cells at 0.5 px), the prototype of a grid that follows the
image size; ``step_cells=X`` the RK4 step in cells at 0.5 px on a 1920-wide image (the
build's ``field.STEP_CELLS``, 1.5); ``cells=X`` the RK4 step in cells whatever the
target and the image size (the build's ``step_cells``, 0.5 to 3); ``stride=N`` the
lattice's first spacing in pixels (1: every pixel's ray traced, none interpolated);
``clock=cpu`` the build's stage seconds (``stages``, as the report's) in CPU seconds of
this process instead of wall seconds: with ``proc=1`` the whole build, so a shared
machine's load does not blur them; ``plane=0`` the trace's step left whole at the near
planes (no ``field.NearPlaneStep``: every gain 1), the build before it shortened there;
``transition_tol=X`` the lattice's target times X on cells of transition pixels alone
(preserved regions and their edges as the build); ``count=1`` counts the trace's
field evaluations (points, with ``proc=1``: a worker's are not seen), its tangent
evaluations and the points Newton solved (``Family.solve``: a SCALAR_FIELD trace's
tangents off each camera's straight stretch; VECTOR_FIELD's grid tangents too).
"""

import dataclasses
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fixtures.rigs as rigs  # noqa: E402
import multiscale_camera.core.field.fill as fill  # noqa: E402
import multiscale_camera.core.field.tracer as tracer  # noqa: E402
import multiscale_camera.core.geometry.family as family  # noqa: E402
import multiscale_camera.core.methods.scalar_field as scalar_field  # noqa: E402
import multiscale_camera.core.methods.traced as traced  # noqa: E402
from multiscale_camera.core.geometry import Rig  # noqa: E402
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from multiscale_camera.core.quality import build_report  # noqa: E402


def main(argv):
    rig, width, height, method, quality = argv[:5]
    opts = dict(a.split("=", 1) for a in argv[5:])
    cams, masks = getattr(rigs, f"{rig}_rig")(int(width), int(height))
    settings = settings_for(quality)
    if "nested" in opts:
        settings = dataclasses.replace(settings, nested=bool(int(opts["nested"])))
    settings = dataclasses.replace(settings, processes=int(opts.get("proc", 1)))
    if "cells_per_px" in opts:
        per_px = float(opts["cells_per_px"])
        fill.CELLS_ACROSS_NEAR_PER_PX = scalar_field.CELLS_ACROSS_NEAR_PER_PX = per_px
        fill.MIN_CELLS_ACROSS_NEAR = scalar_field.MIN_CELLS_ACROSS_NEAR = 4
    if "step_cells" in opts:
        tracer.STEP_CELLS = float(opts["step_cells"])
    if "cells" in opts:
        fixed = float(opts["cells"])
        traced.step_cells = lambda *_args: fixed
    if "stride" in opts:
        spacing = int(opts["stride"])
        traced.lattice_stride = lambda *_args: spacing
    if opts.get("plane") == "0":
        traced.plane_gains = lambda tracer_, rig_, *rest: [1.0] * (len(rig_.cameras) - 1)
    if "transition_tol" in opts:
        factor, own = float(opts["transition_tol"]), traced._AdaptiveLattice._fine
        # only transition cells are judged by the estimate (``_AdaptiveLattice._fine``)
        traced._AdaptiveLattice._fine = lambda self, cells, err: own(self, cells, err / factor)
    counts = {"field points": 0, "tangents": 0, "newton": 0}
    if opts.get("count") == "1":
        velocity, tangent = tracer.FieldTracer.velocity, tracer.FieldTracer._tangent
        solve = family.Family.solve

        def counted_velocity(self, x, rows):
            counts["field points"] += len(x)
            return velocity(self, x, rows)

        def counted_tangent(self, i, x, params, rows):
            counts["tangents"] += len(x)
            return tangent(self, i, x, params, rows)

        def counted_solve(self, points, *args, **kwargs):
            counts["newton"] += len(points)
            return solve(self, points, *args, **kwargs)

        tracer.FieldTracer.velocity = counted_velocity
        tracer.FieldTracer._tangent = counted_tangent
        family.Family.solve = counted_solve
    if opts.get("clock") == "cpu":
        time.perf_counter = time.process_time
    wall, cpu = time.perf_counter(), time.process_time()
    fld = prepare(Rig(cams, masks), method, settings)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    rep = build_report(fld, quality)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    def fig(v):
        return "null" if v is None else f"{v:.2f}"

    cams_out = ", ".join(
        f"{c['name']} {fig(c['preserved_px']['p95'])}/{fig(c['preserved_px']['max'])}"
        for c in rep["cameras"]
    )
    stages = ", ".join(f"{k} {v:.2f}" for k, v in fld.seconds.items())
    traced_rays = getattr(fld, "traced", None)
    vertices = traced_rays.vertices.shape[1] if traced_rays is not None else 0
    transition = ""
    if getattr(fld, "index", None) is not None:
        kept = traced.preserved_labels(fld.rig) > 0
        rk4 = (fld.index >= 0) & ~kept
        transition = f"transition pixels traced {int(rk4.sum())} of {int((~kept).sum())}, "
    print(
        f"{rig} {width}x{height} {method}->{fld.method} {quality} {opts}: build {wall:.1f} s wall, "
        f"{cpu:.1f} s CPU, peak {peak:.0f} MB; stages {stages}; "
        f"p95/max px {cams_out}; folds {rep['folds']}; "
        f"levels {rep['levels']}, grid {rep['grids'][:1]}, traced {fld.stats.get('traced')}, "
        f"vertices {vertices}, {transition}"
        f"plane gains {fld.stats.get('plane_gains')}; "
        f"newton_lost {rep['newton_lost']}, stalled {rep['stalled']}"
    )
    if opts.get("count") == "1":
        print("trace evaluations:", counts)
    if "auto" in rep:
        print("auto:", rep["auto"])


if __name__ == "__main__":
    main(sys.argv[1:])
