"""Which cells of a coarse grid over the scene's box hold geometry, so the renderer can
skip, before any cast, a segment that crosses empty cells only.

Every triangle marks the cells its bounding box (padded) overlaps; a summed-area table
over the marks answers "is any cell in this block of cells marked?" in eight lookups.
A segment is tested through the block of cells spanned by its two ends: a superset of
the cells it crosses, so the test is conservative (a segment that meets a triangle
always passes; one through empty space may pass too, and is then cast as before).
``Occupancy.clearance`` bounds from below how far a point is from any triangle, which
lets the ray simplification straighten a polyline more where nothing is near.

Pure numpy.
"""

import hashlib

import numpy as np

from ..geometry import dot3

# Cells along the longest side of the box: fine enough that a bending stretch of short
# segments above a ground plane finds its cells empty, coarse enough to build in a blink.
CELLS = 64
# How far (in cells) ``Occupancy.clearance`` looks for the nearest occupied cell.
MAX_STEPS = 16


class Occupancy:
    """Occupied cells of a grid over the box ``lo .. hi``.

    Parameters
    ----------
    vertices : (V, 3) float array, world units. triangles : (T, 3) int, vertex indices.
    lo, hi : (3,) float64, a box holding every triangle (world units).
    cells : int, cells along the box's longest side (the others in proportion, >= 1).
    pad : float, world units each triangle's box grows by (covers float32 rounding in
        the BVH that reports the hits).

    Attributes
    ----------
    shape : (3,) int64 cells per axis. size : (3,) float64 cell size, world units.
    occupied : (nx, ny, nz) bool.
    """

    def __init__(self, vertices, triangles, lo, hi, cells=CELLS, pad=0.0):
        self.lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        extent = np.maximum(hi - self.lo, 1e-12)
        n = np.maximum(np.ceil(cells * extent / extent.max()), 1).astype(np.int64)
        self.shape = n
        self.size = extent / n
        count = np.zeros(tuple(n + 1), dtype=np.int64)
        tri = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles, dtype=np.int64)]
        if len(tri):
            a = self.cell_of(tri.min(axis=1) - pad)
            b = self.cell_of(tri.max(axis=1) + pad) + 1
            # +1 / -1 at the corners of each triangle's block of cells; the running sums
            # along the three axes then count the blocks over each cell
            for corner in range(8):
                pick = [(b if corner >> axis & 1 else a)[:, axis] for axis in range(3)]
                sign = 1 - 2 * (bin(corner).count("1") % 2)
                np.add.at(count, tuple(pick), sign)
            count = count.cumsum(0).cumsum(1).cumsum(2)
        self.occupied = count[: n[0], : n[1], : n[2]] > 0
        table = np.zeros(tuple(n + 1), dtype=np.int64)
        table[1:, 1:, 1:] = self.occupied.cumsum(0).cumsum(1).cumsum(2)
        self._table = table
        self._flat = table.ravel()
        self._strides = np.array(table.strides, dtype=np.int64) // table.itemsize

    def cell_of(self, points):
        """(..., 3) int64 cell of each point (..., 3), clamped to the grid."""
        c = (np.asarray(points, dtype=np.float64) - self.lo) / self.size
        # clamped first, truncation is the floor
        return np.clip(c, 0, self.shape - 1, out=c).astype(np.int64)

    def any_between(self, p0, p1):
        """(S,) bool: whether any occupied cell lies in the block of cells spanned by
        ``p0`` and ``p1`` ((S, 3) float, world units): False means the straight segment
        between them crosses empty cells only."""
        c0, c1 = self.cell_of(p0), self.cell_of(p1)
        # the block's corners as flat offsets into the summed-area table, axis by axis
        stride = self._strides
        a = np.minimum(c0, c1) * stride
        b = np.maximum(c0, c1, out=c1)
        b += 1
        b *= stride
        ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
        bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
        t = self._flat
        byz, ayz, bay, aby = by + bz, ay + az, ay + bz, by + az
        total = t[bx + byz] - t[ax + byz] - t[bx + bay] - t[bx + aby]
        total += t[ax + bay] + t[ax + aby] + t[bx + ayz] - t[ax + ayz]
        return total > 0

    def clearance(self, points):
        """(...,) float64, world units: a lower bound of the distance from ``points``
        (..., 3) to any occupied cell (so to any triangle): the distance to the box for a
        point outside it, and for the cell holding (or nearest to) the point, one cell
        less than the Chebyshev distance in cells to the nearest occupied cell (up to
        ``MAX_STEPS``)."""
        p = np.asarray(points, dtype=np.float64)
        hi = self.lo + self.size * self.shape
        d = np.maximum(np.maximum(self.lo - p, p - hi), 0.0)
        outside = np.sqrt(dot3(d, d))
        steps = self._steps()[tuple(np.moveaxis(self.cell_of(p), -1, 0))]
        return np.maximum(outside, np.maximum(steps - 1, 0) * self.size.min())

    def _steps(self):
        """(nx, ny, nz) int64: Chebyshev distance in cells to the nearest occupied cell,
        ``MAX_STEPS`` where none is that near (or none is occupied)."""
        if getattr(self, "_steps_cache", None) is None:
            steps = np.full(self.occupied.shape, MAX_STEPS, dtype=np.int64)
            front = self.occupied.copy()
            for k in range(MAX_STEPS):
                steps[front & (steps == MAX_STEPS)] = k
                grown = front.copy()  # one step of dilation by the 3 x 3 x 3 cube
                for axis in range(3):
                    lo = [slice(None)] * 3
                    hi = [slice(None)] * 3
                    lo[axis], hi[axis] = slice(None, -1), slice(1, None)
                    shifted = grown.copy()
                    shifted[tuple(lo)] |= grown[tuple(hi)]
                    shifted[tuple(hi)] |= grown[tuple(lo)]
                    grown = shifted
                front = grown
            self._steps_cache = steps
        return self._steps_cache

    def digest(self):
        """str, a digest of the occupied cells and the grid (for caches keyed on them)."""
        h = hashlib.sha1(np.packbits(self.occupied).tobytes())
        h.update(np.concatenate([self.lo, self.size]).tobytes())
        return h.hexdigest()
