"""Simplified polylines for the renderer: the straight segments, ready for a BVH, of
rays whose vertices come in a common arc-length layout.

Simplification: a chord over a stretch of length L that turns by Theta in all strays
from it by at most L Theta / 4 (the worst case puts the whole turn at the middle). A
polyline keeps a vertex when the stretch since the last kept one would stray by more
than ``tol_px`` pixels, a pixel being measured where the stretch lies: the smallest
footprint of any camera's pixel there (distance to its eye times its pixel angle).
The last vertex of every bend is kept too, so the straight run after it is exact.

Pure numpy.
"""

from dataclasses import dataclass
from functools import partial

import numpy as np

from ..diagnostics import check_stop
from ..geometry import dot3
from ..runtime import runtime

# Turning below this (radians) is float32 noise of the stored vertices, not a bend.
NOISE = 1e-4
# Default simplification tolerance, pixels: chords stray from the polyline by at most
# this much, far below what a pixel shows.
DEFAULT_TOLERANCE_PX = 0.25
# Rays simplified at once (bounds the temporaries to ~100 MB at K = 128).
CHUNK = 16384
# Vertices measured at once: temporaries of a few MB stay in the caches (the demo's 38k
# rays of 418 vertices measured in 1.7 s this way, 4.8 s in chunks of CHUNK rays).
MEASURE_POINTS = 1 << 17
# Parts per worker when chunks go to worker processes (they finish together).
PARTS_PER_WORKER = 4


@dataclass(frozen=True)
class Segments:
    """Polylines of R rays as a flat list of straight segments.

    origin, direction : (S, 3) float64 (direction unit), world units.
    length : (S,) float64; a ray's last segment includes the ray's reach.
    ray : (S,) int64, the ray each segment belongs to; ``offsets`` (R+1,) int64 index
        each ray's run of segments (every ray has at least one).
    before : (S,) float64: arc length (along the chords) of the ray before the segment.
    start_depth : (R,) float64, distance from camera 1's eye to each ray's vertex 0.
    membership : (R,) float32, membership where the ray leaves the bending stretch.
    castable : (S,) bool or None: False marks a segment known to meet no geometry (the
        renderer need not cast it); None: nothing is known.
    clipped : (R,) bool or None: rays cut short at their far plane (``clipping``);
        None: not clipped.
    """

    origin: np.ndarray
    direction: np.ndarray
    length: np.ndarray
    ray: np.ndarray
    offsets: np.ndarray
    before: np.ndarray
    start_depth: np.ndarray
    membership: np.ndarray
    castable: np.ndarray = None
    clipped: np.ndarray = None

    def __len__(self):
        return len(self.offsets) - 1


def camera_footprints(cameras):
    """(eyes (N, 3) float64, angles (N,) float64): each camera's eye and the angle one
    of its pixels spans (radians per pixel, across the image's width)."""
    eyes = np.array([c.eye for c in cameras], dtype=np.float64)
    angles = np.array(
        [(c.view_plane()[1] - c.view_plane()[0]) / c.width for c in cameras], dtype=np.float64
    )
    return eyes, angles


def footprint(points, eyes, angles):
    """(...,) float64: the smallest pixel footprint of any camera at ``points`` (..., 3),
    world units."""
    p = np.asarray(points, dtype=np.float64)
    best = None
    for eye, angle in zip(eyes, angles):
        d = p - eye
        f = np.sqrt(dot3(d, d)) * angle
        best = f if best is None else np.minimum(best, f)
    return best


def box_distance(points, bounds):
    """(...,) float64 distance from ``points`` (..., 3) to the box ``bounds`` ((3,), (3,)),
    zero inside; zeros when ``bounds`` is None."""
    p = np.asarray(points, dtype=np.float64)
    if bounds is None:
        return np.zeros(p.shape[:-1])
    lo, hi = bounds
    d = np.maximum(np.maximum(lo - p, p - hi), 0.0)
    return np.sqrt(dot3(d, d))


