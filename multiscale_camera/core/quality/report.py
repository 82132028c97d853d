"""The build report (docs/report.md, schema version 2), measured on the rays a field
actually hands to the renderer."""

import json

import numpy as np

from .folds import quad_folds
from .metrics import ERODE_PX, bending_active, measured_pixels, preserved_error

# 2: preserved_px and angle_deg are the worst along the whole preserved ray (from the
# camera's near plane to its clip end), no longer where it meets the near plane; folds
# are counted in sections across the bundle; newton_lost and unfinished are counted.
VERSION = 2


# Ray vertices per chunk when counting folds: bounds memory (quad_folds holds about a
# dozen float64 (rays, K, 3) arrays: about half a GB at this size, whatever K is).
FOLD_CHUNK_VERTICES = 1 << 20
# Images up to this many pixels are checked quad by quad; larger ones on every other
# pixel in each direction (a fold narrower than two pixels is then missed).
FULL_FOLD_PIXELS = 1 << 20


def fold_map(fld):
    """Folds among the rendered rays, quad by quad.

    Returns
    -------
    folds : (Hy - 1, Wx - 1) bool on the pixel lattice of ``stride``. stride : int.
    """
    w, h = fld.rig.size
    stride = 1 if w * h <= FULL_FOLD_PIXELS else 2
    xs = np.unique(np.append(np.arange(0, w, stride), w - 1))
    ys = np.unique(np.append(np.arange(0, h, stride), h - 1))
    traced = getattr(fld, "traced", None)
    k = traced.vertices.shape[1] if traced is not None else 64
    rows = max(2, FOLD_CHUNK_VERTICES // (len(xs) * k))
    out = np.zeros((max(len(ys) - 1, 0), max(len(xs) - 1, 0)), dtype=bool)
    last = fld.rig.cameras[-1]
    for r0 in range(0, len(ys) - 1, rows - 1):
        band = ys[r0 : r0 + rows]
        iy, ix = np.meshgrid(band, xs, indexing="ij")
        bundle = fld.rays(ix.ravel(), iy.ravel())
        k = bundle.vertices.shape[1]
        verts = bundle.vertices.reshape(len(band), len(xs), k, 3)
        exit_index = fld.exit_index(ix.ravel(), iy.ravel())
        counts = None if exit_index is None else (exit_index + 1).reshape(len(band), len(xs))
        active = bending_active(verts, last, counts)
        out[r0 : r0 + len(band) - 1] = quad_folds(verts, active)
    return out, stride


def measure(fld):
    """Preserved errors per camera and folds of a prepared RayField.

    Returns
    -------
    cameras : list of dict (schema "cameras" entries). folds : int.
    """
    rig = fld.rig
    cameras = []
    for i, cam in enumerate(rig.cameras):
        ix, iy = measured_pixels(rig.masks[i])
        pres = preserved_error(rig.cameras, i, fld.rays(ix, iy))
        err, angle = pres.summary()
        entry = {"name": cam.name, "pixels": pres.pixels, "preserved_px": err, "angle_deg": angle}
        if not pres.pixels:
            entry["reason"] = (
                f"no pixel of its mask is left after eroding it by {ERODE_PX} px"
                if rig.masks[i].any()
                else "its mask is empty: it only bends rays"
            )
        cameras.append(entry)
    folds, _stride = fold_map(fld)
    return cameras, int(folds.sum())


def build_report(fld, quality, total_seconds=None):
    """The report of a prepared field as a dict of schema version 2.

    Parameters
    ----------
    fld : RayField. quality : str, the quality enum name.
    total_seconds : float, wall time of the build (default: the sum of the stages).
    """
    cameras, folds = measure(fld)
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
        # added in version 2: tangent evaluations where Newton's inversion of a ray family
        # failed (the point took camera 1's direction), rays the trace's step limit cut
        "newton_lost": int(fld.stats.get("newton_lost", 0)),
        "unfinished": int(fld.stats.get("unfinished", 0)),
        "warnings": list(fld.warnings),
        # added keys: why AUTO chose the method (absent otherwise); grid levels (1 for one
        # uniform grid, more for nested grids, 0 without a 3D grid)
        **({"auto": fld.stats["auto"]} if "auto" in fld.stats else {}),
        "levels": int(fld.stats.get("levels", len(fld.grids))),
    }


def headline(report):
    """One line for the panel: worst p95 error, folds, time."""
    worst = max(
        (
            c["preserved_px"]["p95"]
            for c in report["cameras"]
            if c["preserved_px"]["p95"] is not None
        ),
        default=0.0,
    )
    return (
        f"{report['method']}: p95 error {worst:.2f} px, {report['folds']} folds, "
        f"{report['seconds']['total']:.1f} s"
    )


def to_json(report):
    """The report as the JSON string stored in ``scene.multiscale.report``."""
    return json.dumps(
        report, indent=1, default=lambda o: o.item() if isinstance(o, np.generic) else str(o)
    )


def readable(report):
    """The report as lines of text for people: the headline, then per camera and for the
    build what each figure means."""
    lines = [headline(report), ""]
    for cam in report.get("cameras", []):
        err, ang = cam["preserved_px"], cam["angle_deg"]
        if err["p95"] is None:
            lines.append(f"'{cam['name']}': not measured ({cam.get('reason', 'no pixel')})")
            continue
        surface = cam.get("surface_px", {}).get("p95")
        lines.append(
            f"'{cam['name']}': {cam['pixels']} preserved pixels measured; error along the "
            f"ray p50 {err['p50']:.2f}, p95 {err['p95']:.2f}, max {err['max']:.2f} px; angle "
            f"p95 {ang['p95']:.2f} deg"
            + (f"; at the visible surface p95 {surface:.2f} px" if surface is not None else "")
        )
    s = report.get("seconds", {})
    lines.append("")
    lines.append(
        "Time: "
        + ", ".join(f"{k} {s[k]:.1f} s" for k in ("fill", "solve", "tangents", "trace") if k in s)
        + f" (total {s.get('total', 0.0):.1f} s{', cached' if report.get('cached') else ''})"
    )
    solver = report.get("solver", {})
    lines.append(
        f"Solver: {solver.get('iterations', 0)} iterations, residual "
        f"{solver.get('residual', 0.0):.1e}, "
        + ("converged" if solver.get("converged") else "NOT converged")
    )
    lines.append(
        f"Grids: {', '.join('x'.join(map(str, g)) for g in report.get('grids', [])) or 'none'}"
    )
    lines.append(
        f"Folds: {report.get('folds', 0)} (quads of neighbouring rays that cross)"
        f"; stalled rays: {report.get('stalled', 0)}; Newton failures: "
        f"{report.get('newton_lost', 0)}"
    )
    warnings = report.get("warnings", [])
    if warnings:
        lines.append("")
        lines.append("Warnings:")
        lines += [f"- {w}" for w in warnings]
    return lines
