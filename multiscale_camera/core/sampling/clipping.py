"""Each camera's far clipping (``clip_end``) on the bent rays, as Cycles clips a pinhole
camera's rays: at the plane ``clip_end`` in front of the eye, across the view axis.

A ray's far plane is its membership's blend of the cameras' planes, with the weights
that blend the rays themselves: membership m between cameras i and i + 1 (1-based)
weighs camera i by (i + 1 - m) and camera i + 1 by (m - i). A point p lies beyond the
blended plane where

    f(p) = sum_i w_i (forward_i . (p - eye_i) - clip_end_i) > 0,

which is camera i's own far plane wherever its weight is 1 (its preserved region) and
moves continuously with the membership across a transition, so the clipped image has no
hard cut at a mask's edge. f is linear in p, so each ray's plane is one normal and one
offset.

Pure numpy.
"""

from dataclasses import replace

import numpy as np

from ..geometry import dot3


def reach_to_far_planes(cameras):
    """float, world units: a run past a ray's last vertex long enough to meet every
    camera's far plane (its ``clip_end`` over the cosine of its widest corner ray)."""
    reach = 0.0
    for cam in cameras:
        xmin, xmax, ymin, ymax = cam.view_plane()
        corner = 1.0 + max(xmin * xmin, xmax * xmax) + max(ymin * ymin, ymax * ymax)
        reach = max(reach, float(cam.clip_end) * float(np.sqrt(corner)))
    return reach


def far_planes(cameras, membership):
    """The blended far plane of rays of the given membership.

    Parameters
    ----------
    cameras : sequence of N PinholeCamera (core.geometry), the rig's in order.
    membership : (R,) float, the membership value (camera number, 1-based) where each
        ray leaves the bending stretch (``Segments.membership``).

    Returns
    -------
    normal : (R, 3) float64 and offset : (R,) float64, world units: f(p) = normal . p -
        offset, positive beyond the plane.
    """
    n = len(cameras)
    forward = np.array([c.forward for c in cameras], dtype=np.float64)
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    eye = np.array([c.eye for c in cameras], dtype=np.float64)
    plane = dot3(forward, eye) + np.array([c.clip_end for c in cameras], dtype=np.float64)
    m = np.clip(np.nan_to_num(np.asarray(membership, dtype=np.float64), nan=1.0), 1.0, n)
    lo = np.minimum(np.floor(m).astype(np.int64), n) - 1  # 0-based camera i
    hi = np.minimum(lo + 1, n - 1)
    t = (m - 1.0 - lo)[:, None]  # weight of camera i + 1 (0 at the last camera)
    normal = (1.0 - t) * forward[lo] + t * forward[hi]
    offset = (1.0 - t[:, 0]) * plane[lo] + t[:, 0] * plane[hi]
    return normal, offset


def clip_far(seg, cameras):
    """``seg`` with every ray cut where it first crosses its far plane (``far_planes``).

    Parameters
    ----------
    seg : Segments (``simplification.Segments``) of R rays.
    cameras : the rig's PinholeCameras.

    Returns
    -------
    Segments: lengths shortened at the crossing, the segments after it of length 0 and
    not castable; ``clipped`` (R,) bool says which rays were cut before their end.
    """
    if len(seg.origin) == 0:
        return replace(seg, clipped=np.zeros(len(seg), dtype=bool))
    normal, offset = far_planes(cameras, seg.membership)
    n = normal[seg.ray]
    fa = dot3(seg.origin, n) - offset[seg.ray]
    fu = dot3(seg.direction, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = np.where(fu > 0, -fa / fu, np.inf)
    allowed = np.where(fa > 0, 0.0, np.minimum(seg.length, cross))
    cut = allowed < seg.length
    # segments after a ray's first cut are not reached at all
    count = np.cumsum(cut)
    before_ray = (count - cut)[seg.offsets[:-1]]
    after = (count - cut - before_ray[seg.ray]) > 0
    length = np.where(after, 0.0, allowed)
    castable = length > 0
    if seg.castable is not None:
        castable &= seg.castable
    clipped = np.bincount(seg.ray, weights=cut, minlength=len(seg)) > 0
    return replace(seg, length=length, castable=castable, clipped=clipped)
