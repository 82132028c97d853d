"""Where nested SCALAR_FIELD folds on the 1000x rig, and why (docs/architecture.md,
*Nested grids*, "Where the 1000x rig's transition rays fold").

    .venv/bin/python tools/fold_sites.py WIDTH HEIGHT [key=value ...]

Builds ``fixtures.rigs.zoom1000_rig`` at STANDARD with nested grids in one process,
counts folds with the report's exact counter (``quality.report.fold_map``) and prints
the report's along-ray p95 / max per camera, then, over the folded quads, where their
first folded section lies: the nested level and its blend ramp, N, the pixels' distance
to camera 2's mask, whether the four rays are traced or interpolated, the depth along
cameras 1 and 2 in near distances, camera 2's family parameters there (how far its pixel
lies off the image, tau), the angle between neighbouring rays and their spacing. Keys:
``guard=F`` the guides' ``GUARD_FRACTION`` (0.5); ``cubic=1`` the monotone cubic blend
weights; ``step=D`` retraces the folded quads' rays with the step over D; ``subpx=N``
retraces every ``every``-th folded quad (default 6) on an (N + 1)^2 lattice of rays 1/N
pixel apart and counts its folded sub-quads; ``along=X,Y`` follows the rays of pixels
(X, Y) and (X + 1, Y) through camera 2's family. Changes to the field, tried and not
kept: ``clamp=M`` gives camera i > 1's tangent at a point whose pixel in its family lies
more than M image sizes off its image the tangent of the nearest pixel within that
margin (same tau), ``soft=M`` that of the pixel M tanh(d / M) image sizes off the
image for one d off it (smooth across the edge); ``fade=M0,M1`` fades camera i > 1's
blend weight from 1 at M0 image sizes off its image to 0 at M1 (smoothstep, the
others' weights renormalised); ``family=M`` changes the family itself: camera i > 1's
rays leave its near plane at their pixels' pinhole points along the direction of the
pixel held within M image sizes of its image (``soft_clamp``), its guides and straight
stretch with them (``edge_family``); ``family_only=K`` holds camera K's alone;
``shrink=M0,M1`` brings N between two cameras' values down to the outer one's beside
the smaller camera's view, from M0 to M1 image sizes off it (``shrink_membership``).
"""

import dataclasses
import sys
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import multiscale_camera.core.field.tracer as tracer_module  # noqa: E402
import multiscale_camera.core.geometry.family as family  # noqa: E402
import multiscale_camera.core.geometry.guides as guides  # noqa: E402
from fixtures.rigs import zoom1000_rig  # noqa: E402
from multiscale_camera.core.geometry import Family, Rig  # noqa: E402
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from multiscale_camera.core.methods.traced import _nested_step  # noqa: E402
from multiscale_camera.core.quality import build_report  # noqa: E402
from multiscale_camera.core.quality.folds import quad_folds  # noqa: E402
from multiscale_camera.core.quality.metrics import bending_active  # noqa: E402
from multiscale_camera.core.quality.report import fold_map  # noqa: E402
from tools.flow_jacobian import section_turns  # noqa: E402


def flipped_sections(v, active):
    """(K,) bool: sections of ray a (v[0], (4, K, 3) float64 rays a, b, c, d) whose
    corner triangles turn against the first section, as ``quad_folds`` (brute force:
    ``tools/flow_jacobian.section_turns``)."""
    return section_turns(v, active) > 0


def quad_pixels(y, x):
    return np.array([x, x + 1, x + 1, x]), np.array([y, y, y + 1, y + 1])


def pct(a):
    return f"median {np.median(a):.3g}, range {np.min(a):.3g} to {np.max(a):.3g}"


