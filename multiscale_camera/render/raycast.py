"""First hit along bent rays: each ray's straight segments (``core.sampling.Segments``)
are cast in order on one BVH until one hits.

Segments that miss the scene's bounding box are culled before any cast, and the rest
are clipped to it, so a ray pays only for the stretch that can meet geometry; with an
occupancy grid (``core.sampling.Occupancy``) a stretch that crosses empty cells only is
culled too. The loop over casts is the only per-ray Python in the renderer: the
segments are cast in waves (every ray's first segment, then the next segment of the
rays still unhit, ...), each a ``map`` of ``ray_cast`` over prepared lists that keeps
only the hit triangle's index (the distance is solved in numpy on that triangle),
checking ``should_stop`` every ``CASTS_PER_CHECK`` casts.
"""

import contextlib
import gc
from dataclasses import dataclass
from itertools import islice
from operator import itemgetter

import numpy as np

from ..core.diagnostics import check_stop
from ..core.geometry import RayBundle, dot3
from ..core.sampling import greedy_keep, polyline_measures, segments_from_points

# Segments between two calls of ``should_stop``: a few milliseconds of casting.
CASTS_PER_CHECK = 4096
# What a cast keeps of ``ray_cast``'s (location, normal, index, distance).
HIT_INDEX = itemgetter(2)
INDEX_AND_DISTANCE = itemgetter(2, 3)


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
    # a zero direction component counts as a tiny positive one: no NaN from 0 * inf, and
    # the slab then constrains nothing unless the origin lies outside it
    inv = 1.0 / np.where(direction == 0.0, 1e-300, direction)
    with np.errstate(over="ignore"):
        ta = (lo - origin) * inv
        tb = (hi - origin) * inv
    near = np.minimum(ta, tb)
    far = np.maximum(ta, tb, out=tb)
    # column by column: a reduction over an axis of 3 costs several times more
    t0 = np.maximum(np.maximum(near[:, 0], near[:, 1]), np.maximum(near[:, 2], 0.0))
    t1 = np.minimum(np.minimum(far[:, 0], far[:, 1]), np.minimum(far[:, 2], length))
    return t0 <= t1, t0, t1


