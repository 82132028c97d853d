"""When does IMAGE_BLEND fold, and does SCALAR_FIELD's fill say in advance that it will?
Prints the tables of docs/architecture.md's *Where IMAGE_BLEND folds* section.

    .venv/bin/python tools/fold_predictor.py predict [RIG ...] [--sizes 192x108 480x270]
    .venv/bin/python tools/fold_predictor.py gaps [--size 192x108]
    .venv/bin/python tools/fold_predictor.py conflicts --size 480x270 --out FILE.jsonl
    .venv/bin/python tools/fold_predictor.py conflicts-table FILE.jsonl [FILE.jsonl ...]
    .venv/bin/python tools/fold_predictor.py fill [RIG ...] --size 1920x1080 --quality STANDARD

``predict``: IMAGE_BLEND's rays are P(x) = sum_i w_i(x) R_i(x) (``image_blend``). In a
section across the bundle at vertex k the quad's orientation is the sign of
t . (P_x x P_y), t the ray's direction there and P_x, P_y its derivatives along the
image's x and y. Since the weights sum to one,

    P_x = M_x + sum_i (R_i - P) g_i,x,   M = sum_i w_i J_i,   g_i = grad w_i,

J_i = dR_i/dx the curve's own Jacobian. For two cameras A, B (w = w_A) the matrix
determinant lemma gives det(P') = det(M) (1 + g . s), with s = M^-1 (R_A - R_B) in the
section: the separation of the two cameras' curves in image pixels (as the blend maps
pixels there). A quad turns over where 1 + g . s < 0. The predictor evaluates this at
every quad's centre from the curves alone (R_i at the centre and half a pixel either
side) and the weights' differences across the quad, with no ray of the lattice traced
against another, and is compared, quad by quad, with the exact counter
(``quality.report.fold_map``).

``gaps``: the turned rig with its mask radii, near planes or turns changed, folds
counted (exact) and predicted for each, and the gap the separation s asks for
(``needed_gap``).

``conflicts``: SCALAR_FIELD as AUTO builds it (``bench/methods.py --one RIG
SCALAR_FIELD_DEFAULT QUALITY``) on every bench rig, or with ``--variants`` on variants of
the turned rig, one process each, each given at most ``--timeout`` seconds, its rows
appended to ``--out``; ``conflicts-table`` prints the fill's conflicting voxels against
IMAGE_BLEND's folds and SCALAR_FIELD's measured folds and p95. ``fill``: the fill alone
(its conflicts and seconds), as SCALAR_FIELD's build makes it.
"""

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import fixtures.rigs as rigs  # noqa: E402
import multiscale_camera.core.methods.scalar_field as scalar_field  # noqa: E402
from bench.methods import _commit, _run, _worst  # noqa: E402
from fixtures.masks import radius  # noqa: E402
from multiscale_camera.core.field import choose_grid, fill_membership  # noqa: E402
from multiscale_camera.core.geometry import (  # noqa: E402
    DEFAULT_SEGMENTS,
    Family,
    Rig,
    build_guides,
    cross3,
    curved_rays,
    dot3,
)
from multiscale_camera.core.methods import prepare, settings_for  # noqa: E402
from multiscale_camera.core.quality import (  # noqa: E402
    bending_active,
    build_report,
    kept_folds,
    transition_folds,
)
from multiscale_camera.core.quality.report import fold_map  # noqa: E402

# Half the step of the curves' central differences, pixels.
STEP_PX = 0.5
# Quad rows per chunk of the predictor (bounds memory: about 5 N K 3 floats a quad).
CHUNK_ROWS = 16


def blend_field(cams, masks):
    """IMAGE_BLEND's field of ``cams`` and ``masks`` at STANDARD, in this process."""
    settings = replace(settings_for("STANDARD"), processes=1)
    return prepare(Rig(cams, masks), "IMAGE_BLEND", settings)


def _curves(cams, px, py, beta):
    """(N, P, K, 3) float64: every camera's curve R_i at continuous pixels (px, py)."""
    return curved_rays(build_guides(cams, px, py, beta=beta), DEFAULT_SEGMENTS)


