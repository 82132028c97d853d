"""Camera i's curved rays R_i laid out analytically on the trace's schedule, so that
preserved pixels' rays are R_i exactly and can be mixed and interpolated with traced
ones, vertex by vertex (docs/architecture.md, *Preserved rays*)."""

import numpy as np

from ..geometry import near_plane_entries
from .plane_step import NearPlaneStep

# Dense samples per guide stage for arc-length lookups of R_i: the chord error of
# 64 samples on a guide is below 1e-5 of its length.
ARC_SAMPLES = 64


def arc_length_rays(family, u, v, step, vertices):
    """Camera i's curved rays R_i resampled at arc lengths 0, step, 2 step, ...

    Parameters
    ----------
    family : Family. u, v : (R,) float pixel coordinates. step : float, world units.
    vertices : int, K.

    Returns
    -------
    (R, K, 3) float64, world units: the layout the tracer produces, so analytic and
    traced rays can be mixed and interpolated.
    """
    r = len(u)
    s = np.arange(vertices) * step
    cam = family.cameras[-1]
    p_i = cam.near_points(cam.directions(u, v))
    v_i = cam.directions(u, v)
    if family.i == 0:
        return p_i[:, None] + v_i[:, None] * s[None, :, None]
    taus = np.linspace(0.0, family.i, family.i * ARC_SAMPLES + 1)
    pts, _ = family.evaluate(np.repeat(u, len(taus)), np.repeat(v, len(taus)), np.tile(taus, r))
    pts = pts.reshape(r, len(taus), 3)
    cum = np.concatenate(
        [np.zeros((r, 1)), np.cumsum(np.linalg.norm(np.diff(pts, axis=1), axis=-1), axis=1)], axis=1
    )
    bend = cum[:, -1]
    # every ray's arc lengths, offset so all rays fit one increasing sequence: one
    # searchsorted finds each vertex's guide sample
    span = bend.max() + 1.0
    flat = (cum + span * np.arange(r)[:, None]).ravel()
    want = np.minimum(s[None, :], bend[:, None]) + span * np.arange(r)[:, None]
    hi = np.clip(np.searchsorted(flat, want.ravel()), 1, flat.size - 1).reshape(r, vertices)
    k = len(taus)
    hi = np.clip(hi - np.arange(r)[:, None] * k, 1, k - 1)
    rows = np.arange(r)[:, None]
    c0, c1 = cum[rows, hi - 1], cum[rows, hi]
    w = ((np.minimum(s[None, :], bend[:, None]) - c0) / np.maximum(c1 - c0, 1e-300))[..., None]
    out = pts[rows, hi - 1] * (1 - w) + pts[rows, hi] * w
    beyond = s[None, :] > bend[:, None]
    straight = p_i[:, None] + v_i[:, None] * (s[None, :] - bend[:, None])[..., None]
    out[beyond] = straight[beyond]
    return out


def scheduled_rays(family, u, v, step, vertices, contains, chunk=4096):
    """Camera i's curved rays R_i with vertex k at the k-th step of a step function.

    The layout of traces whose step follows the local cell (nested grids): from each
    vertex x the next lies ``step(x)`` further along the curve, so analytic and traced
    rays can be mixed and interpolated. Vertices lie exactly on R_i: arc length maps to
    the family's tau through a dense table, and the point is evaluated at that tau.
    A ray's vertices stop advancing after its first vertex outside ``contains`` that
    follows another on its straight part (the rest run straight on at the last step's
    length, along camera i's pinhole ray).

    Parameters
    ----------
    family : Family. u, v : (R,) float pixel coordinates.
    step : callable, (P, 3) float64 world points -> (P,) float64 lengths, world units.
    vertices : int, K. contains : callable, (P, 3) -> (P,) bool, the modelled volume.
    chunk : int, rays laid out together (bounds the (chunk, K, 3) work arrays).

    Returns
    -------
    (R, K, 3) float64, world units.
    """
    out = np.empty((len(u), vertices, 3))
    for s in range(0, len(u), chunk):
        out[s : s + chunk] = _scheduled_chunk(
            family, u[s : s + chunk], v[s : s + chunk], step, vertices, contains
        )
    return out


def _scheduled_chunk(family, u, v, step, vertices, contains):
    r = len(u)
    cam = family.cameras[-1]
    v_i = cam.directions(u, v)
    p_i = cam.near_points(v_i)
    out = np.empty((r, vertices, 3))
    if family.i == 0:
        out[:, 0] = p_i
        bend = np.zeros(r)
        taus = cum = None
    else:
        taus = np.linspace(0.0, family.i, family.i * ARC_SAMPLES + 1)
        pts, _ = family.evaluate(np.repeat(u, len(taus)), np.repeat(v, len(taus)), np.tile(taus, r))
        pts = pts.reshape(r, len(taus), 3)
        cum = np.concatenate(
            [np.zeros((r, 1)), np.cumsum(np.linalg.norm(np.diff(pts, axis=1), axis=-1), axis=1)],
            axis=1,
        )
        bend = cum[:, -1]
        out[:, 0] = pts[:, 0]
    s = np.zeros(r)
    seg = np.zeros(r, dtype=np.int64)  # dense sample before each ray's arc length
    live = np.arange(r)
    for k in range(1, vertices):
        if not len(live):
            break
        x = out[live, k - 1]
        h = step(x)
        s[live] += h
        sl = s[live]
        on_curve = sl < bend[live]
        nxt = np.empty((len(live), 3))
        straight = ~on_curve
        if straight.any():
            rows = live[straight]
            nxt[straight] = p_i[rows] + v_i[rows] * (sl[straight] - bend[rows])[:, None]
        if on_curve.any():
            rows = live[on_curve]
            target = sl[on_curve]
            j = seg[rows]
            last = cum.shape[1] - 2
            while True:
                ahead = (j < last) & (cum[rows, j + 1] <= target)
                if not ahead.any():
                    break
                j[ahead] += 1
            seg[rows] = j
            c0, c1 = cum[rows, j], cum[rows, j + 1]
            t = taus[j] + (taus[j + 1] - taus[j]) * (target - c0) / np.maximum(c1 - c0, 1e-300)
            nxt[on_curve], _ = family.evaluate(u[rows], v[rows], t)
        out[live, k] = nxt
        # a ray leaves once outside and on its straight part (its last step too), so it
        # runs on along camera i's pinhole ray, not a chord of its guides
        left = ~contains(nxt) & (sl - h >= bend[live])
        if left.any():
            # past the first vertex outside, run straight on at the last step's length
            gone = live[left]
            d = nxt[left] - x[left]
            more = np.arange(1, vertices - k)
            if isinstance(step, NearPlaneStep):  # the band's steps, as a trace's run-on
                unit = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
                run = step.run_lengths(nxt[left], unit, more[None, :])
                out[gone, k + 1 :] = nxt[left][:, None] + unit[:, None] * run[..., None]
            else:
                out[gone, k + 1 :] = nxt[left][:, None] + d[:, None] * more[None, :, None]
            live = live[~left]
    return out


def first_past_near_plane(cameras, verts):
    """(R,) int: index of each ray's first vertex on or past the last of ``cameras``'
    near planes once it has entered that camera's view (``near_plane_entries``: after
    crossing the planes of the cameras before it, in order), 0 where it never does.
    cameras : the rig's cameras up to this one. verts : (R, K, 3) float world points."""
    entry = near_plane_entries(verts, cameras)[-1]
    return np.where(np.isfinite(entry), np.ceil(np.where(np.isfinite(entry), entry, 0)), 0).astype(
        np.int64
    )
