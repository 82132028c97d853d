"""Ray sampling for the renderer: sub-pixel sample positions, and simplified polylines
(straight segments ready for a BVH) for any continuous image position.

A sample at a continuous image position gets its ray by bilinear interpolation of the
polylines of the four neighbouring pixels, vertex by vertex (vertex k of every ray lies
at the same arc length, so this is what the field itself does between lattice rays).
For a traced field the interpolation goes straight to the traced lattice rays (a pixel's
ray is itself bilinear in them), and each traced ray is simplified once per field, so a
sample never materialises its full polyline.

Simplification: a chord over a stretch of length L that turns by Theta in all strays
from it by at most L Theta / 4 (the worst case puts the whole turn at the middle). A
polyline keeps a vertex when the stretch since the last kept one would stray by more
than ``tol_px`` pixels, a pixel being measured where the stretch lies: the smallest
footprint of any camera's pixel there (distance to its eye times its pixel angle).
The last vertex of every bend is kept too, so the straight run after it is exact.

Pure numpy.
"""

import math
from dataclasses import dataclass

import numpy as np

from .errors import Cancelled
from .geometry import dot3
from .parallel import STALL_SECONDS, beat, forked_map, shared_array

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
# Parts per worker when chunks go to forked workers (they finish together).
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
    processes : int, forked workers sharing the chunks of rays (``in_chunks``).

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

    step = max(1, MEASURE_POINTS // max(k, 1))

    def measure(rows, stop):
        for a in range(rows[0], rows[1], step):
            _check(stop)
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

    in_chunks(measure, r, processes if shared else 1, should_stop)
    return seglen, turn, tol


def in_chunks(fill, n, processes=1, should_stop=None):
    """Call ``fill((a, b), stop)`` over consecutive ranges of ``range(n)`` (at most CHUNK
    long): in forked workers when ``processes`` > 1, ``PARTS_PER_WORKER`` ranges each,
    with ``stop`` = ``parallel.beat`` (``fill`` then writes into arrays made with
    ``parallel.shared_array`` before the call; the parent asks ``should_stop`` while it
    waits); else, or where the work cannot be shared, in this process, with ``stop`` =
    ``should_stop``, also asked before each range (raises ``Cancelled``)."""
    size = CHUNK
    if processes > 1:
        size = min(CHUNK, max(1, -(-n // (processes * PARTS_PER_WORKER))))
    parts = [(a, min(a + size, n)) for a in range(0, n, size)]
    if processes > 1 and len(parts) > 1:

        def task(part):
            fill(part, beat)

        shared = forked_map(task, parts, processes, should_stop, STALL_SECONDS)
        if shared is not None:
            return
    for part in parts:
        _check(should_stop)
        fill(part, should_stop)


def _shares(rows, processes):
    """Whether work over ``rows`` rays goes to forked workers (more than one chunk)."""
    return processes > 1 and rows > CHUNK


def _zeros(shape, dtype, shared):
    return shared_array(shape, dtype) if shared else np.zeros(shape, dtype)


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
                _check(should_stop)
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


def _check(should_stop):
    if should_stop is not None and should_stop():
        raise Cancelled()


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


# --- sample positions ---------------------------------------------------------------


def _hash_uniform(keys):
    """(n,) float64 in [0, 1) from (n,) uint64 keys: a fixed integer hash (splitmix64), so
    a sample's jitter depends only on its pixel, sample number and seed."""
    with np.errstate(over="ignore"):
        z = keys.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def blackman_harris_inverse(width, n=1024):
    """(grid (n,), offsets (n,)): the inverse CDF of Blackman-Harris over [-width/2,
    width/2], the pixel filter Cycles samples by default; interpolate with np.interp."""
    x = np.linspace(0.0, 1.0, 4 * n)
    w = (
        0.35875
        - 0.48829 * np.cos(2 * math.pi * x)
        + 0.14128 * np.cos(4 * math.pi * x)
        - 0.01168 * np.cos(6 * math.pi * x)
    )
    cdf = np.concatenate([[0.0], np.cumsum((w[1:] + w[:-1]) * 0.5)])
    cdf /= cdf[-1]
    return cdf, (x - 0.5) * width


def sample_offsets(ix, iy, samples, filter_width=1.5, seed=0):
    """Sub-pixel sample offsets from each pixel's centre.

    Stratified: sample s of a pixel falls in cell s of a ceil(sqrt(S))-square grid over
    the unit square (cells reused when S is not a square), jittered within it, then
    mapped per axis through the Blackman-Harris inverse CDF of ``filter_width`` pixels
    (Blender's pixel filter size), so the plain average of the samples is the filtered
    pixel. With one sample the ray goes through the pixel centre.

    Parameters
    ----------
    ix, iy : (P,) int pixel indices (top-left origin). samples : int S >= 1.

    Returns
    -------
    (P, S, 2) float64, offsets in pixels from the pixel centre.
    """
    ix, iy = np.asarray(ix, dtype=np.int64), np.asarray(iy, dtype=np.int64)
    if samples <= 1:
        return np.zeros((len(ix), 1, 2))
    n = int(math.ceil(math.sqrt(samples)))
    s = np.arange(samples, dtype=np.int64)
    cx, cy = s % n, (s // n) % n
    key = ((iy[:, None] * 65536 + ix[:, None]) * 1024 + s[None, :]) * 4 + seed * 0x10000000000
    jx = _hash_uniform((key * 2).ravel()).reshape(key.shape)
    jy = _hash_uniform((key * 2 + 1).ravel()).reshape(key.shape)
    ux, uy = (cx[None, :] + jx) / n, (cy[None, :] + jy) / n
    cdf, off = blackman_harris_inverse(max(filter_width, 1e-3))
    return np.stack([np.interp(ux, cdf, off), np.interp(uy, cdf, off)], axis=-1)


# --- rays at continuous image positions ---------------------------------------------


def _start_depth(cameras, sx, sy):
    """(P,) float64: distance from camera 1's eye to its near plane through (sx, sy)."""
    c1 = cameras[0]
    return c1.clip_start / dot3(c1.directions(sx, sy), c1.forward)


def _bilinear_corners(sx, sy, width, height):
    """Corner pixels and weights of continuous positions (pixel centres at +0.5): the
    pixel centres around each position, extrapolating half a pixel at the borders."""
    px, py = np.asarray(sx) - 0.5, np.asarray(sy) - 0.5
    x0 = np.clip(np.floor(px), 0, max(width - 2, 0)).astype(np.int64)
    y0 = np.clip(np.floor(py), 0, max(height - 2, 0)).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    fx = np.where(x1 > x0, px - x0, 0.0)
    fy = np.where(y1 > y0, py - y0, 0.0)
    return (
        (x0, y0, (1 - fx) * (1 - fy)),
        (x1, y0, fx * (1 - fy)),
        (x0, y1, (1 - fx) * fy),
        (x1, y1, fx * fy),
    )


class RaySampler:
    """Simplified rays of a ``RayField`` at continuous image positions.

    Parameters
    ----------
    field : RayField. tol_px : float, simplification tolerance in pixels.
    bounds : ((3,), (3,)) float64 box holding all geometry, or None.
    should_stop : callable, consulted while the lattice is simplified (raises ``Cancelled``).
    clearance : callable, a lower bound of the distance to any geometry at points
        (``polyline_measures``), or None.
    occupied : callable (lo, hi) -> (S,) bool, False where the boxes between corners
        ``lo`` and ``hi`` ((S, 3) float64) hold no geometry (``Occupancy.any_between``),
        or None. With it (and ``bounds``), a traced field's segments that lie in empty
        space for a whole lattice leaf come out with ``Segments.castable`` False.
    processes : int, forked workers that share the lattice's simplification (the same
        result in any number).
    """

    def __init__(
        self,
        field,
        tol_px=DEFAULT_TOLERANCE_PX,
        bounds=None,
        should_stop=None,
        clearance=None,
        occupied=None,
        processes=1,
    ):
        self.field = field
        self.tol = float(tol_px)
        self.bounds = bounds
        self.clearance = clearance
        self.occupied = occupied
        self.cameras = field.rig.cameras
        self.eyes, self.angles = camera_footprints(self.cameras)
        self.size = field.rig.size
        self.reach = float(max(c.clip_end for c in self.cameras))
        traced = getattr(field, "traced", None)
        w, h = self.size
        self.lattice = traced is not None and getattr(field, "leaves", None) is not None
        self.lattice = self.lattice and w >= 2 and h >= 2
        if self.lattice:
            self._prepare_lattice(should_stop, processes)

    def _prepare_lattice(self, should_stop=None, processes=1):
        fld = self.field
        traced = fld.traced
        counts = traced.counts.astype(np.int64)
        k = traced.vertices.shape[1]
        last = np.minimum(counts, k - 1)
        seglen, turn, tol = polyline_measures(
            traced.vertices,
            self.eyes,
            self.angles,
            self.tol,
            self.bounds,
            should_stop,
            self.clearance,
            processes,
        )
        # one schedule per lattice leaf, safe for all four corners (and so for every ray
        # interpolated between them): their largest turns and lengths, smallest footprint
        idx = fld.index
        x0, y0, x1, y1 = fld.leaves.T.astype(np.int64)
        rows = [idx[y0, x0], idx[y0, x1], idx[y1, x0], idx[y1, x1]]
        shared = _shares(len(x0), processes)
        self.leaf_keep = _zeros((len(x0), k), bool, shared)

        def keep_leaves(part, stop):
            corners = [c[part[0] : part[1]] for c in rows]
            self.leaf_keep[part[0] : part[1]] = greedy_keep(
                np.maximum.reduce([seglen[c] for c in corners]),
                np.maximum.reduce([turn[c] for c in corners]),
                np.minimum.reduce([tol[c] for c in corners]),
                np.maximum.reduce([last[c] for c in corners]),
                stop,
            )

        in_chunks(keep_leaves, len(x0), processes if shared else 1, should_stop)
        # the same schedule, ragged: leaf n keeps vertices kept_k[kept_at[n]:kept_at[n + 1]]
        leaf_of_kept, self.kept_k = np.nonzero(self.leaf_keep)
        self.kept_n = np.bincount(leaf_of_kept, minlength=len(self.leaf_keep))
        self.kept_at = np.concatenate([[0], np.cumsum(self.kept_n)]).astype(np.int64)
        # every kept vertex of every leaf in bilinear form: a ray at (fx, fy) in leaf n
        # has vertex a + fx b + fy c + fx fy d at each of the leaf's kept slots; the four
        # terms of a slot lie together, (slots, 4, 3) float64, so that a ray's vertex is
        # one row gathered and one weighted sum
        k = traced.vertices.shape[1]
        flat = traced.vertices.reshape(-1, 3)
        v00, v01, v10, v11 = (
            flat[c[leaf_of_kept] * k + self.kept_k].astype(np.float64) for c in rows
        )
        self.slot_terms = np.stack([v00, v01 - v00, v10 - v00, v11 - v10 - v01 + v00], axis=1)
        self.slot_castable = self._slot_castable((v00, v01, v10, v11))
        w, h = self.size
        # the lattice leaf holding each unit square between four pixel centres
        cell_of = np.zeros((h - 1, w - 1), dtype=np.int32)
        for n, (a, b, c, d) in enumerate(fld.leaves.tolist()):
            cell_of[b : max(d, b + 1), a : max(c, a + 1)] = n
        self.cell_of = cell_of

    def _slot_castable(self, corners):
        """(slots,) bool, whether the segment from each kept slot to the next may meet
        geometry for a ray anywhere in its leaf (None when nothing is known).

        A ray inside a leaf blends the four corner rays with weights in [0, 1], so its
        segment lies in the convex hull of the corners' segments, and so in their box:
        where that box misses ``bounds`` or holds no occupied cell, no ray of the leaf
        can hit on that segment. A leaf's last segment (extended by the reach) is always
        castable."""
        if self.occupied is None or self.bounds is None:
            return None
        nslot = len(self.kept_k)
        castable = np.ones(nslot, dtype=bool)
        last = self.kept_at[1:] - 1
        seg = np.ones(nslot, dtype=bool)
        seg[last] = False  # a slot that starts no segment, or the extended last one
        seg[np.maximum(last - 1, 0)] = False
        q = np.flatnonzero(seg)
        if len(q):
            ends = np.concatenate([[c[q] for c in corners], [c[q + 1] for c in corners]])
            lo, hi = ends.min(axis=0), ends.max(axis=0)
            blo, bhi = self.bounds
            meets = (lo <= bhi).all(axis=1) & (hi >= blo).all(axis=1)
            near = np.flatnonzero(meets)
            meets[near] = self.occupied(lo[near], hi[near])
            castable[q] = meets
        return castable

    def segments(self, sx, sy, ix=None, iy=None):
        """``Segments`` of the rays through continuous positions (sx, sy) ((P,) float,
        pixel centres at +0.5). ``ix, iy`` (P,) int: the pixels they serve, when they are
        pixel centres (then the generic path casts those pixels' own rays)."""
        sx, sy = np.asarray(sx, dtype=np.float64), np.asarray(sy, dtype=np.float64)
        if self.lattice:
            return self._lattice_segments(sx, sy)
        return self._generic_segments(sx, sy, ix, iy)

    def _lattice_segments(self, sx, sy):
        fld, traced = self.field, self.field.traced
        w, h = self.size
        px, py = sx - 0.5, sy - 0.5
        cx = np.clip(np.floor(px), 0, w - 2).astype(np.int64)
        cy = np.clip(np.floor(py), 0, h - 2).astype(np.int64)
        leaf = self.cell_of[cy, cx].copy()
        # a pixel centre takes the leaf the field itself gives it (on a leaf's edge the
        # neighbouring leaf may hold an extra traced ray there)
        centre = (px == np.floor(px)) & (py == np.floor(py))
        if centre.any():
            jx = np.clip(px[centre], 0, w - 1).astype(np.int64)
            jy = np.clip(py[centre], 0, h - 1).astype(np.int64)
            leaf[centre] = fld.leaf_of[jy, jx]
        x0, y0, x1, y1 = fld.leaves[leaf].T.astype(np.int64)
        fx = (px - x0) / np.maximum(x1 - x0, 1)
        fy = (py - y0) / np.maximum(y1 - y0, 1)
        idx = fld.index
        corners = (
            (idx[y0, x0], (1 - fy) * (1 - fx)),
            (idx[y0, x1], (1 - fy) * fx),
            (idx[y1, x0], fy * (1 - fx)),
            (idx[y1, x1], fy * fx),
        )
        exit_ = np.minimum.reduce([traced.counts[row] for row, _w in corners]).astype(np.int64)
        # the kept vertices of each ray, its leaf's schedule, ray after ray
        n = self.kept_n[leaf]
        first = np.cumsum(n) - n
        rid = np.repeat(np.arange(len(sx)), n)
        slot = np.repeat(self.kept_at[leaf] - first, n)
        slot += np.arange(len(rid))
        weights = np.empty((len(rid), 4))
        weights[:, 0] = 1.0
        weights[:, 1] = fx[rid]
        weights[:, 2] = fy[rid]
        np.multiply(weights[:, 1], weights[:, 2], out=weights[:, 3])
        pts = np.einsum("nkj,nk->nj", self.slot_terms.take(slot, axis=0), weights)
        castable = None
        if self.slot_castable is not None:
            castable = self.slot_castable[slot]
            # a blend outside its leaf (half a pixel beyond the image's border centres)
            # leaves the corners' hull: all its segments are cast
            outside = (fx < 0) | (fx > 1) | (fy < 0) | (fy > 1)
            if outside.any():
                castable |= outside[rid]
        leave = np.clip(exit_ - 1, 0, traced.membership.shape[1] - 1)
        membership = sum(traced.membership[row, leave] * wgt for row, wgt in corners)
        return segments_from_points(
            pts,
            rid,
            len(sx),
            np.full(len(sx), self.reach),
            _start_depth(self.cameras, sx, sy),
            membership,
            castable,
        )

    def _generic_segments(self, sx, sy, ix=None, iy=None):
        fld = self.field
        w, h = self.size
        if ix is not None:
            bundle = fld.rays(np.asarray(ix), np.asarray(iy))
            leave = fld.exit_index(np.asarray(ix), np.asarray(iy))
            verts = bundle.vertices
        else:
            corners = _bilinear_corners(sx, sy, w, h)
            keys = np.concatenate([y * w + x for x, y, _ in corners])
            uniq, inv = np.unique(keys, return_inverse=True)
            ub = fld.rays(uniq % w, uniq // w)
            ul = fld.exit_index(uniq % w, uniq // w)
            inv = inv.reshape(4, len(sx))
            verts = sum(
                ub.vertices[inv[c]].astype(np.float64) * corners[c][2][:, None, None]
                for c in range(4)
            )
            leave = None if ul is None else np.min([ul[inv[c]] for c in range(4)], axis=0)
            bundle = ub
        k = verts.shape[1]
        mem_rows = bundle.membership if ix is not None else None
        if leave is None:
            leave = np.full(len(sx), k - 1)
        leave = np.clip(leave, 0, k - 1)
        if mem_rows is not None:
            membership = mem_rows[np.arange(len(sx)), leave]
        else:
            membership = sum(ub.membership[inv[c], leave] * corners[c][2] for c in range(4))
        keep = simplify(
            verts,
            np.full(len(sx), k - 1),
            self.eyes,
            self.angles,
            self.tol,
            self.bounds,
            self.clearance,
        )
        rid, kid = np.nonzero(keep)
        pts = np.asarray(verts[rid, kid], dtype=np.float64)
        return segments_from_points(
            pts,
            rid,
            len(sx),
            np.full(len(sx), self.reach),
            _start_depth(self.cameras, sx, sy),
            membership,
        )
