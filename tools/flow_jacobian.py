"""Where a SCALAR_FIELD folds, does its flow turn over? The determinant of the flow's
Jacobian along the rays, against the exact fold counter, and what the counter's folded
quads look like in their sections (docs/architecture.md, "What the fold counter counts,
and where the flow turns over").

    .venv/bin/python tools/flow_jacobian.py RIG WIDTH HEIGHT QUALITY [key=value ...]

Streamlines P(x, y, s) of one Lipschitz field T (unit speed, s the arc length from
camera 1's near plane) keep the sign of D(s) = det[T, dP/dx, dP/dy]: along a ray
dD/ds = div(T) D, so D(s) = D(0) exp(integral of div T), which can shrink but never
pass through zero. Pixels whose rays' D changes sign are traced on rays that are not
such streamlines (a step too long for the flow, or a field that jumps), and D near
zero (relative to D(0)) is a flow that all but focuses the pixels' rays.

Builds ``fixtures.rigs.<RIG>_rig`` with SCALAR_FIELD (``method``) in one process,
counts its folds with the report's counter (``quality.report.fold_map``), and at
every ``every``-th quad of three kinds (folded, all four pixels in transitions; folded,
touching a preserved pixel; not folded, in transitions) traces the rays of the quad's
centre and ``eps`` pixels either side of it in x and in y (central differences), and
prints, per kind: how many centres' D changes sign inside the bending stretch, how many of the
quads ``eps`` wide the counter finds folded, the median and least of min D / D(0),
the first sign changes' membership N, and at how many sites (and how many of those
whose D changes sign) a ray had a camera's tangent taken from its guides beyond its
near plane (``GuidesBeyond``); then, on the same rays, at how many sites a camera's
family turned its orientation along a ray or its solved tau ran back (``FamilySheets``),
and at how many the six rays split between guides beyond a near plane and not. Keys:
``eps=F`` (0.05 px), ``every=N`` (10), ``method=M`` (SCALAR_FIELD; another method's
field has no flow to trace, and gets the corner triangles alone).

Then, for every folded quad, the most corner triangles (a b c, b c d, c d a, d a b)
turned in one section (``corner_turns``, brute force on the field's rays, as the counter
cuts them). One turned triangle is a quad that is no longer convex: its ray d lies
inside the triangle of a, b and c (or the like), and the triangulation along its other
diagonal keeps both triangles' orientation, so no two neighbouring rays have swapped
(the bilinear interpolation between them, which the renderer uses, is no longer
one-to-one there: docs/report.md, "Folds").
Two or more (the areas of a b c and c d a add up to those of b c d and d a b, so two
turned triangles are neighbours) leave neither triangulation whole: the quad's edges
cross or it is mirrored.
"""

import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fixtures.rigs as rigs  # noqa: E402
import multiscale_camera.core.field.tracer as tracer_module  # noqa: E402
from multiscale_camera.core.geometry import Rig  # noqa: E402
from multiscale_camera.core.geometry.vectors import dot3  # noqa: E402
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from multiscale_camera.core.methods.traced import preserved_labels  # noqa: E402
from multiscale_camera.core.quality.folds import _segment_at, quad_folds, section_points  # noqa: E402
from multiscale_camera.core.quality.metrics import bending_active  # noqa: E402
from multiscale_camera.core.quality.report import fold_map  # noqa: E402

# The rays traced per site: the centre, then +x, -x, +y, -y and +x+y (eps pixels off).
OFFSETS = ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1))


def flow_determinant(centre, xp, xm, yp, ym, eps):
    """D = det[T, dP/dx, dP/dy] at each vertex of the centre rays.

    Parameters
    ----------
    centre, xp, xm, yp, ym : (n, K, 3) float64 rays (vertices in world units) of n
        sites' centres and of the points ``eps`` pixels off them along +x, -x, +y, -y,
        traced with the same steps, so that vertex k of each lies at about the same
        arc length (a difference along T does not change D).
    eps : float, pixels.

    Returns
    -------
    (n, K) float64, world units squared per pixel squared: T the centre ray's unit
    direction (central differences of its vertices), dP/dx and dP/dy central
    differences of the neighbours.
    """
    t = np.gradient(centre, axis=1)
    t /= np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-300)
    px = (xp - xm) / (2.0 * eps)
    py = (yp - ym) / (2.0 * eps)
    return np.einsum("nki,nki->nk", t, np.cross(px, py))