def sites(fld, folds):
    """Print where the folded quads' first folded sections lie."""
    cams, dom = fld.rig.cameras, fld.domain
    w, h = fld.rig.size
    fam = Family(cams, 1, fld.rig.beta)
    mask2 = np.argwhere(np.asarray(fld.rig.masks[1], dtype=bool)) + 0.5
    rows = []
    for y, x in zip(*np.nonzero(folds)):
        px, py = quad_pixels(y, x)
        b = fld.rays(px, py)
        v = b.vertices.astype(np.float64)
        act = bending_active(b.vertices, cams[-1], fld.exit_index(px, py) + 1, cams[:-1])
        k = np.flatnonzero(flipped_sections(v, act))[0]
        p = v[:, k]
        level, ramp = dom._depth(p[:1])
        u, vv, tau = fam.start(p)
        u, vv, tau = fam.solve(p, u, vv, tau, 30, dom.scale(p))[:3]
        off = off_image(u, vv, (w, h))
        d = v[:, min(k + 1, v.shape[1] - 1)] - v[:, max(k - 1, 0)]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip(d[1:] @ d[0], -1, 1))).max()
        near2 = cams[1].near_points(cams[1].directions(np.array([0.0, w]), np.array([h / 2] * 2)))
        spacing = np.linalg.norm(p[1:] - p[0], axis=1).max() / np.linalg.norm(near2[1] - near2[0])
        to_mask = np.hypot(mask2[:, 0] - (y + 1), mask2[:, 1] - (x + 1)).min()
        depth = [float((p[0] - c.eye) @ c.forward / c.clip_start) for c in cams[:2]]
        traced = int((fld.index[py, px] >= 0).sum())
        leaf = fld.leaves[fld.leaf_of[py, px]]
        rows.append(
            (
                k,
                level[0],
                ramp[0],
                float(dom.sample(p[:1])[0]),
                traced,
                (leaf[:, 2] - leaf[:, 0]).max(),
                *depth,
                off[0],
                off.max(),
                tau[0],
                angle,
                spacing,
                to_mask,
            )
        )
    r = np.array(rows, dtype=float)
    print(f"first folded section: vertex {pct(r[:, 0])}")
    levels, counts = np.unique(r[:, 1].astype(int), return_counts=True)
    print(
        "nested level there:",
        dict(zip(levels.tolist(), counts.tolist())),
        f"({int((r[:, 2] < 1).sum())} inside a level's blend band)",
    )
    print(f"N there: {pct(r[:, 3])}")
    print(
        f"quads whose four rays are traced: {int((r[:, 4] == 4).sum())} of {len(r)}; "
        f"largest lattice leaf among their pixels: {int(r[:, 5].max())} px"
    )
    print(f"depth in camera 1's near distances: {pct(r[:, 6])}; in camera 2's: {pct(r[:, 7])}")
    print(
        f"camera 2's family pixel of ray a off the image (image widths): {pct(r[:, 8])}; "
        f"of the farthest ray of the quad: {pct(r[:, 9])}; tau: {pct(r[:, 10])}"
    )
    print(f"largest angle between ray a and b, c, d there (degrees): {pct(r[:, 11])}")
    print(f"their spacing at vertex k over camera 2's near-plane width: {pct(r[:, 12])}")
    print(f"quad's distance to camera 2's mask (px): {pct(r[:, 13])}")


def retrace(fld, folds, div):
    """Retrace the folded quads' rays with the step over ``div``; print how many still fold."""
    cams, tracer = fld.rig.cameras, fld.tracer()
    ys, xs = np.nonzero(folds)
    px, py = (np.concatenate(a) for a in zip(*(quad_pixels(y, x) for y, x in zip(ys, xs))))
    step = partial(_nested_step, fld.step.args[0] / div, fld.domain)
    tr = tracer.trace_pixels(px, py, step, int(700 * div))
    act = bending_active(tr.vertices, cams[-1], tr.counts, cams[:-1])
    v = tr.vertices.astype(np.float64)
    still = sum(flipped_sections(v[q : q + 4], act[q : q + 4]).any() for q in range(0, len(px), 4))
    print(f"retraced with the step / {div:g}: {still} of {len(ys)} quads still fold")


