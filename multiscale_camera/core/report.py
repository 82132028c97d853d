"""The build report (DESIGN.md, report schema version 1), measured on the rays a field
actually hands to the renderer."""

import json

import numpy as np

from .metrics import bending_active, measured_pixels, preserved_error, quad_folds

VERSION = 1


def measure(fld):
    """Preserved errors per camera, folds and stalled rays of a prepared RayField.

    Returns
    -------
    cameras : list of dict (schema "cameras" entries). folds : int.
    fold_quads : (Hy - 1, Wx - 1) bool, where the folds are, on the lattice of ``stride``.
    """
    rig = fld.rig
    cameras = []
    for i, cam in enumerate(rig.cameras):
        ix, iy = measured_pixels(rig.masks[i])
        bundle = fld.rays(ix, iy)
        exit_index = fld.exit_index(ix, iy) if i == 0 and hasattr(fld, "exit_index") else None
        pres = preserved_error(rig.cameras, i, bundle, exit_index)
        err, angle = pres.summary()
        cameras.append({"name": cam.name, "pixels": pres.pixels, "preserved_px": err, "angle_deg": angle})
    verts, counts, _stride = fld.lattice()
    active = bending_active(verts, rig.cameras[-1], counts)
    quads = quad_folds(verts, active)
    return cameras, int(quads.sum()), quads


def build_report(fld, quality, total_seconds=None):
    """The report of a prepared field as a dict of schema version 1.

    Parameters
    ----------
    fld : RayField. quality : str, the quality enum name.
    total_seconds : float, wall time of the build (default: the sum of the stages).
    """
    cameras, folds, _quads = measure(fld)
    seconds = {k: float(fld.seconds.get(k, 0.0)) for k in ("fill", "solve", "tangents", "trace")}
    seconds["total"] = float(total_seconds if total_seconds is not None else sum(seconds.values()))
    return {
        "version": VERSION,
        "method": fld.method,
        "quality": quality,
        "grids": [list(map(int, g)) for g in fld.grids],
        "seconds": seconds,
        "solver": {
            "iterations": int(fld.solver.get("iterations", 0)),
            "residual": float(fld.solver.get("residual", 0.0)),
            "converged": bool(fld.solver.get("converged", True)),
        },
        "cameras": cameras,
        "folds": folds,
        "stalled": int(fld.stats.get("stalled", 0)),
        "conflicts": int(fld.stats.get("conflicts", 0)),
        "warnings": list(fld.warnings),
    }


def headline(report):
    """One line for the panel: worst p95 error, folds, time."""
    worst = max((c["preserved_px"]["p95"] for c in report["cameras"]), default=0.0)
    return (
        f"{report['method']}: p95 error {worst:.2f} px, {report['folds']} folds, "
        f"{report['seconds']['total']:.1f} s"
    )


def to_json(report):
    """The report as the JSON string stored in ``scene.multiscale.report``."""
    return json.dumps(report, indent=1, default=lambda o: o.item() if isinstance(o, np.generic) else str(o))