def sign_changes(d, valid):
    """Where D leaves its first sign (zero counts as leaving it): ``d`` (n, K) float64,
    ``valid`` (n, K) bool (the vertices checked). Returns (n,) bool, whether it does at
    a valid vertex, and (n,) int, the first such vertex (0 where none)."""
    flip = (np.sign(d) != np.sign(d[:, :1])) & valid
    return flip.any(axis=1), np.argmax(flip, axis=1)


def quad_kinds(folds, label):
    """The three kinds of quads (folds: (H-1, W-1) bool, the counter's map; label:
    (H, W) int, 0 in transitions, i + 1 in camera i's kept pixels): a dict of name to
    (H-1, W-1) bool."""
    corners = (label[:-1, :-1], label[:-1, 1:], label[1:, :-1], label[1:, 1:])
    transition = np.logical_and.reduce([c == 0 for c in corners])
    return {
        "folded, in transitions": folds & transition,
        "folded, touching kept pixels": folds & ~transition,
        "not folded, in transitions": ~folds & transition,
    }


class _TangentHook:
    """A ``with`` block during which ``FieldTracer._tangent`` also calls ``record``
    (tracer, i, params, rows, past, straight) after each evaluation, ``params`` as it
    left them: ``past`` (n,) bool, the points at or beyond camera i's near plane;
    ``straight`` (n,) bool, those ``_tangent`` gave camera i's straight part (``past``
    where the ray's tau had reached i - 1 before the call), the rest solved on its
    family."""

    def __enter__(self):
        original = self.original = tracer_module.FieldTracer._tangent

        def tangent(tracer, i, x, params, rows):
            cam = tracer.rig.cameras[i]
            past = dot3(x - cam.eye, cam.forward) >= cam.clip_start
            straight = past & (params[i, rows, 2] >= i - 1)
            out = original(tracer, i, x, params, rows)
            self.record(tracer, i, params, rows, past, straight)
            return out

        tracer_module.FieldTracer._tangent = tangent
        return self

    def __exit__(self, *exc):
        tracer_module.FieldTracer._tangent = self.original
        return False


class GuidesBeyond(_TangentHook):
    """While in a ``with`` block, records which rays had a camera's tangent taken from
    its guides at a point beyond its near plane (``FieldTracer._tangent``: a ray takes
    camera i's straight part only once its tau reaches i - 1; where camera i's family
    also runs beside its frustum, the same point then gets another tangent on another
    ray). ``rays``: (R,) bool after the block, for the last trace's R rays."""

    rays = None

    def record(self, tracer, i, params, rows, past, straight):
        if self.rays is None or len(self.rays) != params.shape[1]:
            self.rays = np.zeros(params.shape[1], dtype=bool)
        self.rays[rows[past & ~straight]] = True


def orientation(family, u, v, tau):
    """(P,) int8: the sign of det[dR/du, dR/dv, dR/dtau] of ``family`` (a
    ``geometry.Family``) at (u, v, tau), (P,) float64 each (0 where it vanishes)."""
    _point, along, du, dv = family.evaluate(u, v, tau, jacobian=True)
    return np.sign(dot3(du, np.cross(dv, along))).astype(np.int8)


class FamilySheets(_TangentHook):
    """While in a ``with`` block, records along every ray of a trace the orientation of
    each camera's family where the ray took that camera's tangent from it (Newton on the
    family, not its straight part): the sign of det[dR/du, dR/dv, dR/dtau] at the
    solved (u, v, tau) (``orientation``). A family whose curves fold over along a
    ray (det taking both signs) gives one point two tangents. ``both``: (F, R) bool
    after the block, camera i's family took both signs along ray r; ``back``: (F, R)
    bool, the solved tau ran back by more than ``BACK_TAU`` between two evaluations (a
    jump to another sheet of the family)."""

    BACK_TAU = 0.05
    both = back = sign = tau = None

    def record(self, tracer, i, params, rows, past, straight):
        f, r = params.shape[:2]
        if self.both is None or self.both.shape != (f, r):
            self.both, self.back = np.zeros((f, r), bool), np.zeros((f, r), bool)
            self.sign, self.tau = np.zeros((f, r), np.int8), np.full((f, r), np.nan)
        solved = rows[~straight]
        if i == 0 or len(solved) == 0:
            return
        u, v, tau = (params[i, solved, c] for c in range(3))
        sign = orientation(tracer.families[i], u, v, tau)
        before = self.sign[i, solved]
        self.both[i, solved] |= (before != 0) & (sign != 0) & (sign != before)
        self.sign[i, solved] = np.where(sign != 0, sign, before)
        last = self.tau[i, solved]
        self.back[i, solved] |= np.isfinite(last) & (tau < last - self.BACK_TAU)
        self.tau[i, solved] = tau