def quad_sections(fld, qy, qx):
    """The section determinants of IMAGE_BLEND's field ``fld`` at the centres of the quads
    (qy, qx) ((Q,) int: the quad of pixels (y, x) to (y + 1, x + 1)), from the curves
    (R_i at the centre and ``STEP_PX`` either side) and the weights' differences across
    the quad.

    Returns
    -------
    det, det_m : (Q, K) float, t . (P_x x P_y) and t . (M_x x M_y) in every section (t
    the blended ray's direction there, a central difference as ``quad_folds`` takes it).
    active : (Q, K) bool, the bending stretch (``bending_active``).
    """
    cams, beta = fld.rig.cameras, fld.rig.beta
    w = np.asarray(fld.weights, dtype=np.float64)
    c00, c01 = w[:, qy, qx], w[:, qy, qx + 1]
    c10, c11 = w[:, qy + 1, qx], w[:, qy + 1, qx + 1]
    wc = 0.25 * (c00 + c01 + c10 + c11)
    gx = 0.5 * ((c01 - c00) + (c11 - c10))
    gy = 0.5 * ((c10 - c00) + (c11 - c01))
    cx, cy = qx + 1.0, qy + 1.0  # the quad's centre (pixel centres at +0.5)
    r0 = _curves(cams, cx, cy, beta)
    step = 2 * STEP_PX
    jx = (_curves(cams, cx + STEP_PX, cy, beta) - _curves(cams, cx - STEP_PX, cy, beta)) / step
    jy = (_curves(cams, cx, cy + STEP_PX, beta) - _curves(cams, cx, cy - STEP_PX, beta)) / step
    p = np.einsum("np,npkc->pkc", wc, r0)
    mx = np.einsum("np,npkc->pkc", wc, jx)
    my = np.einsum("np,npkc->pkc", wc, jy)
    sep = r0 - p[None]  # sum_i g_i = 0: sum_i R_i g_i = sum_i (R_i - P) g_i
    px_ = mx + np.einsum("np,npkc->pkc", gx, sep)
    py_ = my + np.einsum("np,npkc->pkc", gy, sep)
    t = np.empty_like(p)
    t[:, 1:-1] = p[:, 2:] - p[:, :-2]
    t[:, 0] = p[:, 1] - p[:, 0]
    t[:, -1] = p[:, -1] - p[:, -2]
    det = dot3(t, cross3(px_, py_))
    det_m = dot3(t, cross3(mx, my))
    return det, det_m, bending_active(p, cams[-1], None, cams[:-1])


def predict(fld):
    """The predictor on every quad of IMAGE_BLEND's field ``fld`` (``quad_sections``).

    Returns
    -------
    dict of (H - 1, W - 1) arrays: "folds" bool, the quad's section determinant at its
    centre changes sign against section 0 somewhere in the bending stretch; "lemma"
    float, min over that stretch of det(P') / det(M) (for two cameras 1 + g . s: below 0
    the weights' slope turns the quad over); "blend" bool, det(M) itself changes sign
    (the averaged curves fold without the weights' slope).
    """
    h, wd = fld.weights.shape[1:]
    out = {
        "folds": np.zeros((h - 1, wd - 1), dtype=bool),
        "lemma": np.full((h - 1, wd - 1), np.inf),
        "blend": np.zeros((h - 1, wd - 1), dtype=bool),
    }
    xs = np.arange(wd - 1)
    for y0 in range(0, h - 1, CHUNK_ROWS):
        ys = np.arange(y0, min(y0 + CHUNK_ROWS, h - 1))
        qy, qx = np.meshgrid(ys, xs, indexing="ij")
        det, det_m, active = quad_sections(fld, qy.ravel(), qx.ravel())
        flip = active & (np.sign(det) != np.sign(det[:, :1]))
        blend = active & (np.sign(det_m) != np.sign(det_m[:, :1]))
        ratio = np.where(active & (det_m != 0), det / np.where(det_m != 0, det_m, 1.0), np.inf)
        shape = (len(ys), wd - 1)
        out["folds"][ys] = flip.any(axis=1).reshape(shape)
        out["blend"][ys] = blend.any(axis=1).reshape(shape)
        out["lemma"][ys] = ratio.min(axis=1).reshape(shape)
    return out


