"""First hit along bent rays: each ray's straight segments (``core.sampling.Segments``)
are cast in order on one BVH until one hits.

Segments that miss the scene's bounding box are culled before any cast, and the rest
are clipped to it, so a ray pays only for the stretch that can meet geometry. The loop
over casts is the only per-ray Python in the renderer: one flat ``zip`` over prepared
lists, checking ``should_stop`` every ``CASTS_PER_CHECK`` segments.
"""

from dataclasses import dataclass

import numpy as np

from ..core.errors import Cancelled

# Segments between two calls of ``should_stop``: a few milliseconds of casting.
CASTS_PER_CHECK = 4096


@dataclass(frozen=True)
class Hits:
    """First hits of R rays.

    hit : (R,) bool. triangle : (R,) int64 (-1 for a miss).
    distance : (R,) float64, arc length from vertex 0 to the hit (inf for a miss).
    location : (R, 3) float64, world units. direction : (R, 3) float64, unit direction
        of the segment that holds the hit (of the last segment for a miss).
    casts : int, segment casts made.
    """

    hit: np.ndarray
    triangle: np.ndarray
    distance: np.ndarray
    location: np.ndarray
    direction: np.ndarray
    casts: int


def clip_to_box(origin, direction, length, lo, hi):
    """Slab test of segments against an axis-aligned box.

    Parameters
    ----------
    origin, direction : (S, 3) float64 (direction unit). length : (S,) float64.
    lo, hi : (3,) float64 box corners, or None for no box (nothing is culled).

    Returns
    -------
    inside : (S,) bool, whether the segment meets the box.
    t0, t1 : (S,) float64, the stretch of each segment inside the box.
    """
    n = len(origin)
    if lo is None:
        return np.ones(n, bool), np.zeros(n), np.asarray(length, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        ta = (lo - origin) * inv
        tb = (hi - origin) * inv
    near = np.minimum(ta, tb)
    far = np.maximum(ta, tb)
    # a zero direction component inside the slab gives nan: no constraint on that axis
    near = np.where(np.isnan(near), -np.inf, near)
    far = np.where(np.isnan(far), np.inf, far)
    t0 = np.maximum(near.max(axis=1), 0.0)
    t1 = np.minimum(far.min(axis=1), length)
    return t0 <= t1, t0, t1


def march(tree, seg, bounds=None, should_stop=None):
    """Cast every ray's segments in order on ``tree`` until one hits.

    Parameters
    ----------
    tree : mathutils.bvhtree.BVHTree in world space (anything with its ``ray_cast``),
        or None for an empty scene.
    seg : core.sampling.Segments of R rays.
    bounds : ((3,), (3,)) float64 box holding every triangle (padded), or None.
    should_stop : callable returning True to abandon the march (raises ``Cancelled``).

    Returns
    -------
    Hits
    """
    nrays = len(seg)
    hit_seg = np.full(nrays, -1, dtype=np.int64)
    hit_tri = np.full(nrays, -1, dtype=np.int64)
    hit_dist = np.zeros(nrays)
    casts = 0
    if tree is not None and nrays:
        lo, hi = bounds if bounds is not None else (None, None)
        inside, t0, t1 = clip_to_box(seg.origin, seg.direction, seg.length, lo, hi)
        sel = np.flatnonzero(inside)
        start = seg.origin[sel] + seg.direction[sel] * t0[sel, None]
        origins = start.tolist()
        directions = seg.direction[sel].tolist()
        lengths = (t1[sel] - t0[sel]).tolist()
        rays = seg.ray[sel].tolist()
        ids = sel.tolist()
        cast = tree.ray_cast
        found_seg, found_tri, found_dist, found_ray = [], [], [], []
        done = -1
        for a in range(0, len(ids), CASTS_PER_CHECK):
            if should_stop is not None and should_stop():
                raise Cancelled()
            b = a + CASTS_PER_CHECK
            for o, d, n, r, s in zip(
                origins[a:b], directions[a:b], lengths[a:b], rays[a:b], ids[a:b]
            ):
                if r == done:
                    continue
                result = cast(o, d, n)
                if result[2] is not None:
                    done = r
                    found_ray.append(r)
                    found_seg.append(s)
                    found_tri.append(result[2])
                    found_dist.append(result[3])
        if found_ray:
            rows = np.array(found_ray)
            hit_seg[rows] = found_seg
            hit_tri[rows] = found_tri
            hit_dist[rows] = np.array(found_dist) + t0[np.array(found_seg)]
        # casts made: every culled-in segment up to and including a ray's hit
        cast_ray = seg.ray[sel]
        limit = np.where(hit_seg >= 0, hit_seg, np.iinfo(np.int64).max)[cast_ray]
        casts = int((sel <= limit).sum())
    hit = hit_seg >= 0
    last = seg.offsets[1:] - 1
    s = np.where(hit, hit_seg, last)
    t = np.where(hit, hit_dist, 0.0)
    location = seg.origin[s] + seg.direction[s] * t[:, None]
    distance = np.where(hit, seg.before[s] + t, np.inf)
    return Hits(hit, hit_tri, distance, location, seg.direction[s], casts)
