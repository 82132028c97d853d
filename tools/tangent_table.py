"""Prototype: each camera's tangent field X_i tabulated at the nested levels' cell
centres and read trilinearly, as the paper stores it, against the build's exact
tangents (Newton on the ray family at every RK4 stage). docs/architecture.md, "Ray
families instead of sampled tangent fields", holds what it measured.

    .venv/bin/python tools/tangent_table.py RIG WIDTH HEIGHT [RAYS]

Builds forced ``SCALAR_FIELD`` on nested grids (STANDARD, one process), then:

- tabulates X_i (unit, float32) at every centre of every level where camera i's blend
  weight can be positive (N within 1 of i at the centre or a neighbour); cold Newton
  from ``Family.start``, as the build's retries; points Newton loses are left out;
- traces ``RAYS`` (default 4,000, seeded) transition pixels' rays three times with the
  build's step: exact tangents (the build's), the table (exact only where a corner's
  value is missing), and exact tangents with Newton's tolerance at 1e-9 instead of
  1e-6 (what a negligible change moves the rays by: the baseline);
- prints the times and, for each ray, its worst distance across the exact ray
  (``transition_convergence.across_px``), in pixels of the multiscale image there (the
  ``ScaleField``'s view width over the image width): p50, p95, p99 and max over the
  rays.
"""

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fixtures.rigs as rigs  # noqa: E402
import multiscale_camera.core.field.tracer as tracer_module  # noqa: E402
from multiscale_camera.core.field.fill import _dilate  # noqa: E402
from multiscale_camera.core.field.nested import ScaleField  # noqa: E402
from multiscale_camera.core.geometry import Rig  # noqa: E402
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from tools.transition_convergence import across_px, transition_pixels  # noqa: E402


def tabulate(domain, family, i, first_eye):
    """(V, 3) float32 unit X_i at every level's centres, NaN where not needed or lost;
    and the seconds it took."""
    start = time.perf_counter()
    parts = []
    for lev, grid in enumerate(domain.grids):
        n = domain.values[domain.offsets[lev] : domain.offsets[lev] + grid.size]
        need = _dilate(np.abs(n.reshape(grid.shape) - (i + 1)) < 1.0).ravel()
        table = np.full((grid.size, 3), np.nan, dtype=np.float32)
        centres = grid.centres(flat=True)[need]
        if i == 0:  # camera 1's rays are straight
            rel = centres - first_eye
            table[need] = rel / np.linalg.norm(rel, axis=1)[:, None]
        elif len(centres):
            u, v, tau = family.start(centres)
            *_uvt, unit, lost, _jac = family.solve(
                centres, u, v, tau, 8, domain.scale(centres), with_jacobian=True
            )
            unit[lost] = np.nan
            table[need] = unit
        parts.append(table)
    return np.concatenate(parts), time.perf_counter() - start


def read(domain, table, points, level):
    """Trilinear (P, 3) of ``table`` on level ``level[p]`` at ``points[p]`` (as
    ``NestedDomain._read``, three channels)."""
    idx = (points - domain.origins[level]) * domain.inv_cells[level][:, None]
    np.clip(idx, 0.0, domain.tops[level], out=idx)
    corner = np.clip(idx.astype(np.intp), 0, domain.lasts[level])
    f = idx - corner
    strides, steps = domain.strides[level], domain.steps[level]
    base = domain.offsets[level] + (corner * strides).sum(axis=1)
    out = np.zeros((len(points), 3))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = np.prod(np.where([dx, dy, dz], f, 1.0 - f), axis=1)
                at = base + dx * steps[:, 0] + dy * steps[:, 1] + dz * steps[:, 2]
                out += w[:, None] * table[at]
    return out


class TableTracer(tracer_module.FieldTracer):
    """The build's tracer with X_i read from ``tables`` (exact where a corner's value
    is missing)."""

    tables = None
    fallback = 0

    def _tangent(self, i, x, params, rows):
        start = time.perf_counter()
        level, ramp = self.domain._depth(x)
        out = read(self.domain, self.tables[i], x, level)
        band = np.flatnonzero(ramp < 1.0)
        if len(band):
            parent = read(self.domain, self.tables[i], x[band], level[band] - 1)
            out[band] = parent + ramp[band, None] * (out[band] - parent)
        bad = np.flatnonzero(~np.isfinite(out).all(axis=1))
        self.fallback += len(bad)
        self.tangent_seconds += time.perf_counter() - start
        if len(bad):
            out[bad] = super()._tangent(i, x[bad], params, rows[bad])
        return out / np.linalg.norm(out, axis=1)[:, None]


def build_tracer(fld):
    """The build's own tracer of ``fld`` (one process)."""
    return tracer_module.FieldTracer(fld.rig, fld.grid, fld.membership, domain=fld.domain)


def main(argv):
    rig_name, width, height = argv[0], int(argv[1]), int(argv[2])
    count = int(argv[3]) if len(argv) > 3 else 4000
    cams, masks = getattr(rigs, f"{rig_name}_rig")(width, height)
    rig = Rig(cams, masks)
    settings = dataclasses.replace(settings_for("STANDARD"), nested=True, processes=1)
    start = time.perf_counter()
    fld = prepare(rig, "SCALAR_FIELD", settings)
    print(f"build {time.perf_counter() - start:.1f} s: {fld.seconds}")
    domain = fld.domain
    exact, tight = build_tracer(fld), build_tracer(fld)
    table = TableTracer(rig, fld.grid, fld.membership, domain=domain)
    tables, seconds, nodes = [], 0.0, 0
    for i, family in enumerate(exact.families):
        t, s = tabulate(domain, family, i, cams[0].eye)
        tables.append(t)
        seconds += s
        nodes += int(np.isfinite(t[:, 0]).sum())
    table.tables = tables
    total = domain.values.size * len(cams)
    print(f"table: {nodes} values (of {total} centres x families), {seconds:.1f} s")
    u0, v0 = transition_pixels(rig, count)
    runs = {}
    for name, tr in (("exact", exact), ("table", table)):
        start = time.perf_counter()
        runs[name] = tr._trace_here(u0, v0, fld.step, 4000)
        took = time.perf_counter() - start
        print(f"{name}: trace {took:.2f} s, tangents {tr.tangent_seconds:.2f} s")
    print(f"table: {table.fallback} tangents taken exactly (a corner missing)")
    tracer_module.TRACE_NEWTON_TOLERANCE = 1e-9
    runs["tight"] = tight._trace_here(u0, v0, fld.step, 4000)
    scale = ScaleField(cams)
    ref = runs["exact"]
    for name in ("table", "tight"):
        got = runs[name]
        dev = across_px(
            ref.vertices, ref.counts, got.vertices, got.counts, lambda p: scale(p) / width
        )
        p = np.percentile(dev, [50, 95, 99, 100])
        print(
            f"{name} vs exact, each ray's worst px: p50 {p[0]:.4f} p95 {p[1]:.4f} "
            f"p99 {p[2]:.4f} max {p[3]:.4f}"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
