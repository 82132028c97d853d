"""How far the transition rays of nested SCALAR_FIELD move when its cells or its step
are halved: are they converged in the grid? (docs/performance.md, "Where the forced
build's time goes".)

    .venv/bin/python tools/transition_convergence.py RIG WIDTH HEIGHT [RAYS]

Builds the field twice, with 16 cells across the smallest camera's near plane (the
build's, at 0.5 px) and with 32, at STANDARD and a voxel budget four times the
default's (one process each), and traces ``RAYS`` (default 1,500, seeded) transition
pixels' rays through each at the build's step and at half of it
(``nested.STEP_SCALE``: the step is the scale field over it and the cells across).
For each pair it prints, over the rays, p50 / p95 / p99 / max of each ray's worst
distance from the other's, across the other ray (``across_px``), in pixels of the
multiscale image there (the scale field's view width over the image width).
"""

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fixtures.rigs as rigs  # noqa: E402
import multiscale_camera.core.field.fill as fill  # noqa: E402
import multiscale_camera.core.field.nested as nested  # noqa: E402
import multiscale_camera.core.methods.scalar_field as scalar_field  # noqa: E402
from multiscale_camera.core.field import FieldTracer  # noqa: E402
from multiscale_camera.core.field.nested import ScaleField  # noqa: E402
from multiscale_camera.core.geometry import Rig  # noqa: E402
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from multiscale_camera.core.methods.traced import preserved_labels  # noqa: E402


def arc_lengths(verts):
    """(R, K) float64 arc length at each vertex of polylines ``verts`` (R, K, 3)."""
    seg = np.linalg.norm(np.diff(verts, axis=1), axis=2)
    return np.concatenate([np.zeros((len(verts), 1)), np.cumsum(seg, axis=1)], axis=1)


def across_px(ref, ref_counts, got, got_counts, px_at):
    """(R,) each ray's worst distance of ``got``'s vertices from ``ref``'s polyline.

    A vertex of ray r of ``got`` at arc length s is compared with the point of ray r of
    ``ref`` at the same arc length, the difference taken across ``ref``'s segment
    there (sliding along the ray moves nothing in the picture), over the arc length
    both rays have; in pixels: over ``px_at(points)``, (P,) world units a pixel there.

    ref, got : (R, K, 3) float; ref_counts, got_counts : (R,) int, vertices to use.
    """
    ref, got = ref.astype(np.float64), got.astype(np.float64)
    ref_s, got_s = arc_lengths(ref), arc_lengths(got)
    worst = np.zeros(len(got))
    for r in range(len(got)):
        nr, ng = int(ref_counts[r]), int(got_counts[r])
        s = got_s[r, :ng]
        s = s[s <= min(ref_s[r, nr - 1], s[-1])]
        if not len(s):
            continue
        cum = ref_s[r, :nr]
        at = np.stack([np.interp(s, cum, ref[r, :nr, a]) for a in range(3)], axis=1)
        j = np.clip(np.searchsorted(cum, s), 1, nr - 1)
        t = ref[r, j] - ref[r, j - 1]
        t /= np.maximum(np.linalg.norm(t, axis=1), 1e-300)[:, None]
        d = got[r, : len(s)] - at
        d -= (d * t).sum(axis=1)[:, None] * t
        worst[r] = (np.linalg.norm(d, axis=1) / px_at(at)).max()
    return worst


def transition_pixels(rig, count, seed=1):
    """(n,) float64 u, v: the centres of ``count`` transition pixels of ``rig`` (no
    camera keeps them), drawn without repeats (all of them if fewer)."""
    ys, xs = np.nonzero(preserved_labels(rig) == 0)
    pick = np.random.default_rng(seed).choice(len(xs), min(count, len(xs)), replace=False)
    return xs[pick] + 0.5, ys[pick] + 0.5


def main(argv):
    rig_name, width, height = argv[0], int(argv[1]), int(argv[2])
    count = int(argv[3]) if len(argv) > 3 else 1500
    cams, masks = getattr(rigs, f"{rig_name}_rig")(width, height)
    rig = Rig(cams, masks)
    u0, v0 = transition_pixels(rig, count)
    settings = dataclasses.replace(
        settings_for("STANDARD"), nested=True, processes=1, max_voxels=4 * 160**3
    )
    build_scale = nested.STEP_SCALE
    rays = {}
    for across in (32, 16):
        per_px = across * settings.accuracy_px
        fill.CELLS_ACROSS_NEAR_PER_PX = scalar_field.CELLS_ACROSS_NEAR_PER_PX = per_px
        # the step is the scale field over STEP_SCALE x the cells across: 32 across
        # steps as 16 across does at half the build's STEP_SCALE
        nested.STEP_SCALE = build_scale * 16 / across
        start = time.perf_counter()
        fld = prepare(rig, "SCALAR_FIELD", settings)
        capped = any("voxel budget" in w for w in fld.warnings)
        voxels = sum(g.size for g in fld.domain.grids)
        took = time.perf_counter() - start
        print(f"{across} across: build {took:.1f} s, {voxels} voxels, capped {capped}")
        for half in (False, True):
            nested.STEP_SCALE = build_scale * 16 / across * (2 if half else 1)
            tracer = FieldTracer(rig, fld.grid, fld.membership, domain=fld.domain)
            most = 4 * fld.traced.vertices.shape[1]
            rays[across, half] = tracer._trace_here(u0, v0, fld.step, most)
    nested.STEP_SCALE = build_scale
    scale = ScaleField(cams)

    def px_at(points):
        return scale(points) / width

    pairs = (
        ("the step halved, 16 across (the build's cells)", (16, False), (16, True)),
        ("the step halved, 32 across", (32, False), (32, True)),
        ("the cells halved, the build's step", (16, False), (32, False)),
        ("the cells halved, half the build's step", (16, True), (32, True)),
    )
    for what, a, b in pairs:
        dev = across_px(rays[b].vertices, rays[b].counts, rays[a].vertices, rays[a].counts, px_at)
        p = np.percentile(dev, [50, 95, 99, 100])
        print(f"{what}: p50 {p[0]:.3f} p95 {p[1]:.3f} p99 {p[2]:.3f} max {p[3]:.3f} px")


if __name__ == "__main__":
    main(sys.argv[1:])