def dilate(a, steps=1):
    """(Hq, Wq) bool ``a`` grown by ``steps`` quads in the 8 directions."""
    out = a.copy()
    for _ in range(steps):
        b = out.copy()
        b[1:] |= out[:-1]
        b[:-1] |= out[1:]
        c = b.copy()
        c[:, 1:] |= b[:, :-1]
        c[:, :-1] |= b[:, 1:]
        out = c
    return out


def compare(counted, predicted):
    """Quad-by-quad agreement of the exact count and the prediction: a dict of counts
    (``near``: within one quad of the other map)."""
    return {
        "counted": int(counted.sum()),
        "predicted": int(predicted.sum()),
        "both": int((counted & predicted).sum()),
        "missed": int((counted & ~predicted).sum()),
        "false": int((predicted & ~counted).sum()),
        "missed_near": int((counted & ~dilate(predicted)).sum()),
        "false_near": int((predicted & ~dilate(counted)).sum()),
    }


# Points of the eased weight's range where the needed gap is sought (``needed_gap``).
EASE_STEPS = 64


def needed_gap(cams, beta, inner, outer, px, py):
    """The narrowest gap, in pixels, across which the weights of cameras ``inner`` and
    ``outer`` (0-based; inner: the one whose mask lies nearer the image's centre) can go
    from 1 to 0 without a fold at pixels (px, py), from the curves alone.

    Across a gap of G pixels the harmonic weight h falls about linearly from 1 to 0, and
    the eased weight w = e(h) = 3 h^2 - 2 h^3 has slope e'(h) / G toward the centre. With
    s(w) = M(w)^-1 (R_inner - R_outer), M(w) = w J_inner + (1 - w) J_outer, in each section
    (the separation of the two curves in image pixels, as the blend maps pixels there)
    and s_r its component away from the image's centre, the lemma's 1 + g . s stays
    positive where G > e'(h) s_r(e(h)). The largest such bound over h in (0, 1) and the
    sections of the bending stretch is returned: (P,) float, pixels (0 where s_r never
    points outward). Where the inner camera's pixels are much smaller than the outer's
    (J_inner << J_outer) the bound peaks near the inner mask (w near 1), not mid-gap.
    """
    w, h = cams[0].width, cams[0].height
    pair = [inner, outer]

    def curves(x, y):
        return _curves(cams, x, y, beta)[pair]

    r = curves(px, py)
    jx = (curves(px + STEP_PX, py) - curves(px - STEP_PX, py)) / (2 * STEP_PX)
    jy = (curves(px, py + STEP_PX) - curves(px, py - STEP_PX)) / (2 * STEP_PX)
    u = r[0] - r[1]
    dx, dy = px - w / 2, py - h / 2
    norm = np.hypot(dx, dy)
    norm = np.where(norm > 0, norm, 1.0)
    ux, uy = (dx / norm)[:, None], (dy / norm)[:, None]
    out = np.zeros(len(px))
    for hh in (np.arange(EASE_STEPS) + 0.5) / EASE_STEPS:
        ww = hh * hh * (3 - 2 * hh)
        slope = 6 * hh * (1 - hh)
        p = ww * r[0] + (1 - ww) * r[1]
        mx = ww * jx[0] + (1 - ww) * jx[1]
        my = ww * jy[0] + (1 - ww) * jy[1]
        t = np.empty_like(p)
        t[:, 1:-1] = p[:, 2:] - p[:, :-2]
        t[:, 0] = p[:, 1] - p[:, 0]
        t[:, -1] = p[:, -1] - p[:, -2]
        det = dot3(t, cross3(mx, my))
        det = np.where(det != 0, det, np.inf)
        s_r = (dot3(t, cross3(u, my)) / det) * ux + (dot3(t, cross3(mx, u)) / det) * uy
        active = bending_active(p, cams[-1], None, cams[:-1])
        out = np.maximum(out, slope * np.where(active, s_r, 0.0).max(axis=1))
    return out