def polyline_measures(
    vertices, eyes, angles, tol_px, bounds=None, should_stop=None, clearance=None, processes=1
):
    """Per-vertex quantities the simplification reads.

    Parameters
    ----------
    vertices : (R, K, 3) float array, world units. eyes, angles : ``camera_footprints``.
    tol_px : float, pixels. bounds : ((3,), (3,)) box holding all geometry, or None.
    should_stop : callable, consulted once per chunk of rays (raises ``Cancelled``).
    clearance : callable (..., 3) points -> (...,) float64, a lower bound of their
        distance to any geometry, world units (``Occupancy.clearance``), or None: the
        distance to ``bounds`` is used.
    processes : int, worker processes sharing the chunks of rays (``in_chunks``).

    Returns
    -------
    seglen : (R, K-1) float32, segment lengths. turn : (R, K-2) float32, the turning
        (radians) at vertices 1..K-2, float noise below ``NOISE`` zeroed.
    tol : (R, K) float32, how far a chord may stray near each vertex, world units:
        ``tol_px`` pixel footprints (``footprint``), or half the distance to the
        geometry (``clearance``, else to its box) where that is larger (a chord that
        strays less than that cannot reach geometry the polyline misses, nor miss what
        it hits).
    """
    r, k = vertices.shape[:2]
    shared = _shares(r, processes)
    seglen = _zeros((r, max(k - 1, 0)), np.float32, shared)
    turn = _zeros((r, max(k - 2, 0)), np.float32, shared)
    tol = _zeros((r, k), np.float32, shared)
    shared = shared and all(_is_shared(a) for a in (seglen, turn, tol))
    fill = partial(_measure, vertices, eyes, angles, tol_px, bounds, clearance, seglen, turn, tol)
    in_chunks(fill, r, processes if shared else 1, should_stop)
    return seglen, turn, tol