def march(tree, seg, should_stop=None, bounds=None, geometry=None, occupancy=None):
    """Cast every ray's segments in order on ``tree`` until one hits.

    Parameters
    ----------
    tree : mathutils.bvhtree.BVHTree in world space (anything with its ``ray_cast``),
        or None for an empty scene.
    seg : core.sampling.Segments of R rays (from ``RaySampler.segments``), or a
        RayBundle, whose polylines are then cast exactly (``bundle_segments``).
    should_stop : callable returning True to abandon the march (raises ``Cancelled``).
    bounds : ((3,), (3,)) float64 box holding every triangle (padded), or None.
    geometry : the triangles ``tree`` was built from (``vertices`` (V, 3) float64 and
        ``triangles`` (T, 3) int, as SceneGeometry has them), or None. With them a cast
        keeps only the index of the triangle it hits and the distance is solved here
        (``plane_distance``), which is cheaper than keeping ``ray_cast``'s whole answer.
    occupancy : core.sampling.Occupancy of the same triangles, or None: segments whose
        stretch in the box crosses empty cells only are skipped. Segments that ``seg``
        marks not castable (``Segments.castable``) are skipped before any test.

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
            # the segments that can meet geometry, grouped by ray, in order along each
            # ray, each as the stretch start + direction * [0, length] inside the box
            if getattr(seg, "castable", None) is not None:
                cand = np.flatnonzero(seg.castable)
                inside, t0, t1 = clip_to_box(
                    seg.origin[cand], seg.direction[cand], seg.length[cand], lo, hi
                )
                sel = cand[inside]
                t0, t1 = t0[inside], t1[inside]
            else:
                inside, t0, t1 = clip_to_box(seg.origin, seg.direction, seg.length, lo, hi)
                sel = np.flatnonzero(inside)
                t0, t1 = t0[sel], t1[sel]
            direction = seg.direction[sel]
            start = seg.origin[sel] + direction * t0[:, None]
            length = t1 - t0
            if occupancy is not None:
                keep = occupancy.any_between(start, start + direction * length[:, None])
                if not keep.all():
                    sel, direction, t0, start, length = (
                        x[keep] for x in (sel, direction, t0, start, length)
                    )
            count = np.bincount(seg.ray[sel], minlength=nrays)
            first = np.cumsum(count) - count
            pending = np.flatnonzero(count)
            planes = None if geometry is None else triangle_planes(geometry)
            cast = tree.ray_cast
            wave = 0
            # wave j casts the j-th segment (inside the box) of every ray not hit yet, so
            # only segments that are cast get converted to Python numbers
            while len(pending):
                k = first[pending] + wave if wave or len(pending) < len(sel) else None
                w_start = start if k is None else start[k]
                w_dir = direction if k is None else direction[k]
                w_len = length if k is None else length[k]
                args = flat_triples(w_start), flat_triples(w_dir), w_len.tolist()
                if planes is not None:
                    tri = cast_all(cast, *args, should_stop)
                else:
                    found = cast_all(cast, *args, should_stop, INDEX_AND_DISTANCE)
                    tri = found[:, 0] if len(found) else np.zeros(0)
                casts += len(pending)
                got = tri == tri  # not NaN: a hit
                if got.any():
                    rows = pending[got]
                    gk = np.flatnonzero(got) if k is None else k[got]
                    hit_seg[rows] = sel[gk]
                    hit_tri[rows] = tri[got].astype(np.int64)
                    if planes is not None:
                        dist = plane_distance(
                            planes, hit_tri[rows], start[gk], direction[gk], length[gk]
                        )
                    else:
                        dist = found[got, 1]
                    hit_dist[rows] = dist + t0[gk]
                wave += 1
                pending = pending[~got & (count[pending] > wave)]
    hit = hit_seg >= 0
    last = seg.offsets[1:] - 1
    s = np.where(hit, hit_seg, last)
    t = np.where(hit, hit_dist, 0.0)
    location = seg.origin[s] + seg.direction[s] * t[:, None]
    distance = np.where(hit, seg.before[s] + t, np.inf)
    return Hits(hit, hit_tri, distance, location, seg.direction[s], casts)


def triangle_planes(geometry):
    """Per-triangle quantities the march and the shading reuse, computed once for a
    geometry (and kept on it).

    Parameters
    ----------
    geometry : anything with ``vertices`` (V, 3) float and ``triangles`` (T, 3) int.

    Returns
    -------
    dict of float64 arrays: ``a`` (T, 3) corner 0, world units; ``e1``, ``e2`` (T, 3)
    the edges to corners 1 and 2; ``normal`` (T, 3) their cross product (not unit);
    ``offset`` (T,) ``normal . a``.
    """
    cached = geometry.__dict__.get("_triangle_planes")
    if cached is None:
        tri = np.asarray(geometry.triangles, dtype=np.int64)
        v = np.asarray(geometry.vertices, dtype=np.float64)
        a = v[tri[:, 0]] if len(tri) else np.zeros((0, 3))
        e1 = v[tri[:, 1]] - a if len(tri) else np.zeros((0, 3))
        e2 = v[tri[:, 2]] - a if len(tri) else np.zeros((0, 3))
        normal = np.cross(e1, e2)
        cached = {"a": a, "e1": e1, "e2": e2, "normal": normal, "offset": (normal * a).sum(-1)}
        geometry.__dict__["_triangle_planes"] = cached
    return cached


def plane_distance(planes, triangles, origin, direction, length):
    """Distance along each ray to the triangle it is known to hit.

    Parameters
    ----------
    planes : ``triangle_planes`` of the geometry. triangles : (P,) int, the hit triangles.
    origin, direction : (P, 3) float64 (direction unit). length : (P,) float64, how far
        the cast reached.

    Returns
    -------
    (P,) float64 in [0, length]: where the ray meets the triangle's plane; for a ray that
    runs along the plane (no single crossing), the nearest corner's distance along it.
    """
    n = planes["normal"][triangles]
    den = dot3(direction, n)
    num = planes["offset"][triangles] - dot3(origin, n)
    crossing = np.abs(den) > 1e-9 * np.sqrt(dot3(n, n))
    t = num / np.where(crossing, den, 1.0)
    along = ~crossing
    if along.any():
        tri = triangles[along]
        a = planes["a"][tri]
        corners = np.stack([a, a + planes["e1"][tri], a + planes["e2"][tri]], axis=1)
        rel = corners - origin[along][:, None]
        t[along] = (rel * direction[along][:, None]).sum(-1).min(-1)
    return np.clip(t, 0.0, length)


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


def cast_all(cast, origins, directions, lengths, should_stop, pick=None):
    """``cast`` over prepared lists, consulting ``should_stop`` every CASTS_PER_CHECK.

    The casts run in ``map`` (no Python frame per cast) and keep only what ``pick`` takes
    of each answer (``HIT_INDEX``, the triangle index, by default), so the rest of
    ``ray_cast``'s answer is freed at once and its memory reused by the next cast.

    Parameters
    ----------
    cast : callable (origin, direction, distance) -> ``ray_cast``'s answer.
    origins, directions : iterables of n 3-sequences of floats, world units (directions
        unit); lengths : iterable of n floats. ``flat_triples`` makes the 3-sequences
        from an (n, 3) array for the cost of one flat ``tolist``.
    should_stop : callable or None.

    Returns
    -------
    (n,) float64 triangle indices, NaN for a miss (``HIT_INDEX``); or (n, k) float64
    for a ``pick`` that takes k items.
    """
    pick = HIT_INDEX if pick is None else pick
    answers = map(pick, map(cast, origins, directions, lengths))
    out = []
    while True:
        check_stop(should_stop)
        done = len(out)
        out += islice(answers, CASTS_PER_CHECK)
        if len(out) - done < CASTS_PER_CHECK:
            break
    return np.array(out, dtype=np.float64)


def flat_triples(points):
    """An iterator of 3-tuples of floats over the rows of ``points`` ((n, 3) array).

    One flat ``tolist`` makes the floats; ``zip`` over one iterator groups them in threes
    and reuses its tuple when the consumer has let go of the previous one (as ``ray_cast``
    does), so no per-row list is built: about half the cost of ``points.tolist()``."""
    it = iter(np.ravel(points).tolist())
    return zip(it, it, it)