def by_pair(fld, quads):
    """Counts of the quads ``quads`` ((H - 1, W - 1) bool) by where they lie: "kept"
    (masks keep all four pixels: ``quality.kept_folds``), else the two cameras of
    largest weight over the quad's pixels ("2-3": cameras 2 and 3;
    ``quality.transition_folds``, which AUTO's warning names them by)."""
    masks = fld.rig.masks
    n = len(masks)
    names = [str(i + 1) for i in range(n)]
    out = {"kept": kept_folds(masks, quads, 1, names)[0]}
    out.update({f"{i + 1}-{j + 1}": 0 for i in range(n) for j in range(i + 1, n)})
    for (a, b), count in transition_folds(fld.weights, masks, quads, names):
        out[f"{a}-{b}"] = count
    return out


def ring_layout(width, height, r3, r2_in, r2_out, r1):
    """The three-camera masks of ``fixtures.masks.rings`` with other radii (fractions
    of the width): camera 3 within ``r3``, camera 2 between ``r2_in`` and ``r2_out``,
    camera 1 beyond ``r1``."""
    r = radius(width, height) / width
    return np.stack([r > r1, (r > r2_in) & (r < r2_out), r < r3])


def needed_at(cams, beta, inner, outer, r_in):
    """``needed_gap``'s largest bound over the pixels at ``r_in`` (fraction of the
    width, within half a pixel) from the image's centre: the gap, in pixels, that a
    transition from camera ``inner``'s mask edge there outward asks for (the bound falls
    outward on the rigs measured, so its value at the inner edge holds across the gap)."""
    w, h = cams[0].width, cams[0].height
    px, py = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    r = np.hypot(px - w / 2, py - h / 2)
    on = np.abs(r - r_in * w) <= 0.5
    if not on.any():
        return 0.0
    return float(needed_gap(cams, beta, inner, outer, px[on], py[on]).max())


def fill_conflicts(rig, settings):
    """SCALAR_FIELD's fill alone, as its build makes it (one uniform grid or nested
    levels, as ``scalar_field`` chooses): (conflicts, voxels, seconds), conflicts the
    voxels two cameras' preserved rays claim (nested: each level's where no finer level
    takes over, as the report counts them), without the solve and the trace."""
    start = time.perf_counter()
    families = [Family(rig.cameras, i, rig.beta) for i in range(len(rig.cameras))]
    if scalar_field._nested(rig, settings):
        grids = scalar_field.frame_levels(rig, settings).grids
    else:
        grids = (choose_grid(rig, settings.accuracy_px, settings.max_voxels).grid,)
    fills = [fill_membership(rig, g, families) for g in grids]
    conflicts = scalar_field._composite_fill(grids, fills).conflicts
    return conflicts, sum(g.size for g in grids), time.perf_counter() - start


# --- the tables ---

