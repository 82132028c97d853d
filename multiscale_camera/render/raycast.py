"""First hit along bent rays: each polyline's segments are cast in order on one BVH.

Polylines are simplified first: straight runs (collinear vertices) become one segment,
so a ray that does not bend costs one cast, and a bend keeps a vertex each time its
accumulated turning grows by a fraction of its whole turn. The bending stretch holds no
geometry in a well-made rig, and beyond it the rays run straight, so what a pixel shows
is untouched. The loop over casts is the only per-ray Python in the renderer;
everything around it is numpy.
"""

from dataclasses import dataclass

import numpy as np

from ..core.errors import Cancelled

# Turning below this (radians) is float32 noise of the stored vertices, not a bend.
NOISE = 1e-4
# A bent ray keeps a vertex each time its accumulated turning grows by 1/BEND_SEGMENTS of
# its whole turn (a guide is then followed within about 1% of its length), or by
# MIN_QUANTUM radians for a ray that hardly turns (its chords then stray by at most
# MIN_QUANTUM / 8 of their length, 2.5e-4).
BEND_SEGMENTS = 16
MIN_QUANTUM = 2e-3
# How many rays between two calls of ``should_stop``: a fraction of a second of work.
RAYS_PER_CHECK = 2048


@dataclass(frozen=True)
class Segments:
    """The bundle's polylines as a flat list of straight segments.

    origin, direction : (S, 3) float64 (direction unit), world units.
    length : (S,) float64; a ray's last segment includes the bundle's reach.
    ray : (S,) int64, the ray each segment belongs to; ``offsets`` (R+1,) int64 index
        each ray's run of segments. ``before`` (S,) float64: arc length of the ray
        before the segment.
    """

    origin: np.ndarray
    direction: np.ndarray
    length: np.ndarray
    ray: np.ndarray
    offsets: np.ndarray
    before: np.ndarray


def polyline_segments(bundle):
    """Flatten a ``RayBundle`` into merged straight segments (``Segments``)."""
    v = bundle.vertices.astype(np.float64)
    r, k = v.shape[:2]
    d = np.diff(v, axis=1)
    n = np.linalg.norm(d, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = d / n[..., None]
    turn = np.arccos(np.clip(np.nan_to_num((u[:, :-1] * u[:, 1:]).sum(-1), nan=1.0), -1.0, 1.0))
    total = np.cumsum(turn, axis=1)
    quantum = np.maximum(total[:, -1:] / BEND_SEGMENTS, MIN_QUANTUM)
    band = np.floor(total / quantum)
    keep = np.ones((r, k), dtype=bool)
    # keep the vertex where the accumulated turning enters a new band, and the last
    # vertex of every bend, so the straight run after it starts exactly there
    entered = np.diff(band, axis=1, prepend=0) > 0
    bending = turn > NOISE
    ends = bending & np.append(~bending[:, 1:], np.ones((r, 1), bool), axis=1)
    keep[:, 1:-1] = entered | ends
    rid, kid = np.nonzero(keep)
    pts = v[rid, kid]
    same = rid[1:] == rid[:-1]
    origin = pts[:-1][same]
    vec = pts[1:][same] - origin
    length = np.linalg.norm(vec, axis=-1)
    direction = vec / np.where(length > 0, length, 1.0)[:, None]
    ray = rid[:-1][same]
    counts = np.bincount(ray, minlength=r)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    cum = np.cumsum(length)
    before = cum - length - np.repeat(cum[offsets[:-1]] - length[offsets[:-1]], counts)
    length = length.copy()
    length[offsets[1:] - 1] += bundle.reach
    return Segments(origin, direction, length, ray, offsets, before)


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


def march(tree, bundle, should_stop=None):
    """Cast every ray's segments in order on ``tree`` (a mathutils BVHTree) until one hits.

    Parameters
    ----------
    tree : mathutils.bvhtree.BVHTree in world space, or None for an empty scene.
    bundle : RayBundle of R rays.
    should_stop : callable returning True to abandon the march (raises ``Cancelled``).

    Returns
    -------
    Hits
    """
    seg = polyline_segments(bundle)
    nrays = len(bundle)
    hit_seg = np.full(nrays, -1, dtype=np.int64)
    hit_tri = np.full(nrays, -1, dtype=np.int64)
    hit_dist = np.zeros(nrays)
    casts = 0
    if tree is not None and nrays:
        origin, direction, length = seg.origin.tolist(), seg.direction.tolist(), seg.length.tolist()
        offsets = seg.offsets.tolist()
        cast = tree.ray_cast
        found_seg, found_tri, found_dist, found_ray = [], [], [], []
        for start in range(0, nrays, RAYS_PER_CHECK):
            if should_stop is not None and should_stop():
                raise Cancelled()
            stop = min(start + RAYS_PER_CHECK, nrays)
            casts += offsets[stop] - offsets[start]
            for r in range(start, stop):
                for s in range(offsets[r], offsets[r + 1]):
                    _loc, _nor, index, dist = cast(origin[s], direction[s], length[s])
                    if index is not None:
                        found_ray.append(r)
                        found_seg.append(s)
                        found_tri.append(index)
                        found_dist.append(dist)
                        casts -= offsets[r + 1] - s - 1
                        break
        if found_ray:
            rows = np.array(found_ray)
            hit_seg[rows] = found_seg
            hit_tri[rows] = found_tri
            hit_dist[rows] = found_dist
    else:
        casts = 0
    hit = hit_seg >= 0
    last = seg.offsets[1:] - 1
    s = np.where(hit, hit_seg, last)
    t = np.where(hit, hit_dist, 0.0)
    location = seg.origin[s] + seg.direction[s] * t[:, None]
    distance = np.where(hit, seg.before[s] + t, np.inf)
    return Hits(hit, hit_tri, distance, location, seg.direction[s], casts)