def _measure(vertices, eyes, angles, tol_px, bounds, clearance, seglen, turn, tol, rows, stop):
    """``polyline_measures`` of rays rows[0] .. rows[1] - 1, written into ``seglen``,
    ``turn`` and ``tol``."""
    k = vertices.shape[1]
    step = max(1, MEASURE_POINTS // max(k, 1))
    for a in range(rows[0], rows[1], step):
        check_stop(stop)
        b = min(a + step, rows[1])
        v = np.asarray(vertices[a:b], dtype=np.float64)
        d = v[:, 1:] - v[:, :-1]
        n = np.sqrt(dot3(d, d))
        seglen[a:b] = n
        if k >= 3:
            u = d / np.maximum(n, 1e-30)[..., None]
            t = np.arccos(np.clip(dot3(u[:, :-1], u[:, 1:]), -1.0, 1.0))
            t[t < NOISE] = 0.0
            turn[a:b] = t
        far = box_distance(v, bounds) if clearance is None else clearance(v)
        tol[a:b] = np.maximum(footprint(v, eyes, angles) * tol_px, 0.5 * far)


def in_chunks(fill, n, processes=1, should_stop=None):
    """Call ``fill((a, b), stop)`` over consecutive ranges of ``range(n)`` (at most CHUNK
    long): in worker processes when ``processes`` > 1, ``PARTS_PER_WORKER`` ranges each,
    with ``stop`` the worker's ``runtime.Context`` (``fill`` is then a picklable task
    that writes into arrays made with ``runtime().shared_array``; a range whose worker
    was given up is filled here); else in this process, with ``stop`` = ``should_stop``,
    also asked before each range (raises ``Cancelled``)."""
    size = CHUNK
    if processes > 1:
        size = min(CHUNK, max(1, -(-n // (processes * PARTS_PER_WORKER))))
    parts = [(a, min(a + size, n)) for a in range(0, n, size)]
    if processes > 1 and len(parts) > 1:
        runtime().map(fill, parts, processes, should_stop)
        return
    for part in parts:
        check_stop(should_stop)
        fill(part, should_stop)


def _shares(rows, processes):
    """Whether work over ``rows`` rays goes to worker processes (more than one chunk)."""
    return processes > 1 and rows > CHUNK


def _zeros(shape, dtype, shared):
    """Zeros, in shared memory when ``shared`` (and shared memory is to be had)."""
    if shared:
        try:
            return runtime().shared_array(shape, dtype)
        except OSError:  # no shared memory: the work stays in this process
            pass
    return np.zeros(shape, dtype)


def _is_shared(array):
    return runtime().shared.handle(array) is not None


def _keep_leaves(rows, seglen, turn, tol, last, leaf_keep, part, stop):
    """The leaf schedules of leaves part[0] .. part[1] - 1, written into ``leaf_keep``:
    the greedy pass over the largest turns and lengths, and the smallest tolerances, of
    each leaf's four corner rays (``rows``, four (L,) index arrays)."""
    corners = [c[part[0] : part[1]] for c in rows]
    lasts = [last[c] for c in corners]
    keep = greedy_keep(
        np.maximum.reduce([seglen[c] for c in corners]),
        np.maximum.reduce([turn[c] for c in corners]),
        np.minimum.reduce([tol[c] for c in corners]),
        np.maximum.reduce(lasts),
        stop,
    )
    # between the first corner's last vertex and the last one's the corners run on out
    # of step (each straight, its step following the points it passes), so a ray
    # blended from them bends there though no corner turns: every vertex is kept, and
    # the ray runs on past the last as the field's own does (``traced.straight_on``)
    slots = np.arange(keep.shape[1])
    lo, hi = np.minimum.reduce(lasts)[:, None], np.maximum.reduce(lasts)[:, None]
    keep |= (slots >= lo) & (slots <= hi)
    leaf_keep[part[0] : part[1]] = keep


def greedy_keep(seglen, turn, tol, last, should_stop=None):
    """Which vertices to keep so every chord strays by at most ``tol`` (world units).

    Parameters
    ----------
    seglen : (R, K-1), turn : (R, K-2), tol : (R, K) float arrays (``polyline_measures``,
        tol = tolerance in pixels times the footprint). last : (R,) int, the last vertex
        of each ray (kept; later ones dropped). should_stop : callable, consulted every
        16 vertices (raises ``Cancelled``).

    Returns
    -------
    keep : (R, K) bool; vertex 0, ``last`` and the last vertex of every bend kept.
    """
    r, k = tol.shape
    keep = np.zeros((r, k), dtype=bool)
    keep[:, 0] = True
    last = np.asarray(last, dtype=np.int64)
    keep[np.arange(r), last] = True
    if k >= 3:
        bending = turn > 0
        ends = bending.copy()
        ends[:, :-1] &= ~bending[:, 1:]
        keep[:, 1:-1] |= ends
        length = seglen[:, 0].astype(np.float64)
        theta = np.zeros(r)
        allowed = np.minimum(tol[:, 0], tol[:, 1]).astype(np.float64)
        for j in range(1, k - 1):
            if j % 16 == 0:
                check_stop(should_stop)
            # the chord from the anchor would now run past vertex j to j + 1
            length2 = length + seglen[:, j]
            theta2 = theta + turn[:, j - 1]
            allowed2 = np.minimum(allowed, tol[:, j + 1])
            cut = (length2 * theta2 > 4.0 * allowed2) | keep[:, j]
            keep[:, j] = cut
            length = np.where(cut, seglen[:, j], length2)
            theta = np.where(cut, 0.0, theta2)
            allowed = np.where(cut, np.minimum(tol[:, j], tol[:, j + 1]), allowed2)
    keep &= np.arange(k)[None, :] <= last[:, None]
    return keep


def simplify(vertices, last, eyes, angles, tol_px, bounds=None, clearance=None):
    """Which vertices of each polyline to keep: chords stray by at most ``tol_px``
    pixels (module docstring).

    Parameters
    ----------
    vertices : (R, K, 3) float array, world units.
    last : (R,) int, index of each ray's last vertex (kept; later vertices are dropped).
    eyes, angles : from ``camera_footprints``. tol_px : float, pixels.
    bounds : the geometry's box, or None. clearance : callable or None
        (``polyline_measures``).

    Returns
    -------
    keep : (R, K) bool; vertex 0 and ``last`` always kept.
    """
    seglen, turn, tol = polyline_measures(
        vertices, eyes, angles, tol_px, bounds, clearance=clearance
    )
    return greedy_keep(seglen, turn, tol, last)


def segments_from_points(points, ray, nrays, reach, start_depth, membership, castable=None):
    """Build ``Segments`` from kept vertices.

    points : (P, 3) float64, the kept vertices of all rays, each ray's in order.
    ray : (P,) int, sorted, the ray of each point (every ray has at least two points).
    reach : (R,) float, how far each ray's last segment runs on past its last vertex.
    castable : (P,) bool or None, per point: whether the segment starting there may meet
        geometry (see ``Segments.castable``).
    """
    j = np.flatnonzero(ray[1:] == ray[:-1])
    origin = points[j]
    vec = points[j + 1] - origin
    length = np.sqrt(dot3(vec, vec))
    direction = vec / np.where(length > 0, length, 1.0)[:, None]
    sray = ray[j]
    counts = np.bincount(sray, minlength=nrays)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    cum = np.cumsum(length)
    first = np.minimum(offsets[:-1], max(len(cum) - 1, 0))
    # arc length before each segment, restarting at every ray's first segment
    before = cum - length - np.repeat((cum - length)[first] if len(cum) else cum, counts)
    length = length.copy()
    length[offsets[1:] - 1] += np.asarray(reach, dtype=np.float64)
    return Segments(
        origin,
        direction,
        length,
        sray.astype(np.int64),
        offsets,
        before,
        np.asarray(start_depth, dtype=np.float64),
        np.asarray(membership, dtype=np.float32),
        None if castable is None else castable[j],
    )