# The rigs of the predictor's table: fixtures.rigs' bench rigs whose IMAGE_BLEND is built
# (turn100_rig is refused before any ray is made).
PREDICT_RIGS = (
    "turned_rig",
    "zoom_rig",
    "three_camera_rig",
    "zoom25_rig",
    "zoom1000_rig",
    "contradictory_rig",
    "demo_rig",
    "galleon_rig",
)
# The turned rig (cameras 20, 8 and 3.2 from the subject, orbiting it by 0, 45 and 100
# degrees, near planes 8, 3.2 and 1.28 from their eyes) with other azimuths of cameras 2
# and 3, near planes (clip_start, world units) of cameras 2 and 3 and mask radii
# (fractions of the width: camera 3 within r3, camera 2 from r2_in to r2_out, camera 1
# beyond r1), as ``gaps`` measures it.
TURNED = {"distances": (20.0, 8.0, 3.2), "clip1": 8.0}
GAP_LAYOUTS = (
    # the bench's turned rig, then the 1-2 gap widened, then the 2-3 gap
    ((45, 100), (3.2, 1.28), (0.12, 0.2, 0.3, 0.42)),
    ((45, 100), (3.2, 1.28), (0.12, 0.2, 0.3, 0.5)),
    ((45, 100), (3.2, 1.28), (0.12, 0.2, 0.3, 0.53)),
    ((45, 100), (3.2, 1.28), (0.12, 0.2, 0.3, 0.54)),
    ((45, 100), (3.2, 1.28), (0.12, 0.28, 0.3, 0.54)),
    ((45, 100), (3.2, 1.28), (0.06, 0.28, 0.3, 0.54)),
    ((45, 100), (3.2, 1.28), (0.02, 0.28, 0.3, 0.54)),
    # near planes moved toward the subject
    ((45, 100), (3.2, 2.0), (0.12, 0.2, 0.3, 0.42)),
    ((45, 100), (3.2, 2.6), (0.12, 0.2, 0.3, 0.42)),
    ((45, 100), (3.2, 2.6), (0.12, 0.24, 0.3, 0.54)),
    ((45, 100), (3.2, 2.6), (0.12, 0.28, 0.3, 0.54)),
    ((45, 100), (3.2, 2.6), (0.08, 0.28, 0.3, 0.54)),
    ((45, 100), (5.0, 1.28), (0.12, 0.2, 0.3, 0.42)),
    ((45, 100), (5.0, 2.0), (0.12, 0.2, 0.3, 0.42)),
    ((45, 100), (5.0, 2.6), (0.12, 0.2, 0.3, 0.42)),
    ((45, 100), (5.0, 2.6), (0.12, 0.21, 0.3, 0.42)),
    ((45, 100), (6.0, 2.6), (0.12, 0.2, 0.3, 0.42)),
    # smaller turns
    ((30, 60), (3.2, 1.28), (0.12, 0.2, 0.3, 0.42)),
    ((20, 40), (3.2, 1.28), (0.12, 0.2, 0.3, 0.42)),
    ((10, 20), (3.2, 1.28), (0.12, 0.2, 0.3, 0.42)),
)


def _size(text):
    w, h = text.lower().split("x")
    return int(w), int(h)


def _pairs(counts):
    """ " (2-3, 1-2)" counts of ``by_pair``'s dict on a rig of three cameras that folds."""
    if "2-3" not in counts or not sum(counts.values()):
        return ""
    return f" ({counts['2-3']}, {counts['1-2']})"


def predict_table(names, sizes):
    """Lines of the predictor's table: the exact count against the prediction."""
    yield (
        "| rig | size | folds counted (2-3, 1-2) | predicted (2-3, 1-2) | both | counted, not "
        "predicted (> 1 quad from one) | predicted, not counted (> 1 quad from one) | "
        "quads where det(M) turns | count s | predictor s |"
    )
    yield "|---|---|---|---|---|---|---|---|---|---|"
    for width, height in sizes:
        for name in names:
            cams, masks = getattr(rigs, name)(width, height)
            fld = blend_field(cams, masks)
            start = time.perf_counter()
            counted, _stride = fold_map(fld, 1)
            mid = time.perf_counter()
            prediction = predict(fld)
            end = time.perf_counter()
            pred = prediction["folds"]
            c = compare(counted, pred)
            pc, pp = by_pair(fld, counted), by_pair(fld, pred)
            yield (
                f"| {name} | {width}x{height} | {c['counted']}{_pairs(pc)} | "
                f"{c['predicted']}{_pairs(pp)} | {c['both']} | {c['missed']} ({c['missed_near']}) "
                f"| {c['false']} ({c['false_near']}) | {int(prediction['blend'].sum())} | "
                f"{mid - start:.2f} | {end - mid:.2f} |"
            )


