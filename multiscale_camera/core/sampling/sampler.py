"""Ray sampling for the renderer: sub-pixel sample positions, and simplified polylines
(``simplification``) for any continuous image position.

A sample at a continuous image position gets its ray by bilinear interpolation of the
polylines of the four neighbouring pixels, vertex by vertex (vertex k of every ray lies
at the same arc length, so this is what the field itself does between lattice rays).
For a traced field the interpolation goes straight to the traced lattice rays (a pixel's
ray is itself bilinear in them), and each traced ray is simplified once per field, so a
sample never materialises its full polyline. A field without a traced lattice can have
every pixel's ray taken and simplified once, as a lattice of unit squares
(``PixelRays``), for pictures that sample it between its pixels.

Pure numpy.
"""

import math
from functools import partial

import numpy as np

from ..diagnostics import check_stop
from ..geometry import dot3
from .clipping import clip_far, reach_to_far_planes
from .simplification import (
    CHUNK,
    DEFAULT_TOLERANCE_PX,
    _is_shared,
    _keep_leaves,
    _shares,
    _zeros,
    camera_footprints,
    in_chunks,
    polyline_measures,
    segments_from_points,
    simplify,
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


class PixelRays:
    """Every pixel's ray of a field without a traced lattice (IMAGE_BLEND, LINEAR), laid
    out as a traced field's lattice (``TracedField``): each pixel a lattice ray, each
    unit square between four pixel centres a leaf. A ray between pixel centres is the
    bilinear blend of its square's four corner rays, as the generic path blends them,
    so ``RaySampler`` can simplify these rays once per field (a schedule per square)
    instead of simplifying every sample's own blend.

    Attributes (those of ``TracedField`` that ``RaySampler`` reads)
    ----------
    traced : self. vertices : (H*W, K, 3) float32, world units, pixel (x, y) at row
        y*W + x. membership : (H*W, K) float32. counts : (H*W,) int64, all K (no ray
        leaves a modelled volume early).
    index : (H, W) int64, each pixel's row. leaves : (L, 4) int32 (x0, y0, x1, y1),
        L = (H-1)(W-1), square (x, y) at leaf y*(W-1) + x. leaf_of : (H, W) int64, the
        square a pixel centre takes (the last row and column take the squares before
        them). cell_of : (H-1, W-1) int64, the leaf of each square.
    """

    def __init__(self, field, should_stop=None):
        w, h = field.rig.size
        n = w * h
        iy, ix = np.divmod(np.arange(n, dtype=np.int64), w)
        for a in range(0, n, CHUNK):
            check_stop(should_stop)
            b = min(a + CHUNK, n)
            bundle = field.rays(ix[a:b], iy[a:b])
            if a == 0:
                k = bundle.vertices.shape[1]
                self.vertices = np.empty((n, k, 3), dtype=np.float32)
                self.membership = np.empty((n, k), dtype=np.float32)
            self.vertices[a:b] = bundle.vertices
            self.membership[a:b] = bundle.membership
        self.counts = np.full(n, self.vertices.shape[1], dtype=np.int64)
        self.traced = self
        self.index = np.arange(n, dtype=np.int64).reshape(h, w)
        sy, sx = np.divmod(np.arange((h - 1) * (w - 1), dtype=np.int64), w - 1)
        self.leaves = np.stack([sx, sy, sx + 1, sy + 1], axis=1).astype(np.int32)
        self.cell_of = np.arange(len(sx), dtype=np.int64).reshape(h - 1, w - 1)
        cy = np.minimum(np.arange(h), h - 2)[:, None]
        cx = np.minimum(np.arange(w), w - 2)[None, :]
        self.leaf_of = cy * (w - 1) + cx

    @staticmethod
    def suits(field):
        """Whether ``field``'s rays can be laid out so: no traced lattice of its own, at
        least 2 x 2 pixels, and no ray that leaves a modelled volume early
        (``exit_index`` None), so that every ray keeps all its vertices."""
        w, h = field.rig.size
        if getattr(field, "traced", None) is not None or w < 2 or h < 2:
            return False
        return field.exit_index(np.zeros(1, np.int64), np.zeros(1, np.int64)) is None


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
    processes : int, worker processes that share the lattice's simplification (the same
        result in any number).
    pixel_rays : bool, for a field without a traced lattice: take every pixel's ray once
        (``PixelRays``, H*W*K*12 bytes) and simplify them once, so that samples between
        pixel centres gather their kept vertices (within the same tolerance) rather
        than being blended and simplified one by one. For a small picture that samples
        between a field's pixels (the live picture), not for a full render's.
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
        pixel_rays=False,
    ):
        self.field = field
        self.tol = float(tol_px)
        self.bounds = bounds
        self.clearance = clearance
        self.occupied = occupied
        self.cameras = field.rig.cameras
        self.eyes, self.angles = camera_footprints(self.cameras)
        self.size = field.rig.size
        self.reach = reach_to_far_planes(self.cameras)
        traced = getattr(field, "traced", None)
        w, h = self.size
        # the lattice the samples gather from: the field's own, or every pixel's ray
        self.source = field
        if pixel_rays and PixelRays.suits(field):
            self.source = PixelRays(field, should_stop)
        traced = self.source.traced if self.source is not field else traced
        self.lattice = traced is not None and getattr(self.source, "leaves", None) is not None
        self.lattice = self.lattice and w >= 2 and h >= 2
        if self.lattice:
            self._prepare_lattice(should_stop, processes)

    def _prepare_lattice(self, should_stop=None, processes=1):
        fld = self.source
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
        shared = shared and _is_shared(self.leaf_keep)
        keep = partial(_keep_leaves, rows, seglen, turn, tol, last, self.leaf_keep)
        in_chunks(keep, len(x0), processes if shared else 1, should_stop)
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
        cell_of = getattr(fld, "cell_of", None)
        if cell_of is None:
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

    def segments(self, sx, sy, ix=None, iy=None, clip=True):
        """``Segments`` of the rays through continuous positions (sx, sy) ((P,) float,
        pixel centres at +0.5). ``ix, iy`` (P,) int: the pixels they serve, when they are
        pixel centres (then the generic path casts those pixels' own rays). With
        ``clip`` each ray ends at its far plane, the cameras' ``clip_end`` blended as
        its rays are (``clipping.clip_far``); without, it runs ``reach`` past its last
        vertex."""
        sx, sy = np.asarray(sx, dtype=np.float64), np.asarray(sy, dtype=np.float64)
        if self.lattice:
            seg = self._lattice_segments(sx, sy)
        else:
            seg = self._generic_segments(sx, sy, ix, iy)
        return clip_far(seg, self.cameras) if clip else seg

    def _lattice_segments(self, sx, sy):
        fld, traced = self.source, self.source.traced
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
