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
most sections: 94% of a SCALAR_FIELD on the turned rig, 63% on the nested 1000x rig);
the others walk as ``section_points`` does, reading the band's
vertices where the walk goes (``_cross``: no polyline is copied whole, and the walk's
start is a binary search over the arc lengths). Per-ray quantities (arc
lengths, tangents, segments) are computed once per band and shared by the three roles
b, c and d, whose windows are stacked so that one numpy call serves all three;
coordinates are held as three (Hy, Wx, K) planes, the vertices around j0 are read
through slices, and the sections go in chunks of ``CHUNK_SECTIONS``, so that the
arithmetic runs over contiguous memory in a core's cache. Sides, points and areas are
the same float64 operations in the same order as ``dot3`` and ``cross3`` on (..., 3)
rows would make.
"""

import numpy as np


def dot_planes(a, b):
    """Dot product of vectors held as three coordinate planes (``a``, ``b``: sequences of
    three arrays of one shape), summed in the order ``dot3`` sums contiguous rows
    (x, then z, then y: numpy's einsum), so that both give the same float64 bits."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


def _segment_at(cum, length):
    """(P, M) int: for polylines of arc lengths ``cum`` (P, K), the segment holding each
    of the arc lengths ``length`` (P, M), clamped to the polyline: the last vertex at or
    before it (the last segment from the last two vertices on)."""
    length = np.asarray(length)
    rows = np.broadcast_to(np.arange(len(cum))[:, None], length.shape)
    return _segment_in(cum, (rows.ravel(),), length.ravel()).reshape(length.shape)


def _segment_in(cum, index, length):
    """(N,) int: ``_segment_at`` for N arc lengths ``length`` (N,) float64, each on the
    polyline ``index`` (a tuple of (N,) int arrays into the leading axes of ``cum``,
    (..., K) float64, non-decreasing along its last axis): the number of its vertices at
    or before the length (clamped to the polyline) less one, clamped to the segments.
    A binary search, log2(K) gathers of N entries, with no (N, K) copy of ``cum``."""
    k = cum.shape[-1]
    want = np.clip(length, 0.0, cum[(*index, k - 1)])
    lo = np.zeros(len(want), dtype=np.int64)
    hi = np.full(len(want), k, dtype=np.int64)
    for _ in range(int(k).bit_length()):
        mid = (lo + hi) >> 1
        at = cum[(*index, np.minimum(mid, k - 1))] <= want
        open_ = lo < hi
        lo = np.where(open_ & at, mid + 1, lo)
        hi = np.where(open_ & ~at, mid, hi)
    return np.clip(lo - 1, 0, k - 2)


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
    p, m = np.shape(start)
    rows = np.broadcast_to(np.arange(p)[:, None], (p, m)).ravel()
    planes = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    point, j = _cross(
        planes,
        (rows,),
        np.reshape(origin, (-1, 3)).T,
        np.reshape(normal, (-1, 3)).T,
        np.ravel(start),
    )
    return point.T.reshape(p, m, 3), j.reshape(p, m)


def _cross(vertex, index, origin, normal, start):
    """``section_points`` for N sections of polylines held as coordinate planes, each
    read where its walk goes rather than copied whole.

    vertex : (3, ..., K) float64, the polylines' vertices; ``index`` a tuple of (N,) int
    arrays into the axes between the first and the last: each section's polyline.
    origin, normal : (3, N) float64 (coordinate planes). start : (N,) int, the segment
    the walk starts from. Returns the crossing relative to ``origin``, (3, N) float64,
    and its segment's first vertex, (N,) int. The sides are ``dot_planes``, the bits of
    ``dot3`` on rows."""
    k = vertex.shape[-1]
    j = np.clip(start, 0, k - 2).astype(np.int64)

    def side(sel, jj):
        at = (*(ix[sel] for ix in index), jj)
        return dot_planes([vertex[c][at] - origin[c][sel] for c in range(3)], normal[:, sel])

    every = np.arange(len(j))
    s0, s1 = side(every, j), side(every, j + 1)
    # A walk goes one way, back from a segment both of whose ends lie on the plane's
    # positive side, on from one on the negative side, and stops at the first segment
    # whose ends do not (or that would turn it back), or at the polyline's end: back,
    # at the first earlier vertex on the plane or behind it; on, at the first later
    # segment whose far end is on the plane or beyond it. Vertices are read ahead in
    # windows that double, so a long walk takes a few numpy calls.
    back = np.flatnonzero((s0 > 0) & (s1 > 0) & (j > 0))
    ahead = np.flatnonzero((s0 < 0) & (s1 < 0) & (j < k - 2))
    for sel, way in ((back, -1), (ahead, 1)):
        width = 4
        while len(sel):
            cand = j[sel, None] + way * np.arange(1, width + 1)
            if way < 0:
                cand = np.maximum(cand, 0)
                stop = ~(side(sel[:, None], cand) > 0) | (cand == 0)
            else:
                cand = np.minimum(cand, k - 2)
                stop = ~(side(sel[:, None], cand + 1) < 0) | (cand == k - 2)
            found = stop.any(axis=1)
            first = np.argmax(stop, axis=1)
            j[sel[found]] = cand[found, first[found]]
            j[sel[~found]] = cand[~found, -1]
            sel, width = sel[~found], width * 2
    walked = np.concatenate([back, ahead])
    s0[walked], s1[walked] = side(walked, j[walked]), side(walked, j[walked] + 1)
    den = s0 - s1
    w = np.where(den != 0, s0 / np.where(den != 0, den, 1.0), 0.0)
    qa = [vertex[c][(*index, j)] for c in range(3)]
    qb = [vertex[c][(*index, j + 1)] for c in range(3)]
    point = np.stack([(qa[c] - origin[c]) + (qb[c] - qa[c]) * w for c in range(3)])
    return point, j


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
    at once: walked as ``section_points`` walks, from the segment at a's arc length, on
    the band's planes of vertices (no polyline copied); their points (three planes) and
    ``alive`` updated in place. ``q``: the role's (row, column) slices of the band;
    ``plane``: a's vertices and the normals (three planes each), a's arc lengths."""
    a, normal, ref = plane
    iy, ix, _k = where
    ray = (iy + q[0].start, ix + q[1].start)
    start = _segment_in(rays.cum, ray, ref[where])
    origin = np.stack([c[where] for c in a])
    nrm = np.stack([c[where] for c in normal])
    pt, j = _cross(rays.vertex, ray, origin, nrm, start)
    for i in range(3):
        point[i][where] = pt[i]
    alive[where] = rays.active[(*ray, j)]


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