def gaps_table(size):
    """Lines of the gap table: the turned rig with other turns, near planes and mask radii
    (``GAP_LAYOUTS``), folds counted and predicted per transition, the gaps against
    ``needed_at``'s, the least det(P') / det(M) of any quad."""
    width, height = size
    yield (
        "| azimuths C2, C3 (view turns, degrees) | near planes C2, C3 | radii r3, r2_in, "
        "r2_out, r1 (W) | gap 2-3 px (needed) | gap 1-2 px (needed) | folds counted 2-3, "
        "1-2, kept | predicted 2-3, 1-2 | least det(P') / det(M) | pixels C1, C2, C3 |"
    )
    yield "|---|---|---|---|---|---|---|---|---|"
    for (az2, az3), (clip2, clip3), (r3, r2_in, r2_out, r1) in GAP_LAYOUTS:
        clips, turns = (TURNED["clip1"], clip2, clip3), (0.0, az2, az3)
        cams = rigs._chain(TURNED["distances"], clips, turns, width, height)
        fld = blend_field(cams, ring_layout(width, height, r3, r2_in, r2_out, r1))
        counted, _stride = fold_map(fld, 1)
        prediction = predict(fld)
        pred = prediction["folds"]
        pc, pp = by_pair(fld, counted), by_pair(fld, pred)
        least = float(prediction["lemma"].min())
        n23 = needed_at(cams, fld.rig.beta, 2, 1, r3)
        n12 = needed_at(cams, fld.rig.beta, 1, 0, r2_out)
        kept = fld.rig.masks.sum(axis=(1, 2))
        ahead = [-c.matrix_world[:3, 2] for c in cams]
        turn = [np.degrees(np.arccos(np.clip(a @ b, -1, 1))) for a, b in zip(ahead, ahead[1:])]
        yield (
            f"| {az2:g}, {az3:g} ({turn[0]:.1f}, {turn[1]:.1f}) | {clip2:g}, {clip3:g} | "
            f"{r3:g}, {r2_in:g}, {r2_out:g}, {r1:g} | "
            f"{(r2_in - r3) * width:.0f} ({n23:.0f}) | {(r1 - r2_out) * width:.0f} ({n12:.0f}) | "
            f"{pc['2-3']}, {pc['1-2']}, {pc['kept']} | {pp['2-3']}, {pp['1-2']} | {least:.3f} | "
            f"{', '.join(str(int(k)) for k in kept)} |"
        )


# The bench's rigs SCALAR_FIELD is built on (bench/methods.py's RIGS but turn100_rig,
# which validation refuses before any work).
FIELD_RIGS = PREDICT_RIGS
# How AUTO holds a field to the target (core/methods/registry.py): p95 <= the quality's
# accuracy, max <= MAX_OVER_TARGET times it, no fold.
MAX_OVER_TARGET = 4.0


def run_conflicts(size, quality, out, timeout, variants=False):
    """SCALAR_FIELD as AUTO builds it, one process per rig, rows appended to ``out`` as
    JSON lines: the bench's rigs (``bench/methods.py --one RIG SCALAR_FIELD_DEFAULT
    QUALITY``), or with ``variants`` the rigs of ``FIELD_VARIANTS`` (``run_variant``). A
    rig that runs past ``timeout`` seconds gets a row saying so."""
    width, height = size
    dims = ["--width", str(width), "--height", str(height)]
    if variants:
        jobs = [
            (variant_name(*FIELD_VARIANTS[i]), [__file__, "variant", str(i), quality, *dims])
            for i in range(len(FIELD_VARIANTS))
        ]
    else:
        script = str(ROOT / "bench" / "methods.py")
        jobs = [
            (name, [script, *dims, "--one", name, "SCALAR_FIELD_DEFAULT", quality])
            for name in FIELD_RIGS
        ]
    for name, cmd in jobs:
        start = time.perf_counter()
        try:
            done = _run(["nice", "-n", "10", sys.executable, *cmd], timeout)
            row = json.loads(done.stdout.strip().splitlines()[-1])
        except subprocess.TimeoutExpired:
            row = {"rig": name, "size": [width, height], "quality": quality}
            row["timed_out"] = timeout
            row["load_1min"] = round(os.getloadavg()[0], 2)
        row["wall_seconds"] = round(time.perf_counter() - start, 1)
        if not variants:
            cams, masks = getattr(rigs, name)(width, height)
            row["image_blend_folds"] = int(fold_map(blend_field(cams, masks), 1)[0].sum())
        with open(out, "a") as f:
            f.write(json.dumps(row) + "\n")