def examine(fld, quads, eps, every):
    """Trace every ``every``-th quad of ``quads`` ((H-1, W-1) bool) of the field ``fld``
    at its centre and ``eps`` px around it; a dict of the figures the module prints."""
    ys, xs = (a[::every] for a in np.nonzero(quads))
    n = len(ys)
    if n == 0:
        return {"sites": 0}
    cams = fld.rig.cameras
    u = np.concatenate([xs + 1.0 + eps * dx for dx, _dy in OFFSETS])
    v = np.concatenate([ys + 1.0 + eps * dy for _dx, dy in OFFSETS])
    with GuidesBeyond() as guides, FamilySheets() as sheets:
        traced = fld.tracer().trace(u, v, fld.step, 4000)
    on = guides.rays.reshape(len(OFFSETS), n)
    beyond = on.any(axis=0)
    # a site's rays split between the guides beyond a near plane and the rest
    split = beyond & ~on.all(axis=0)
    f = sheets.both.shape[0]
    folded_family = sheets.both.reshape(f, len(OFFSETS), n).any(axis=1)
    ran_back = sheets.back.reshape(f, len(OFFSETS), n).any(axis=1)
    rays = traced.vertices.astype(np.float64).reshape(len(OFFSETS), n, -1, 3)
    counts = traced.counts.reshape(len(OFFSETS), n)
    active = bending_active(traced.vertices, cams[-1], traced.counts, cams[:-1])
    active = active.reshape(len(OFFSETS), n, -1)
    k = rays.shape[2]
    valid = (np.arange(k) < counts.min(axis=0)[:, None] - 1) & active[0]
    d = flow_determinant(rays[0], rays[1], rays[2], rays[3], rays[4], eps)
    flips, first = sign_changes(d, valid)
    least = np.where(valid, d * np.sign(d[:, :1]), np.inf).min(axis=1) / np.abs(d[:, 0])
    # the counter on the quad eps wide: (y, x) rows of centre, +x / +y, +x+y
    tiny = 0
    for q in range(n):
        grid = np.stack([[rays[0, q], rays[1, q]], [rays[3, q], rays[5, q]]])
        act = np.stack([[active[0, q], active[1, q]], [active[3, q], active[5, q]]])
        tiny += bool(quad_folds(grid, act).any())
    membership = traced.membership.reshape(len(OFFSETS), n, -1)[0]
    at = membership[np.flatnonzero(flips), first[flips]]
    return {
        "sites": n,
        "d_flips": int(flips.sum()),
        "tiny_folds": tiny,
        "least_p50": float(np.median(least)),
        "least_min": float(least.min()),
        "flip_n": at,
        "beyond": int(beyond.sum()),
        "beyond_flips": int((beyond & flips).sum()),
        "split": int(split.sum()),
        "split_flips": int((split & flips).sum()),
        # per camera: sites where its family's orientation turned along a ray (and of
        # them where D turns), and where its solved tau ran back
        "family_turns": [int(folded_family[i].sum()) for i in range(f)],
        "family_turns_flips": [int((folded_family[i] & flips).sum()) for i in range(f)],
        "tau_back": [int(ran_back[i].sum()) for i in range(f)],
    }


# The corner triangles of a quad a b c d (its rays 0, 1, 2, 3: pixels (x, y), (x + 1,
# y), (x + 1, y + 1), (x, y + 1)), as the counter orders them.
CORNERS = ((0, 1, 2), (1, 2, 3), (2, 3, 0), (3, 0, 1))


def section_turns(rays, active):
    """How many corner triangles of one quad are turned against the first section, in
    each section: ``rays`` (4, K, 3) float64 (a, b, c, d), ``active`` (4, K) bool (the
    bending stretch). The sections are planes through a's vertices normal to its
    direction (central differences); b, c and d cross them where ``section_points``
    finds them from the vertex at a's arc length, as the counter does. A section counts
    where a's vertex and the three crossings' segments are active. Returns (K,) int."""
    a = rays[0]
    t = np.empty_like(a)
    t[1:-1], t[0], t[-1] = a[2:] - a[:-2], a[1] - a[0], a[-1] - a[-2]
    normal = t / np.linalg.norm(t, axis=1, keepdims=True)
    cum = np.zeros(rays.shape[:2])
    cum[:, 1:] = np.cumsum(np.linalg.norm(np.diff(rays, axis=1), axis=-1), axis=1)
    points, live = [np.zeros_like(a)], active[0].copy()
    for r in (1, 2, 3):
        start = _segment_at(cum[r : r + 1], cum[0][None])
        p, j = section_points(rays[r : r + 1], a[None], normal[None], start)
        points.append(p[0])
        live &= active[r][j[0]]
    turned = np.zeros(len(a), dtype=int)
    for i, j, k in CORNERS:
        area = np.einsum("ij,ij->i", np.cross(points[j] - points[i], points[k] - points[i]), normal)
        o = np.sign(area)
        turned += (o != o[0]) & (o != 0) & (o[0] != 0)
    return np.where(live, turned, 0)


