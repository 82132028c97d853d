"""First hit along bent rays: each ray's straight segments (``core.sampling.Segments``)
are cast in order on one BVH until one hits.

Segments that miss the scene's bounding box are culled before any cast, and the rest
are clipped to it, so a ray pays only for the stretch that can meet geometry. The loop
over casts is the only per-ray Python in the renderer: the segments are cast in waves
(every ray's first segment, then the next segment of the rays still unhit, ...), each a
list comprehension over prepared lists, checking ``should_stop`` every
``CASTS_PER_CHECK`` casts.
"""

import contextlib
import gc
from dataclasses import dataclass

import numpy as np

from ..core.bundle import RayBundle
from ..core.errors import Cancelled
from ..core.sampling import greedy_keep, polyline_measures, segments_from_points

# Segments between two calls of ``should_stop``: a few milliseconds of casting.
CASTS_PER_CHECK = 4096


@contextlib.contextmanager
def gc_paused():
    """Pause Python's cyclic garbage collector: converting arrays to lists and casting
    create millions of short-lived containers, and the collections they set off cost
    more than the casts themselves (measured: ``tolist`` of 100k x 3 floats 70 ms with
    the collector, 28 ms without). Reference counting still frees everything."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


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


def march(tree, seg, should_stop=None, bounds=None):
    """Cast every ray's segments in order on ``tree`` until one hits.

    Parameters
    ----------
    tree : mathutils.bvhtree.BVHTree in world space (anything with its ``ray_cast``),
        or None for an empty scene.
    seg : core.sampling.Segments of R rays (from ``RaySampler.segments``), or a
        RayBundle, whose polylines are then cast exactly (``bundle_segments``).
    should_stop : callable returning True to abandon the march (raises ``Cancelled``).
    bounds : ((3,), (3,)) float64 box holding every triangle (padded), or None.

    Returns
    -------
    Hits
    """
    if isinstance(seg, RayBundle):
        seg = bundle_segments(seg)
    nrays = len(seg)
    hit_seg = np.full(nrays, -1, dtype=np.int64)
    hit_tri = np.full(nrays, -1, dtype=np.int64)
    hit_dist = np.zeros(nrays)
    casts = 0
    if tree is not None and nrays:
        with gc_paused():
            lo, hi = bounds if bounds is not None else (None, None)
            inside, t0, t1 = clip_to_box(seg.origin, seg.direction, seg.length, lo, hi)
            sel = np.flatnonzero(inside)  # grouped by ray, in order along each ray
            count = np.bincount(seg.ray[sel], minlength=nrays)
            first = np.concatenate([[0], np.cumsum(count)[:-1]])
            pending = np.flatnonzero(count)
            wave = 0
            # wave j casts the j-th segment (inside the box) of every ray not hit yet, so
            # only segments that are cast get converted to Python numbers
            while len(pending):
                s = sel[first[pending] + wave]
                results = _cast_all(
                    tree.ray_cast,
                    (seg.origin[s] + seg.direction[s] * t0[s, None]).tolist(),
                    seg.direction[s].tolist(),
                    (t1[s] - t0[s]).tolist(),
                    should_stop,
                )
                casts += len(s)
                got = np.array([r[2] is not None for r in results], dtype=bool)
                if got.any():
                    rows = pending[got]
                    found = [results[i] for i in np.flatnonzero(got).tolist()]
                    hit_seg[rows] = s[got]
                    hit_tri[rows] = [r[2] for r in found]
                    hit_dist[rows] = np.array([r[3] for r in found]) + t0[s[got]]
                wave += 1
                pending = pending[~got & (count[pending] > wave)]
    hit = hit_seg >= 0
    last = seg.offsets[1:] - 1
    s = np.where(hit, hit_seg, last)
    t = np.where(hit, hit_dist, 0.0)
    location = seg.origin[s] + seg.direction[s] * t[:, None]
    distance = np.where(hit, seg.before[s] + t, np.inf)
    return Hits(hit, hit_tri, distance, location, seg.direction[s], casts)


def bundle_segments(bundle):
    """``Segments`` of a RayBundle's polylines, exact: straight runs merged, every
    bending vertex kept. Membership is taken at each ray's last vertex."""
    r, k = bundle.vertices.shape[:2]
    eyes, angles = np.zeros((1, 3)), np.zeros(1)
    seglen, turn, tol = polyline_measures(bundle.vertices, eyes, angles, 0.0)
    keep = greedy_keep(seglen, turn, tol, np.full(r, k - 1))
    rid, kid = np.nonzero(keep)
    return segments_from_points(
        bundle.vertices[rid, kid].astype(np.float64),
        rid,
        r,
        bundle.reach,
        bundle.start_depth,
        bundle.membership[:, -1],
    )


def _cast_all(cast, origins, directions, lengths, should_stop):
    """``cast`` over prepared lists, consulting ``should_stop`` every CASTS_PER_CHECK."""
    if len(origins) <= CASTS_PER_CHECK:
        if should_stop is not None and should_stop():
            raise Cancelled()
        return [cast(o, d, n) for o, d, n in zip(origins, directions, lengths)]
    out = []
    for a in range(0, len(origins), CASTS_PER_CHECK):
        if should_stop is not None and should_stop():
            raise Cancelled()
        b = a + CASTS_PER_CHECK
        out += [cast(o, d, n) for o, d, n in zip(origins[a:b], directions[a:b], lengths[a:b])]
    return out