# Variants of the turned rig (azimuths of cameras 2 and 3, near planes of cameras 2 and 3;
# the bench's masks) on which SCALAR_FIELD's conflicts are measured beside the bench's
# rigs: IMAGE_BLEND folds on the first five (``gaps``), not on the last two.
FIELD_VARIANTS = (
    ((20, 40), (3.2, 1.28)),
    ((30, 60), (3.2, 1.28)),
    ((45, 100), (3.2, 2.6)),
    ((45, 100), (5.0, 2.0)),
    ((45, 100), (5.0, 2.6)),
    ((45, 100), (6.0, 2.6)),
    ((10, 20), (3.2, 1.28)),
)


def variant_rig(azimuths, clips, width, height):
    """The turned rig with cameras 2 and 3 at ``azimuths`` and near planes ``clips``
    (``GAP_LAYOUTS``' terms), the bench's masks: (cameras, masks)."""
    clips = (TURNED["clip1"], *clips)
    cams = rigs._chain(TURNED["distances"], clips, (0.0, *azimuths), width, height)
    return cams, rigs.rings(width, height)


def variant_name(azimuths, clips):
    return f"turned az {azimuths[0]:g},{azimuths[1]:g} near {clips[0]:g},{clips[1]:g}"


def run_variant(index, size, quality):
    """One row of ``FIELD_VARIANTS``: SCALAR_FIELD as AUTO builds it and its report, in
    this process, and IMAGE_BLEND's exact fold count; a dict in the terms of
    ``bench/methods.py``'s rows."""
    azimuths, clips = FIELD_VARIANTS[index]
    width, height = size
    cams, masks = variant_rig(azimuths, clips, width, height)
    rig = Rig(cams, masks)
    blend_folds = int(fold_map(blend_field(cams, masks), 1)[0].sum())
    start = time.perf_counter()
    fld = prepare(rig, "SCALAR_FIELD", settings_for(quality))
    report = build_report(fld, quality, time.perf_counter() - start)
    return {
        "rig": variant_name(azimuths, clips),
        "size": [width, height],
        "quality": quality,
        "image_blend_folds": blend_folds,
        "conflicts": report["conflicts"],
        "folds": report["folds"],
        "worst_p95_px": _worst(report["cameras"], "p95"),
        "worst_max_px": _worst(report["cameras"], "max"),
        "compute_field_seconds": round(time.perf_counter() - start, 3),
        "load_1min": round(os.getloadavg()[0], 2),
        "commit": _commit(),
    }


