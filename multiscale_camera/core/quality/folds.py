"""Folds: neighbouring rays that cross, found in sections across the bundle.

A 2x2 quad of neighbouring pixels' rays a, b, c, d (pixels (y, x), (y, x+1),
(y+1, x+1), (y+1, x)) is cut by a plane across the bundle at every vertex of ray a: the
plane through that vertex normal to a's direction there (a central difference). Each
of b, c and d meets the plane where its polyline crosses it, found by walking from the
vertex at the same arc length to the segment whose ends lie on either side. In the
plane, the four points' corner triangles (a b c, b c d, c d a, d a b) have an
orientation, the sign of their area along a's direction, computed in float64 relative
to the vertex of a. The quad folds where any corner triangle's orientation differs
from the one it has in the first section (on camera 1's near plane), inside the bending
stretch. Two of the quad's rays cannot pass through one another in the sections
without a corner triangle holding both going through zero area, so every crossing
among the four rays seen at a vertex of a is counted; the four triangles keep their
orientation exactly while the four points stay the corners of a convex quadrilateral
turned as the pixels are. Equal arc length is no section: rays of different speeds
compared there flag crossings that do not exist.

Every quad of the lattice is checked, at every image size, in float64 throughout, or,
given a per-quad ``limit``, its first ``limit`` sections (``report.kept_limits``: what
provably cannot fold is not checked); the windows then follow each row's runs of quads
to check. The walk's start is the last vertex of q at or before a's arc length; section
k is settled at once where that start is segment j0 = min(k, K - 2) or j0 - 1 and the
walk stops within one step (rays of one band share their vertices' order, so this is
nearly every section); the others walk in ``section_points``. Per-ray quantities (arc
lengths, tangents, segments) are computed once per band and shared by the three roles
b, c and d, whose windows are stacked so that one numpy call serves all three;
coordinates are held as three (Hy, Wx, K) planes, the vertices around j0 are read
through slices, and the sections go in chunks of ``CHUNK_SECTIONS``, so that the
arithmetic runs over contiguous memory in a core's cache. Sides, points and areas are
the same float64 operations in the same order as ``dot3`` and ``cross3`` on (..., 3)
rows would make.
"""

import numpy as np

from ..geometry import dot3