def subpixel(fld, folds, n, every):
    """Trace every ``every``-th folded quad on rays 1/``n`` px apart; print its folds."""
    cams, tracer = fld.rig.cameras, fld.tracer()
    g = np.arange(n + 1) / n
    hit = total = 0
    for y, x in list(zip(*np.nonzero(folds)))[::every]:
        u, v = np.meshgrid(x + 0.5 + g, y + 0.5 + g)
        tr = tracer.trace(u.ravel(), v.ravel(), fld.step, 700)
        kk = tr.vertices.shape[1]
        act = bending_active(tr.vertices, cams[-1], tr.counts, cams[:-1])
        f = quad_folds(tr.vertices.reshape(n + 1, n + 1, kk, 3), act.reshape(n + 1, n + 1, kk))
        hit, total = hit + bool(f.any()), total + 1
        print(f"  quad ({x}, {y}): {int(f.sum())} of {f.size} sub-quads 1/{n} px wide fold")
    print(f"{hit} of {total} folded quads still fold on rays 1/{n} px apart")


def off_image(u, v, size):
    """How far pixels (u, v) lie off an image of ``size`` (width, height), in image sizes."""
    w, h = size
    return np.maximum(np.maximum(-u, u - w) / w, np.maximum(-v, v - h) / h).clip(0)


def clamp_tangents(margin, soft=False):
    """Patch ``FieldTracer._tangent``: camera i > 1's tangent at a point whose family
    pixel lies more than ``margin`` image sizes off its image is that of the nearest
    pixel within the margin, at the same tau (``clamp=``); with ``soft``, for a pixel d
    image sizes off the image, that of the pixel ``margin`` tanh(d / ``margin``) off it
    (``soft=``)."""
    original = tracer_module.FieldTracer._tangent

    def tangent(self, i, x, params, rows):
        out = original(self, i, x, params, rows)
        if i == 0:
            return out
        w, h = self.rig.size
        cam = self.rig.cameras[i]
        beyond = ((x - cam.eye) @ cam.forward >= cam.clip_start) & (params[i, rows, 2] >= i - 1)
        u, v, tau = (params[i, rows, c].copy() for c in range(3))
        pix, _depth = cam.project(x[beyond])
        u[beyond], v[beyond] = pix[:, 0], pix[:, 1]
        if soft:  # u beyond the image's edge e goes to e + margin * tanh((u - e) / margin)
            cu, cv = soft_clamp(u, w, margin)[0], soft_clamp(v, h, margin)[0]
        else:
            cu = np.clip(u, -margin * w, (1 + margin) * w)
            cv = np.clip(v, -margin * h, (1 + margin) * h)
        moved = (cu != u) | (cv != v)
        straight, bent = moved & beyond, moved & ~beyond
        out[straight] = cam.directions(cu[straight], cv[straight])
        if bent.any():
            t = self.families[i].evaluate(cu[bent], cv[bent], tau[bent])[1]
            out[bent] = t / np.linalg.norm(t, axis=1, keepdims=True)
        return out

    tracer_module.FieldTracer._tangent = tangent


def soft_clamp(c, n, margin):
    """(c', dc'/dc): pixel coordinates ``c`` held softly within ``margin`` image sizes
    of [0, n]: e + margin n tanh((c - e) / (margin n)) beyond an edge e, c inside."""
    edge = np.clip(c, 0.0, n)
    th = np.tanh((c - edge) / (margin * n))
    return edge + margin * n * th, 1.0 - th * th


