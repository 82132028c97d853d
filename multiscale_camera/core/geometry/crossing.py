"""Where a bent ray enters each camera's view: its crossings of the near planes, in order.

A multiscale ray starts on camera 1's near plane and, in the paper's model, passes
camera 2's near plane, then camera 3's, and so on, each from behind (paper section 4.2).
Depth along a camera's view axis alone does not say where a ray has entered that
camera's view: when consecutive cameras are turned far apart (40 degrees and more), the
start of a ray, near camera 1's near plane, can already lie beyond camera 3's near
plane, to one side of camera 3's frustum, long before the ray comes round to camera 3's
plane from behind (docs/report.md, *Preserved error*).
"""

import numpy as np


def near_plane_entries(vertices, cameras):
    """For each camera in order, where each polyline enters its view.

    The entry into camera 1's view is the ray's first point on or beyond camera 1's near
    plane (depth along the view axis at least the near distance). The entry into camera
    j's view is the first point, not before the entry into camera j-1's, where the ray
    crosses camera j's near plane from behind; if it never does after that point, the
    entry is that point itself when the ray is already on or beyond camera j's plane
    there, else there is none (infinite).

    Parameters
    ----------
    vertices : (R, K, 3) float array, K >= 2, world units: polylines.
    cameras : sequence of PinholeCamera (N of them), in the rig's order.

    Returns
    -------
    (N, R) float64: the polyline parameter of each entry, vertex index plus the fraction
    of the segment (k + t: the point v[k] + t (v[k+1] - v[k])); inf where there is none.
    """
    v = np.asarray(vertices)
    return near_plane_entries_on_planes(np.moveaxis(v, -1, 0).astype(np.float64), cameras)


def near_plane_entries_on_planes(comp, cameras):
    """``near_plane_entries`` of polylines held as coordinate planes: ``comp`` (3, R, K)
    float64, the same bits (the depths are summed as ``dot3`` sums rows: x, then z, then
    y, numpy's einsum)."""
    r, k = comp.shape[1:]
    out = np.empty((len(cameras), r))
    prev = np.zeros(r)
    rows = np.arange(r)
    d, term = np.empty((r, k)), np.empty((r, k))
    for n, cam in enumerate(cameras):
        eye = np.asarray(cam.eye, dtype=np.float64)
        fwd = np.asarray(cam.forward, dtype=np.float64)
        # ((p0 + p2) + p1) - near, p_i = (v_i - eye_i) fwd_i, in place: (R, K), >= 0 beyond
        np.subtract(comp[0], eye[0], out=d)
        d *= fwd[0]
        for i in (2, 1):
            np.subtract(comp[i], eye[i], out=term)
            term *= fwd[i]
            d += term
        d -= float(cam.clip_start)
        d0, d1 = d[:, :-1], d[:, 1:]
        # the upward crossings alone (few: one or two per ray) are located
        behind = d < 0
        ri, ci = np.nonzero(behind[:, :-1] & (d >= 0)[:, 1:])
        a0, a1 = d0[ri, ci], d1[ri, ci]
        with np.errstate(divide="ignore", invalid="ignore"):
            at_up = ci.astype(np.float64) + (-a0 / (a1 - a0))
        # ... not before the entry into the camera before (the first camera: vertex 0)
        keep = at_up >= prev[ri]
        at = np.full(r, np.inf)
        np.minimum.at(at, ri[keep], at_up[keep])
        finite = np.isfinite(prev)
        seg = np.clip(np.floor(np.where(finite, prev, 0.0)), 0, k - 2).astype(np.int64)
        t = np.where(finite, prev, 0.0) - seg
        there = d[rows, seg] * (1 - t) + d[rows, seg + 1] * t
        # no crossing from behind after the entry before: the ray may already be beyond
        # this camera's plane there (a camera whose plane the ray starts on)
        at = np.where(np.isinf(at) & finite & (there >= 0), prev, at)
        out[n] = at
        prev = at
    return out