def dot_planes(a, b):
    """Dot product of vectors held as three coordinate planes (``a``, ``b``: sequences of
    three arrays of one shape), summed in the order ``dot3`` sums contiguous rows
    (x, then z, then y: numpy's einsum), so that both give the same float64 bits."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


def _segment_at(cum, length):
    """(P, M) int: for polylines of arc lengths ``cum`` (P, K), the segment holding each
    of the arc lengths ``length`` (P, M), clamped to the polyline: the last vertex at or
    before it (the last segment from the last two vertices on)."""
    want = np.clip(length, 0.0, cum[:, -1:])
    count = (cum[:, None, :] <= want[..., None]).sum(axis=-1)
    return np.clip(count - 1, 0, cum.shape[1] - 2)


def section_points(q, origin, normal, start):
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


def quad_folds(vertices, active, limit=None):
    """Quads of neighbouring rays that fold in the bending stretch (module docstring).

    Parameters
    ----------
    vertices : (Hy, Wx, K, 3) float array, K >= 2: rays on a pixel lattice, world units.
    active : (Hy, Wx, K) bool: whether vertex k is inside the bending stretch.
    limit : (Hy - 1, Wx - 1) int or None: each quad's sections k < limit are those
        checked (0: the quad is not checked, K or None: every section). A quad's map
        entry depends on its own sections only, and a section on its four rays only,
        so a quad's sections below its limit give the bits they give without one.

    Returns
    -------
    (Hy - 1, Wx - 1) bool: True where a corner triangle's orientation in some checked
    section inside the bending stretch differs from its orientation in the first
    section.
    """
    hy, wx, k = vertices.shape[:3]
    out = np.zeros((max(hy - 1, 0), max(wx - 1, 0)), dtype=bool)
    if hy < 2 or wx < 2:
        return out
    rays = _Rays(vertices, np.asarray(active, dtype=bool))
    cols = min(wx - 1, max(1, CHUNK_SECTIONS // k))
    if limit is None:
        rows = max(1, CHUNK_SECTIONS // (k * (wx - 1)))
        for r0 in range(0, hy - 1, rows):
            for c0 in range(0, wx - 1, cols):
                window = (slice(r0, min(r0 + rows, hy - 1)), slice(c0, min(c0 + cols, wx - 1)))
                out[window] = _chunk_folds(rays, window, k, None)
        return out
    limit = np.minimum(np.asarray(limit), k)
    for r0 in range(hy - 1):
        for c0, c1, kmax in _row_windows(limit[r0], cols):
            window = (slice(r0, r0 + 1), slice(c0, c1))
            out[window] = _chunk_folds(rays, window, kmax, limit[window])
    return out


# Quads not checked between two that are, at most this many, are checked with them
# (and their result dropped): a window's fixed cost is that of about this many quads.
GAP_QUADS = 24
# A run of quads of one section limit shorter than this joins its neighbours' window.
MIN_RUN_QUADS = 96


def _row_windows(limit, cols):
    """The windows of one row of quads whose ``limit`` ((Wx - 1,) int) is not 0: a list
    of (c0, c1, kmax), columns c0 to c1 (excluded) and the largest limit among them.
    A short run (under ``MIN_RUN_QUADS``) joins the window before it where its limit is
    lower or that window is short too, a short gap (``GAP_QUADS``) joins it always: a
    window's fixed cost is paid fewer times; no window is wider than ``cols``."""
    cut = np.flatnonzero(np.diff(limit) != 0) + 1
    bounds = np.concatenate([[0], cut, [len(limit)]])
    runs = [[int(b0), int(b1), int(limit[b0])] for b0, b1 in zip(bounds[:-1], bounds[1:])]
    merged = []
    for c0, c1, lim in runs:
        last = merged[-1] if merged else None
        short = c1 - c0 < MIN_RUN_QUADS
        if lim == 0 and (last is None or c1 - c0 > GAP_QUADS):
            merged.append(None)  # nothing checked here
        elif last is not None and (
            lim == 0
            or lim == last[2]
            or (short and (lim < last[2] or last[1] - last[0] < MIN_RUN_QUADS))
        ):
            last[1], last[2] = c1, max(last[2], lim)
        else:
            merged.append([c0, c1, lim])
    out = []
    for run in merged:
        if run is None:
            continue
        for c in range(run[0], run[1], cols):
            checked = np.flatnonzero(limit[c : min(c + cols, run[1])])
            if len(checked):  # a piece starts and ends on quads to check
                c0, c1 = c + checked[0], c + checked[-1] + 1
                out.append((int(c0), int(c1), int(limit[c0:c1].max())))
    return out


class _Rays:
    """Per-ray arrays of a lattice band, computed once for a and the three roles b, c and
    d (about 13 float64 (Hy, Wx, K) planes in all): coordinates and segments (as
    ``np.diff`` makes them) as planes (3, Hy, Wx, K) and (3, Hy, Wx, K - 1); the runs
    that gather, for each section k, the vertices around its first segment j0 (segment
    k, the last one for the last vertex): jm = j0 - 1, j0, j0 + 1; arc lengths at every
    vertex and at those (inf where no such start is possible); activity at every vertex
    and at jm and j0; a's section normals (3, Hy - 1, Wx - 1, K)."""

    def __init__(self, v, active):
        k = v.shape[2]
        self.source = v
        j0 = np.minimum(np.arange(k), k - 2)
        jm = np.maximum(j0 - 1, 0)
        self.k = k
        # whether a walk may go on from segment j0 back, from it on, from j0 - 1 back
        self.inner = (j0 > 0, j0 < k - 2, j0 > 1)
        self.vertex = vertex = np.moveaxis(v, -1, 0).astype(np.float64, order="C")
        self.runs = [_runs(j) for j in (jm, j0, j0 + 1)]
        self.steps = steps = np.diff(vertex, axis=-1)  # the bits of np.diff(v, axis=-2)
        # _arc_lengths and _unit_tangents, bit for bit, on the planes
        cum = np.zeros(vertex.shape[1:])
        np.cumsum(np.sqrt(dot_planes(steps, steps)), axis=-1, out=cum[..., 1:])
        self.cum, self.end = cum, cum[..., -1:]
        # (3, Hy, Wx, K): the arc lengths at jm, j0 and j0 + 1
        self.cums = np.stack([np.take(cum, j, axis=-1) for j in (jm, j0, j0 + 1)])
        self.cums[0][..., j0 == 0] = np.inf  # no segment before the first
        self.cums[2][..., j0 == k - 2] = np.inf  # a's arc length past vertex K - 2
        self.active = active
        # (2, Hy, Wx, K): the activity at jm and j0
        self.actives = np.stack([np.take(active, j, axis=-1) for j in (jm, j0)])
        a = vertex[:, :-1, :-1]
        t = np.empty(a.shape)
        t[..., 1:-1] = a[..., 2:] - a[..., :-2]
        t[..., 0] = a[..., 1] - a[..., 0]
        t[..., -1] = a[..., -1] - a[..., -2]
        n = np.sqrt(dot_planes(t, t))
        self.normal = t / np.where(n > 0, n, 1.0)