def edge_family(margin, only=None):
    """Patch ``Family._near`` and ``FieldTracer._tangent`` (``family=M``): camera i > 1's
    rays leave its near plane at the pinhole points of their pixels, as before, but
    along the direction of the pixel held within ``margin`` image sizes of its image
    (``soft_clamp``), so off the image its guides turn no more than near the edge and
    its straight stretch runs on along those directions. The family stays one family
    (points, tangents and Jacobian agree), unlike ``clamp=``, which changes the tangent
    alone. Off the image beyond the near plane the tangent is no longer the pinhole
    direction, so there the tracer solves the family as it does on the guides (from
    ``Family.start``, no warm start; its lost points counted as the tracer's)."""
    near = family.Family._near

    def _near(self, j, u, v, derivatives=False):
        if j == 0 or (only is not None and j != only):
            return near(self, j, u, v, derivatives)
        cam = self.cameras[j]
        u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
        p = cam.near_points(cam.directions(u, v))
        cu, fu = soft_clamp(u, cam.width, margin)
        cv, fv = soft_clamp(v, cam.height, margin)
        d = cam.directions(cu, cv)
        if not derivatives:
            return p, d
        ax, _bx, ay, _by = cam.image_affine
        r, f = cam.rotation, cam.forward
        a = (p - cam.eye) * (1.0 / cam.clip_start)
        inv_norm_c = (d @ f)[:, None]  # 1 / |a| at the held pixel, where a . f = 1
        out = []
        for col, scale, fac in ((r[:, 0], ax, fu), (r[:, 1], ay, fv)):
            da = col * scale
            dp = cam.clip_start * (da - a * (da @ f))
            dd = (da - d * (d @ da)[:, None]) * inv_norm_c * fac[:, None]
            out += [dp, dd]
        return p, d, out

    family.Family._near = _near
    original = tracer_module.FieldTracer._tangent

    def tangent(self, i, x, params, rows):
        out = original(self, i, x, params, rows)
        if i == 0 or (only is not None and i != only):
            return out
        cam = self.rig.cameras[i]
        beyond = ((x - cam.eye) @ cam.forward >= cam.clip_start) & (params[i, rows, 2] >= i - 1)
        pix = cam.project(x[beyond])[0]
        off = np.flatnonzero(beyond)[off_image(pix[:, 0], pix[:, 1], self.rig.size) > 0]
        if len(off):
            fam = self.families[i]
            scale = self.domain.scale(x[off]) if self.domain is not None else None
            solved = fam.solve(x[off], *fam.start(x[off]), 12, scale)
            out[off] = solved[3]
            self.missed += solved[4]  # counted as the tracer counts its own
        return out

    tracer_module.FieldTracer._tangent = tangent


def fade_weights(m0, m1):
    """Patch ``FieldTracer.velocity``: camera i > 1's weight fades from 1 at ``m0`` image
    sizes off its image to 0 at ``m1`` (``fade=``); where every weight fades, the
    unfaded blend."""

    def velocity(self, x, rows):
        w = tracer_module.blend_weights(self.n_of(x), len(self.families), self.cubic)
        y, total = np.zeros_like(x), np.zeros(len(x))
        raw, raw_total = np.zeros_like(x), np.zeros(len(x))
        for i in range(len(self.families)):
            sel = np.flatnonzero(w[i] > 0)
            if not len(sel):
                continue
            t = self._tangent(i, x[sel], self.params, rows[sel])
            raw[sel] += w[i, sel, None] * t
            raw_total[sel] += w[i, sel]
            f = np.ones(len(sel))
            if i > 0:
                off = off_image(*self.params[i, rows[sel], :2].T, self.rig.size)
                s = np.clip((m1 - off) / (m1 - m0), 0.0, 1.0)
                f = s * s * (3.0 - 2.0 * s)
            y[sel] += (w[i, sel] * f)[:, None] * t
            total[sel] += w[i, sel] * f
        faded = total < 1e-6
        y[faded], total[faded] = raw[faded], raw_total[faded]
        return y / np.maximum(total, 1e-30)[:, None]

    tracer_module.FieldTracer.velocity = velocity


def shrunk_membership(rig, x, nval, m0, m1):
    """(P,) float64: N at points ``x`` (P, 3) brought down as ``shrink_membership`` says,
    from ``nval`` (P,), for ``rig``'s cameras."""
    nval = np.array(nval, dtype=np.float64)
    base = np.floor(nval)
    for c in range(1, len(rig.cameras)):
        sel = np.flatnonzero((nval > base) & (base == c))
        if not len(sel):
            continue
        cam = rig.cameras[c]
        pix, depth = cam.project(x[sel])
        ahead = depth > 0
        off = np.full(len(sel), np.inf)
        off[ahead] = off_image(pix[ahead, 0], pix[ahead, 1], rig.size)
        t = np.clip((m1 - off) / (m1 - m0), 0.0, 1.0)
        keep = t * t * (3.0 - 2.0 * t)
        g = np.clip(depth / cam.clip_start, 0.0, 1.0)
        keep = 1.0 - (1.0 - keep) * g * g * (3.0 - 2.0 * g)
        nval[sel] = base[sel] + (nval[sel] - base[sel]) * keep
    return nval


