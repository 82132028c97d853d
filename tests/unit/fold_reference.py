"""The fold counter as it was before it was made fast (every section in (P, K, 3) rows,
the walk's start by one searchsorted): the slow reference the fast ``quad_folds`` must
equal, quad for quad. Kept as it was, not imported from the package."""

import numpy as np

from multiscale_camera.core.geometry import cross3, dot3

# Corner triangles of a quad a, b, c, d (indices into its four section points).
TRIANGLES = ((0, 1, 2), (1, 2, 3), (2, 3, 0), (3, 0, 1))


def _unit_tangents(a):
    """(..., K, 3) float64 unit directions of polylines ``a`` at their vertices: central
    differences, one-sided at the ends (zero where a polyline stands still)."""
    t = np.empty_like(a)
    t[..., 1:-1, :] = a[..., 2:, :] - a[..., :-2, :]
    t[..., 0, :] = a[..., 1, :] - a[..., 0, :]
    t[..., -1, :] = a[..., -1, :] - a[..., -2, :]
    n = np.sqrt(dot3(t, t))
    return t / np.where(n > 0, n, 1.0)[..., None]


def _arc_lengths(v):
    """(..., K) float64: arc length along polylines ``v`` (..., K, 3) at their vertices."""
    d = np.diff(v, axis=-2)
    seg = np.sqrt(dot3(d, d))
    return np.concatenate([np.zeros(seg.shape[:-1] + (1,)), np.cumsum(seg, axis=-1)], axis=-1)


def _segment_at(cum, length):
    """(P, M) int: for polylines of arc lengths ``cum`` (P, K), the segment holding each
    of the arc lengths ``length`` (P, M) (clamped to the polyline), one searchsorted for
    all: every polyline's lengths are offset to follow the one before."""
    p, k = cum.shape
    span = float(max(cum[:, -1].max(initial=0.0), length.max(initial=0.0))) + 1.0
    offset = span * np.arange(p)[:, None]
    want = np.clip(length, 0.0, cum[:, -1:]) + offset
    idx = np.searchsorted((cum + offset).ravel(), want.ravel(), side="right").reshape(want.shape)
    return np.clip(idx - 1 - np.arange(p)[:, None] * k, 0, k - 2)


def reference_section_points(q, origin, normal, start):
    """Where polylines ``q`` cross planes, near a starting segment.

    Parameters
    ----------
    q : (P, K, 3) float64 polylines, K >= 2. origin, normal : (P, M, 3) float64: M
        planes per polyline, through ``origin`` with unit ``normal``.
    start : (P, M) int, the segment to start the search from.

    Returns
    -------
    point : (P, M, 3) float64, the crossing relative to ``origin``: on the nearest
        segment, walking from ``start``, whose ends are on either side of the plane (the
        first or last segment extended when the polyline ends before the plane).
    index : (P, M) int, that segment's first vertex.
    """
    p, k = q.shape[:2]
    m = start.shape[1]
    rows = np.broadcast_to(np.arange(p)[:, None], (p, m))
    j = np.clip(start, 0, k - 2).astype(np.int64)

    def side(r, jj, o, n):
        return dot3(q[r, jj] - o, n)

    s0 = side(rows, j, origin, normal)
    s1 = side(rows, j + 1, origin, normal)
    need = np.flatnonzero(
        ((s0 > 0) & (s1 > 0) & (j > 0)).ravel() | ((s0 < 0) & (s1 < 0) & (j < k - 2)).ravel()
    )
    flat_j, flat_s0, flat_s1 = j.ravel(), s0.ravel(), s1.ravel()
    flat_rows = rows.ravel()
    o, n = origin.reshape(-1, 3), normal.reshape(-1, 3)
    while len(need):
        step = np.where(flat_s0[need] > 0, -1, 1)
        flat_j[need] += step
        jj, rr = flat_j[need], flat_rows[need]
        flat_s0[need] = side(rr, jj, o[need], n[need])
        flat_s1[need] = side(rr, jj + 1, o[need], n[need])
        a, b, jn = flat_s0[need], flat_s1[need], flat_j[need]
        still = ((a > 0) & (b > 0) & (jn > 0)) | ((a < 0) & (b < 0) & (jn < k - 2))
        # a walk never turns back: stop where it would (a polyline that doubles back)
        still &= np.where(step < 0, a > 0, b < 0)
        need = need[still]
    j = flat_j.reshape(p, m)
    s0, s1 = flat_s0.reshape(p, m), flat_s1.reshape(p, m)
    den = s0 - s1
    w = np.where(den != 0, s0 / np.where(den != 0, den, 1.0), 0.0)
    qa, qb = q[rows, j], q[rows, j + 1]
    return (qa - origin) + (qb - qa) * w[..., None], j


def reference_quad_folds(vertices, active, limit=None):
    """Quads of neighbouring rays that fold in the bending stretch (module docstring).

    Parameters
    ----------
    vertices : (Hy, Wx, K, 3) float array, K >= 2: rays on a pixel lattice, world units.
    active : (Hy, Wx, K) bool: whether vertex k is inside the bending stretch.
    limit : (Hy - 1, Wx - 1) int or None: only each quad's sections k < limit count.

    Returns
    -------
    (Hy - 1, Wx - 1) bool: True where a corner triangle's orientation in some section
    inside the bending stretch differs from its orientation in the first section.
    """
    hy, wx, k = vertices.shape[:3]
    if hy < 2 or wx < 2:
        return np.zeros((max(hy - 1, 0), max(wx - 1, 0)), dtype=bool)
    v = vertices.astype(np.float64)
    cum = _arc_lengths(v)
    corners = (
        (slice(None, -1), slice(None, -1)),
        (slice(None, -1), slice(1, None)),
        (slice(1, None), slice(1, None)),
        (slice(1, None), slice(None, -1)),
    )
    p = (hy - 1) * (wx - 1)
    a = v[corners[0]].reshape(p, k, 3)
    normal = _unit_tangents(a)
    ref = cum[corners[0]].reshape(p, k)
    points = [np.zeros_like(a)]
    live = active[corners[0]].reshape(p, k).copy()
    if limit is not None:
        live &= np.arange(k) < np.asarray(limit).reshape(p, 1)
    for sl in corners[1:]:
        q = v[sl].reshape(p, k, 3)
        qc = cum[sl].reshape(p, k)
        # the search starts at the segment of q at a's arc length
        start = _segment_at(qc, ref)
        pt, j = reference_section_points(q, a, normal, start)
        points.append(pt)
        live &= np.take_along_axis(active[sl].reshape(p, k), j, axis=1)
    orient = np.stack(
        [
            np.sign(dot3(cross3(points[y] - points[x], points[z] - points[x]), normal))
            for x, y, z in TRIANGLES
        ],
        axis=-1,
    )
    first = orient[:, :1]
    flipped = (orient != first) & (orient != 0) & (first != 0) & live[..., None]
    return flipped.any(axis=(1, 2)).reshape(hy - 1, wx - 1)