# Sections per chunk of the per-section arithmetic: its two dozen float64 temporaries
# then stay in a core's cache.
CHUNK_SECTIONS = 1 << 14
# Roles b, c, d: their (row, column) offsets from a on the lattice.
ROLES = ((0, 1), (1, 1), (1, 0))


def _chunk_folds(rays, window, kmax, limit):
    """(rows, cols) bool: the folds of the quads ``window`` (row, column slices) in
    their sections k < ``kmax`` (and k < ``limit``, (rows, cols) int, where given)."""
    ys, xs = window
    a = rays.vertex[:, ys, xs, :kmax]
    normal = rays.normal[:, ys, xs, :kmax]
    ref = rays.cum[ys, xs, :kmax]
    live = rays.active[ys, xs, :kmax].copy()
    if limit is not None:
        live &= np.arange(kmax) < limit[..., None]
    point, alive = _sections(rays, window, a, normal, ref)
    live &= alive.all(axis=0)
    return _flipped((point[:, 0], point[:, 1], point[:, 2]), normal, live)


def _roles(x, window, lead=0):
    """The three roles' (``ROLES``) windows of a per-ray array ``x`` (``lead`` axes
    before its (Hy, Wx) ones), stacked on a new axis after the leading ones."""
    ys, xs = window
    pre = (slice(None),) * lead
    return np.stack(
        [
            x[(*pre, slice(ys.start + dy, ys.stop + dy), slice(xs.start + dx, xs.stop + dx))]
            for dy, dx in ROLES
        ],
        axis=lead,
    )


def _sections(rays, window, a, normal, ref):
    """Where the three roles' rays (``ROLES``, offset from the quads ``window``) cross
    a's sections: the points relative to a's vertices (3, 3, rows, cols, kmax: the
    coordinates, then the roles) and whether each point's segment is active (3, rows,
    cols, kmax). ``section_points``' walk, from the segment at a's arc length, settled
    at once where it takes at most one step from segment j0 or j0 - 1; the other
    sections walk there. The roles go together: the same float64 operations, in one
    numpy call each instead of three."""
    kmax = ref.shape[-1]
    inner0, inner1, inner_m = (x[:kmax] for x in rays.inner)
    runs = [_upto(r, kmax) for r in rays.runs]
    a, normal = a[:, None], normal[:, None]
    vq = _roles(rays.vertex, window, 1)
    d_m, d_0, d_1 = (_minus(vq, a, r) for r in runs)  # (3, 3, rows, cols, kmax) each
    s_m = dot_planes(d_m, normal)
    s_0 = dot_planes(d_0, normal)
    s_1 = dot_planes(d_1, normal)
    cum = _roles(rays.cums[..., :kmax], window, 1)
    want = np.clip(ref, 0.0, _roles(rays.end, window))
    start_0 = (cum[1] <= want) & (want < cum[2])
    start_m = (cum[0] <= want) & (want < cum[1])
    pos, neg = s_0 > 0, s_0 < 0
    # segments j0 and j0 - 1 hold the plane (a walk stops there)
    stop_0 = ~((pos & (s_1 > 0) & inner0) | (neg & (s_1 < 0) & inner1))
    stop_m = ~((pos & (s_m > 0) & inner_m) | (neg & (s_m < 0)))
    back = stop_m & (start_m | (start_0 & pos & ~stop_0))
    here = stop_0 & (start_0 | (start_m & ~stop_m & (s_m < 0)))
    s_a = np.where(back, s_m, s_0)
    den = s_a - np.where(back, s_0, s_1)
    w = np.where(den != 0, s_a / np.where(den != 0, den, 1.0), 0.0)
    sq = _roles(rays.steps, window, 1)
    runs_m, runs_0 = runs[:2]
    shape = (3, *w.shape)
    point = (
        np.where(back, d_m, d_0)
        + np.where(back, _gather(sq, runs_m, shape), _gather(sq, runs_0, shape)) * w
    )
    act = _roles(rays.actives[..., :kmax], window, 1)
    alive = np.where(back, act[0], act[1])
    slow = ~(back | here)
    for r, (dy, dx) in enumerate(ROLES if slow.any() else ()):
        where = np.nonzero(slow[r])
        if len(where[0]):
            ys, xs = window
            q = (slice(ys.start + dy, ys.stop + dy), slice(xs.start + dx, xs.stop + dx))
            _walk(rays, q, (a[:, 0], normal[:, 0], ref), where, point[:, r], alive[r])
    return point, alive