def corner_turns(fld, ys, xs):
    """(n,) int: for the quads at (``xs``, ``ys``) ((n,) int, their top-left pixels) of
    the field ``fld``, the most corner triangles turned in one section
    (``section_turns``), on the rays and the bending stretch the report's counter
    takes (``quality.report``: up to the ray's exit from the field where it has one)."""
    cams = fld.rig.cameras
    ys, xs = np.asarray(ys, dtype=np.int64), np.asarray(xs, dtype=np.int64)
    n = len(ys)
    out = np.zeros(n, dtype=int)
    if not n:
        return out
    # every quad's four rays in one request (a ray does not depend on the others asked
    # for with it; past its trace it runs straight, outside the bending stretch)
    ix = (xs[:, None] + np.array([0, 1, 1, 0])).ravel()
    iy = (ys[:, None] + np.array([0, 0, 1, 1])).ravel()
    bundle = fld.rays(ix, iy)
    exit_index = fld.exit_index(ix, iy)
    counts = None if exit_index is None else exit_index + 1
    active = bending_active(bundle.vertices, cams[-1], counts, cams[:-1])
    rays = bundle.vertices.astype(np.float64).reshape(n, 4, -1, 3)
    active = active.reshape(n, 4, -1)
    for q in range(n):
        out[q] = section_turns(rays[q], active[q]).max()
    return out


def main(argv):
    rig_name, width, height, quality = argv[:4]
    opts = dict(a.split("=", 1) for a in argv[4:])
    eps, every = float(opts.get("eps", 0.05)), int(opts.get("every", 10))
    method = opts.get("method", "SCALAR_FIELD")
    cams, masks = getattr(rigs, f"{rig_name}_rig")(int(width), int(height))
    settings = dataclasses.replace(settings_for(quality), processes=1)
    fld = prepare(Rig(cams, masks), method, settings)
    folds, stride = fold_map(fld, 1)
    if stride != 1:
        raise SystemExit("the counter took every second pixel: ask for at most a megapixel")
    print(f"{rig_name} {width}x{height} {quality} {method}: {int(folds.sum())} folded quads")
    if method == "SCALAR_FIELD":
        print(f"D from rays eps {eps:g} px apart, every {every}th quad of each kind:")
        print(
            "| quads | sites | D changes sign | eps quads folded | min D/D(0) p50 | least "
            "| N at the first sign change | guides beyond a near plane (of the sign changes) |"
        )
        print("|---|---|---|---|---|---|---|---|")
        sheets = []
        for name, quads in quad_kinds(folds, preserved_labels(fld.rig)).items():
            r = examine(fld, quads, eps, every)
            if not r["sites"]:
                print(f"| {name} | 0 | | | | | | |")
                continue
            n_at = r["flip_n"]
            span = f"{n_at.min():.2f} to {n_at.max():.2f}" if len(n_at) else "-"
            print(
                f"| {name} | {r['sites']} | {r['d_flips']} | {r['tiny_folds']} | "
                f"{r['least_p50']:.3g} | {r['least_min']:.3g} | {span} | "
                f"{r['beyond']} ({r['beyond_flips']}) |"
            )
            sheets.append((name, r))
        print("Families along the same rays (sites, and of them where D turns):")
        for name, r in sheets:
            turns = ", ".join(
                f"camera {i + 1} {t} ({tf}), tau back {b}"
                for i, (t, tf, b) in enumerate(
                    zip(r["family_turns"], r["family_turns_flips"], r["tau_back"])
                )
                if i
            )
            print(
                f"- {name}: a family's orientation turned: {turns}; rays split between "
                f"guides beyond a near plane and not: {r['split']} ({r['split_flips']})"
            )
    turns = corner_turns(fld, *np.nonzero(folds))
    counts = {n: int((turns == n).sum()) for n in range(5)}
    print(
        f"folded quads by the most corner triangles turned in one section: {counts} "
        f"(0: the counter's stretch and this one differ)"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