def conflicts_table(paths, wide=False):
    """Lines of the conflicts table from the rows of ``run_conflicts`` (JSON lines): a
    line per rig, a column per size and quality, each cell "IMAGE_BLEND's folds; the
    fill's conflicting voxels, SCALAR_FIELD's folds, its worst camera's p95 / max px,
    whether it meets AUTO's target"; with ``wide`` a line per row with its time, load
    and commit."""
    rows = [json.loads(line) for path in paths for line in Path(path).read_text().splitlines()]
    configs, names, cells = [], [], {}
    for r in rows:
        config = f"{r['size'][0]}x{r['size'][1]} {r['quality']}"
        if config not in configs:
            configs.append(config)
        if r["rig"] not in names:
            names.append(r["rig"])
        blend = r.get("image_blend_folds")
        if blend is None and hasattr(rigs, r["rig"]):  # a bench row: counted here
            cams, masks = getattr(rigs, r["rig"])(*r["size"])
            blend = int(fold_map(blend_field(cams, masks), 1)[0].sum())
        if "timed_out" in r:
            cell = f"{blend}; timed out after {r['timed_out']:g} s"
        else:
            target = settings_for(r["quality"]).accuracy_px
            p95, top = r["worst_p95_px"], r["worst_max_px"]
            ok = not r["folds"] and p95 <= target and top <= MAX_OVER_TARGET * target
            cell = (
                f"{blend}; {r['conflicts']}, {r['folds']}, {p95:.2f} / {top:.2f}, "
                f"{'**yes**' if ok else 'no'}"
            )
        if wide:
            yield (
                f"| {r['rig']} | {config} | {cell} | {r.get('compute_field_seconds', '')} | "
                f"{r['load_1min']} | {r.get('commit', '')} |"
            )
        cells[r["rig"], config] = cell
    if wide:
        return
    yield "| rig | " + " | ".join(configs) + " |"
    yield "|---|" + "---|" * len(configs)
    for name in names:
        yield f"| {name} | " + " | ".join(cells.get((name, c), "") for c in configs) + " |"


def fill_table(names, size, quality):
    """Lines of the fill's table: ``fill_conflicts`` of each bench rig in this process."""
    yield "| rig | size, quality | conflicting voxels | voxels (all levels) | fill s | load |"
    yield "|---|---|---|---|---|---|"
    for name in names:
        cams, masks = getattr(rigs, name)(*size)
        conflicts, voxels, seconds = fill_conflicts(Rig(cams, masks), settings_for(quality))
        yield (
            f"| {name} | {size[0]}x{size[1]}, {quality} | {conflicts} | {voxels} | "
            f"{seconds:.1f} | {os.getloadavg()[0]:.2f} |"
        )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("predict", help="the predictor against the exact fold count")
    p.add_argument("rigs", nargs="*", default=list(PREDICT_RIGS))
    p.add_argument("--sizes", nargs="+", type=_size, default=[(192, 108), (480, 270)])
    g = sub.add_parser("gaps", help="the turned rig's masks and near planes moved")
    g.add_argument("--size", type=_size, default=(192, 108))
    c = sub.add_parser("conflicts", help="SCALAR_FIELD on every bench rig, one process each")
    c.add_argument("--size", type=_size, default=(480, 270))
    c.add_argument("--quality", default="PREVIEW")
    c.add_argument("--timeout", type=float, default=180.0)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--variants", action="store_true", help="FIELD_VARIANTS, not the bench's")
    v = sub.add_parser("variant", help=argparse.SUPPRESS)
    v.add_argument("index", type=int)
    v.add_argument("quality")
    v.add_argument("--width", type=int, required=True)
    v.add_argument("--height", type=int, required=True)
    f = sub.add_parser("fill", help="SCALAR_FIELD's fill alone: its conflicts and time")
    f.add_argument("rigs", nargs="*", default=list(FIELD_RIGS))
    f.add_argument("--size", type=_size, default=(1920, 1080))
    f.add_argument("--quality", default="STANDARD")
    t = sub.add_parser("conflicts-table", help="the table of conflicts' rows")
    t.add_argument("files", nargs="+", type=Path)
    t.add_argument("--wide", action="store_true", help="a line per row, time, load, commit")
    args = parser.parse_args(argv)
    if args.command == "predict":
        lines = predict_table(args.rigs, args.sizes)
    elif args.command == "gaps":
        lines = gaps_table(args.size)
    elif args.command == "conflicts":
        run_conflicts(args.size, args.quality, args.out, args.timeout, args.variants)
        lines = conflicts_table([args.out])
    elif args.command == "fill":
        lines = fill_table(args.rigs, args.size, args.quality)
    elif args.command == "variant":
        print(json.dumps(run_variant(args.index, (args.width, args.height), args.quality)))
        return
    else:
        lines = conflicts_table(args.files, args.wide)
    for line in lines:
        print(line, flush=True)


if __name__ == "__main__":
    main()