def _runs(index):
    """The runs of an index array (K,) that steps by one: (destination, source) slice
    pairs, so that ``x[..., index]`` is gathered without a copy of ``x``."""
    cut = np.flatnonzero(np.diff(index) != 1) + 1
    bounds = [0, *cut.tolist(), len(index)]
    return [
        (slice(b0, b1), slice(int(index[b0]), int(index[b0]) + b1 - b0))
        for b0, b1 in zip(bounds[:-1], bounds[1:])
    ]


def _upto(runs, kmax):
    """``runs`` of an index array cut to its first ``kmax`` entries."""
    return [
        (slice(d.start, min(d.stop, kmax)), slice(s.start, s.start + min(d.stop, kmax) - d.start))
        for d, s in runs
        if d.start < kmax
    ]


def _minus(q, a, runs):
    """``q[..., index] - a`` for the index array whose ``runs`` are given."""
    out = np.empty(np.broadcast_shapes((*q.shape[:-1], a.shape[-1]), a.shape))
    for dst, src in runs:
        np.subtract(q[..., src], a[..., dst], out=out[..., dst])
    return out


def _gather(x, runs, shape):
    """``x[..., index]`` (of ``shape``) for the index array whose ``runs`` are given."""
    out = np.empty(shape)
    for dst, src in runs:
        out[..., dst] = x[..., src]
    return out


def _walk(rays, q, plane, where, point, alive):
    """The sections ``where`` (index arrays into the chunk's (rows, cols, K)) not settled
    at once: walked by ``section_points`` from the segment at a's arc length; their
    points (three planes) and ``alive`` updated in place. ``plane``: a's vertices and
    the normals (three planes each), a's arc lengths."""
    a, normal, ref = plane
    iy, ix, _k = where
    polylines = np.asarray(rays.source[q][iy, ix], dtype=np.float64)
    start = _segment_at(rays.cum[q][iy, ix], ref[where][:, None])
    origin = np.stack([c[where] for c in a], axis=-1)[:, None]
    nrm = np.stack([c[where] for c in normal], axis=-1)[:, None]
    pt, j = section_points(polylines, origin, nrm, start)
    for i in range(3):
        point[i][where] = pt[:, 0, i]
    alive[where] = rays.active[q][iy, ix, j[:, 0]]


def _flipped(points, normal, live):
    """(rows, cols) bool: quads one of whose corner triangles, in a live section, is
    turned against the first section. ``points``: b's, c's and d's section points
    relative to a's vertex (three planes each). The areas are those ``cross3`` and
    ``dot3`` make of the triangles' edges, bit for bit, up to a triangle's sign (an
    edge from a is a point, or a point negated; an area negated keeps its flips)."""
    p1, p2, p3 = points
    e21, e31, e32 = p2 - p1, p3 - p1, p3 - p2
    # a b c: (P1, P2); b c d: (P2 - P1, P3 - P1); c d a: (P3 - P2, -P2); d a b: (-P3, P1 - P3)
    flips = np.zeros(live.shape, dtype=bool)
    for e, f in ((p1, p2), (e21, e31), (e32, p2), (p3, e31)):
        cross = (e[1] * f[2] - e[2] * f[1], e[2] * f[0] - e[0] * f[2], e[0] * f[1] - e[1] * f[0])
        orient = np.sign(dot_planes(cross, normal))
        first = orient[..., :1]
        flips |= (orient != first) & (orient != 0) & (first != 0)
    flips &= live
    return flips.any(axis=-1)