def shrink_membership(m0, m1):
    """Patch ``FieldTracer.velocity`` (``shrink=M0,M1``): where N lies between two
    cameras' values, k < N < k + 1, its excess over k is brought down towards k (the
    outer camera's value) beside the smaller camera's view: scaled by 1 within ``m0``
    image sizes of its image, seen from its eye, falling by a smoothstep to 0 at
    ``m1``; the fall itself fades in with the point's depth in that camera, from 0 at
    its eye to whole at its near plane (no change behind its eye). Whole values, which
    the preserved rays hold, do not move."""
    original = tracer_module.FieldTracer.velocity

    def velocity(self, x, rows):
        own = self.n_of  # the blend reads N through it: shrink it for this call alone
        self.n_of = lambda pts: shrunk_membership(self.rig, pts, own(pts), m0, m1)
        try:
            return original(self, x, rows)
        finally:
            self.n_of = own

    tracer_module.FieldTracer.velocity = velocity


def along(fld, x, y, first=30, last=100):
    """Print, every 5 vertices, N and camera 2's family (u, v, tau) along the rays of
    pixels (x, y) and (x + 1, y), and the angle of X_2 there to camera 1's direction of
    the pixel (``along=X,Y``)."""
    cams, dom = fld.rig.cameras, fld.domain
    fam = Family(cams, 1, fld.rig.beta)
    b = fld.rays(np.array([x, x + 1]), np.array([y, y]))
    for r, v in enumerate(b.vertices.astype(np.float64)):
        p = v[first:last:5]
        u, vv, tau = fam.start(p)
        u, vv, tau, tangent = fam.solve(p, u, vv, tau, 30, dom.scale(p))[:4]
        d1 = cams[0].directions(np.array([x + r + 0.5]), np.array([y + 0.5]))[0]
        t = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)
        angle = np.degrees(np.arccos(np.clip(t @ d1, -1, 1)))
        print(f"pixel ({x + r}, {y}):")
        for k, n, a, b2, c, d in zip(range(first, last, 5), dom.sample(p), u, vv, tau, angle):
            print(
                f"  vertex {k}: N {n:.3f}, camera 2's u {a:.0f} v {b2:.0f} tau {c:.3f}, "
                f"X_2 {d:.1f} degrees from camera 1's ray"
            )


def main(argv):
    width, height = int(argv[0]), int(argv[1])
    opts = dict(a.split("=", 1) for a in argv[2:])
    if "guard" in opts:
        guides.GUARD_FRACTION = family.GUARD_FRACTION = float(opts["guard"])
    if "clamp" in opts:
        clamp_tangents(float(opts["clamp"]))
    if "soft" in opts:
        clamp_tangents(float(opts["soft"]), soft=True)
    if "fade" in opts:
        fade_weights(*(float(m) for m in opts["fade"].split(",")))
    if "shrink" in opts:
        shrink_membership(*(float(m) for m in opts["shrink"].split(",")))
    if "family" in opts:
        only = int(opts["family_only"]) - 1 if "family_only" in opts else None
        edge_family(float(opts["family"]), only)
    cams, masks = zoom1000_rig(width, height)
    settings = dataclasses.replace(
        settings_for("STANDARD"), nested=True, processes=1, cubic=opts.get("cubic") == "1"
    )
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings)
    folds, _stride = fold_map(fld, processes=1)
    report = build_report(fld, "STANDARD")
    print(
        f"{width}x{height}: {int(folds.sum())} folded quads (report: {report['folds']}); "
        "along-ray p95 / max px per camera: "
        + ", ".join(
            f"{c['preserved_px']['p95']:.2f} / {c['preserved_px']['max']:.2f}"
            for c in report["cameras"]
        )
        + f"; Newton lost {report['newton_lost']}"
    )
    if "along" in opts:
        along(fld, *(int(c) for c in opts["along"].split(",")))
    if folds.any():
        sites(fld, folds)
        if "step" in opts:
            retrace(fld, folds, float(opts["step"]))
        if "subpx" in opts:
            subpixel(fld, folds, int(opts["subpx"]), int(opts.get("every", 6)))


if __name__ == "__main__":
    main(sys.argv[1:])
