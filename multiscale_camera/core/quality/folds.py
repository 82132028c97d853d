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
to check. Sections past ray a's last active vertex are not checked either
(``_live_sections``): none of them is live, so none can flip (a traced field's
bending stretch is 30% of its rays' vertices on average on the 1000x rig).
The walk's start is the last vertex of q at or before a's arc length; section k is
settled at once where that start is segment j0 = min(k, K - 2) or j0 - 1 and the
walk stops within one step (rays of one band share their vertices' order, so this is
most sections: 94% of a SCALAR_FIELD on the turned rig, 63% on the nested 1000x rig);
the others walk as ``section_points`` does, reading the band's
vertices where the walk goes (``_cross``: no polyline is copied whole, and the walk's
start is a binary search over the arc lengths). Arc lengths and tangents are computed
once per band, as three (Hy, Wx, K) coordinate planes. A window is a few rows of quads
(each row's runs of quads to check, stacked where they line up: ``_rectangles``): its
rays, and each role's, lie one after the other in memory (``_window``: a copy of the
window's rows, one ray wider than its quads, so that a ray's neighbours on the right
and below are fixed offsets on), so
that the vertices j0 - 1, j0 and j0 + 1 of every ray are the window's vertices read
one element back, in place or one on (``_along``: one numpy call over the whole window
and a column or two fixed where the index is no such shift), and the arithmetic runs
over contiguous memory, in chunks of ``CHUNK_SECTIONS`` that stay in a core's cache.
Sides, points and areas are the same float64 operations in the same order as ``dot3``
and ``cross3`` on (..., 3) rows would make.
"""

import numpy as np


def dot_planes(a, b):
    """Dot product of vectors held as three coordinate planes (``a``, ``b``: sequences of
    three arrays of one shape), summed in the order ``dot3`` sums contiguous rows
    (x, then z, then y: numpy's einsum), so that both give the same float64 bits."""
    out = np.multiply(a[0], b[0])
    term = np.multiply(a[2], b[2])
    out += term
    np.multiply(a[1], b[1], out=term)
    out += term
    return out


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
    flat, base = _flat_rows(cum, index)
    want = np.clip(length, 0.0, flat.take(base + (k - 1)))
    lo = np.zeros(len(want), dtype=np.int64)
    hi = np.full(len(want), k, dtype=np.int64)
    for _ in range(int(k).bit_length()):
        mid = (lo + hi) >> 1
        at = flat.take(base + np.minimum(mid, k - 1)) <= want
        open_ = lo < hi
        lo = np.where(open_ & at, mid + 1, lo)
        hi = np.where(open_ & ~at, mid, hi)
    return np.clip(lo - 1, 0, k - 2)


def _flat_rows(x, index):
    """``x`` (..., K) as one flat array (a view where ``x`` is C-contiguous) and the
    flat position of vertex 0 of each polyline ``index`` (a tuple of (N,) int arrays
    into its leading axes), (N,) int64: vertex j of polyline n is ``flat[base[n] + j]``,
    one gather where ``x[(*index, j)]`` makes numpy combine the indices on every read."""
    x = np.ascontiguousarray(x)
    base = np.ravel_multi_index(tuple(np.asarray(i) for i in index), x.shape[:-1])
    return x.reshape(-1), base * x.shape[-1]


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
    flat, base = _flat_rows(vertex[0], index)
    flat = [flat] + [np.ascontiguousarray(vertex[c]).reshape(-1) for c in (1, 2)]

    def side(sel, jj):
        at = base[sel] + jj
        return dot_planes([flat[c].take(at) - origin[c][sel] for c in range(3)], normal[:, sel])

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
    qa = [flat[c].take(base + j) for c in range(3)]
    qb = [flat[c].take(base + j + 1) for c in range(3)]
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
    planes = np.moveaxis(np.asarray(vertices), -1, 0).astype(np.float64, order="C")
    return quad_folds_on_planes(planes, active, limit)


def quad_folds_on_planes(planes, active, limit=None):
    """``quad_folds`` of rays held as coordinate planes: ``planes`` (3, Hy, Wx, K)
    float64, C-contiguous (each coordinate's rays one after the other), the same map."""
    hy, wx, k = planes.shape[1:]
    out = np.zeros((max(hy - 1, 0), max(wx - 1, 0)), dtype=bool)
    if hy < 2 or wx < 2:
        return out
    rays = _Rays(planes, np.asarray(active, dtype=bool))
    budget = max(1, CHUNK_SECTIONS // k)
    cols = min(wx - 1, budget)
    if limit is None:
        limit = np.full(out.shape, k)
    limit = np.minimum(np.minimum(np.asarray(limit), k), _live_sections(rays.active, k))
    for c0, c1, kmax, rows in _rectangles(limit, cols, budget):
        lim = np.zeros((len(rows), c1 - c0), dtype=limit.dtype)
        for i, (r0, a, b) in enumerate(rows):
            lim[i, a - c0 : b - c0] = limit[r0, a:b]
        got = _chunk_folds(rays, (rows[0][0], len(rows), c0, c1), kmax, lim)
        for i, (r0, a, b) in enumerate(rows):
            out[r0, a:b] = got[i, a - c0 : b - c0]
    return out


def _rectangles(limit, cols, budget):
    """The windows of every row (``_row_windows``, at most ``cols`` quads) stacked into
    rectangles of consecutive rows: a list of (c0, c1, kmax, rows), the columns c0 to c1
    (excluded) that hold the windows of consecutive rows ``rows``, each row's own
    window (row, c0, c1). A row's window joins the rectangle of the row above
    with the same ``kmax`` where its ends lie within ``GAP_QUADS`` of the rectangle's
    and the rectangle stays within ``budget`` quads (its rows times one more than its
    width): a window's fixed cost is then paid once for a few narrow rows (on the 6x
    rig at 1920x1080 the row windows averaged 240 quads, and those of 32 cost four
    times as much a quad as those of 900). The quads of the rectangle outside a row's
    own window are computed with no section checked and dropped."""
    done, open_ = [], []
    for r0 in range(limit.shape[0]):
        carried = []
        for c0, c1, kmax in _row_windows(limit[r0], cols):
            for n, rect in enumerate(open_):
                if rect is None or rect[2] != kmax:
                    continue
                lo, hi = min(rect[0], c0), max(rect[1], c1)
                near = abs(rect[0] - c0) <= GAP_QUADS and abs(rect[1] - c1) <= GAP_QUADS
                if near and (len(rect[3]) + 1) * (hi - lo + 1) <= budget:
                    rect[0], rect[1] = lo, hi
                    rect[3].append((r0, c0, c1))
                    carried.append(rect)
                    open_[n] = None
                    break
            else:
                carried.append([c0, c1, kmax, [(r0, c0, c1)]])
        done += [rect for rect in open_ if rect is not None]
        open_ = carried
    return [tuple(rect) for rect in done + open_]


# The sections a quad may fold in end after ray a's last active vertex, rounded up to a
# multiple of this fraction of K: quads of a row then share their limit in long runs
# (``_row_windows``), so their windows stay long.
LIVE_STEP_FRACTION = 1 / 8


def _live_sections(active, k):
    """(Hy - 1, Wx - 1) int: for each quad, one more than the index of ray a's last
    active vertex (0 where none is), rounded up to a multiple of ``LIVE_STEP_FRACTION``
    K and at most K. A section past it is not live (``_chunk_folds``), so it cannot flip
    and is not checked: the map is the same. ``active``: (Hy, Wx, K) bool."""
    a = active[:-1, :-1]
    last = np.where(a.any(axis=-1), k - np.argmax(a[..., ::-1], axis=-1), 0)
    step = max(1, int(np.ceil(k * LIVE_STEP_FRACTION)))
    return np.minimum(-(-last // step) * step, k)


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
    d: the vertices as coordinate planes (3, Hy, Wx, K), float64; the arc lengths at
    every vertex (Hy, Wx, K); the activity (Hy, Wx, K); the unit tangents, a's section
    normals, (3, Hy, Wx, K); for each section k, the first vertices of the segments
    around the one at a's vertex: jm = j0 - 1, j0 (segment k, the last one for the last
    vertex) and j0 + 1, (K,) int each."""

    def __init__(self, vertex, active):
        k = vertex.shape[-1]
        self.k = k
        self.j0 = j0 = np.minimum(np.arange(k), k - 2)
        self.jm = np.maximum(j0 - 1, 0)
        # whether a walk may go on from segment j0 back, from it on, from j0 - 1 back
        self.inner = (j0 > 0, j0 < k - 2, j0 > 1)
        self._plans = {}
        self.vertex = vertex = np.ascontiguousarray(vertex, dtype=np.float64)
        steps = np.diff(vertex, axis=-1)  # the bits of np.diff(v, axis=-2)
        # _arc_lengths and _unit_tangents, bit for bit, on the planes
        cum = np.zeros(vertex.shape[1:])
        np.cumsum(np.sqrt(dot_planes(steps, steps)), axis=-1, out=cum[..., 1:])
        self.cum = cum
        self.active = np.ascontiguousarray(active, dtype=bool)
        t = np.empty(vertex.shape)
        np.subtract(vertex[..., 2:], vertex[..., :-2], out=t[..., 1:-1])
        np.subtract(vertex[..., 1], vertex[..., 0], out=t[..., 0])
        np.subtract(vertex[..., -1], vertex[..., -2], out=t[..., -1])
        n = np.sqrt(dot_planes(t, t))
        t /= np.where(n > 0, n, 1.0)
        self.normal = t

    def plan(self, name, kq):
        """The ``_shift_plan`` of reads ``name`` for windows of kq vertices: "m", "0",
        "1" (vertices jm, j0, j0 + 1, less vertex k), "step", "step_m" (vertex j0 + 1
        less j0, jm + 1 less jm)."""
        key = (name, kq)
        if key not in self._plans:
            jm, j0, k = self.jm, self.j0, np.arange(self.k)
            ix, iy = {
                "m": (jm, k),
                "0": (j0, k),
                "1": (j0 + 1, k),
                "step": (j0 + 1, j0),
                "step_m": (jm + 1, jm),
            }[name]
            self._plans[key] = _shift_plan(ix, iy, kq)
        return self._plans[key]


# Sections per chunk of the per-section arithmetic: its two dozen float64 temporaries
# then stay in a core's cache.
CHUNK_SECTIONS = 1 << 14
# Roles b, c, d: their (row, column) offsets from a on the lattice.
ROLES = ((0, 1), (1, 1), (1, 0))


def _flat(x):
    """A view of ``x`` (..., P, kq) with its last two axes as one (..., P * kq): the
    rays of a window one after the other, so that a shift by one vertex is a shift by
    one element. Raises where that needs a copy (a window not contiguous)."""
    view = x.view()
    view.shape = (*x.shape[:-2], x.shape[-2] * x.shape[-1])
    return view


def _shift_plan(ix, iy, kq):
    """How ``_along`` reads vertices ``ix`` and ``iy`` ((K,) int each, K >= kq) for
    rays of kq vertices: (sx, sy, fixes), the shifts of the flat call (the most common
    ``index[k] - k``, -1, 0 or 1) and the (k, jx, jy) of the vertices it misses, whose
    index is no such shift or reaches past the window (that vertex's section is never
    checked: it reads vertex kq - 1)."""
    k = np.arange(kq)
    ix, iy = ix[:kq], iy[:kq]
    sx, sy = (
        int(np.bincount(np.clip(i - k + 1, 0, 2), minlength=3).argmax()) - 1 for i in (ix, iy)
    )
    fix = np.flatnonzero((ix != k + sx) | (iy != k + sy) | (ix >= kq) | (iy >= kq))
    return sx, sy, [(int(c), min(int(ix[c]), kq - 1), min(int(iy[c]), kq - 1)) for c in fix]


def _along(out, x, plan, y=None, func=None):
    """Fill ``out`` (..., P, kq), P rays of kq vertices held contiguous, with
    ``func(x[..., ix[k]], y[..., iy[k]])`` at every vertex k (or ``x[..., ix[k]]`` with
    no ``func``): ``x``, ``y`` (..., P, kq) contiguous likewise, ``plan`` the
    ``_shift_plan`` of ``ix`` and ``iy``. One numpy call on the flat rays, shifted by
    the plan's shifts, and the vertices it misses written a column at a time: the same
    operation on the same operands as ``func(x[..., ix], y[..., iy])``, element for
    element."""
    sx, sy, fixes = plan
    of, xf = _flat(out), _flat(x)
    n = of.shape[-1]
    lo, hi = max(0, -sx, -sy), n - max(0, sx, sy)
    if func is None:
        np.copyto(of[..., lo:hi], xf[..., lo + sx : hi + sx])
        for c, jx, _jy in fixes:
            out[..., c] = x[..., jx]
        return out
    func(xf[..., lo + sx : hi + sx], _flat(y)[..., lo + sy : hi + sy], out=of[..., lo:hi])
    for c, jx, jy in fixes:
        func(x[..., jx], y[..., jy], out=out[..., c])
    return out


def _window(x, y, rows, c0, c1, kq, lead=1):
    """Rows y to y + rows (included), columns c0 to c1 (included), vertices below kq
    of a band array ``x`` (``lead`` axes before its (Hy, Wx, K) ones), as one run of
    rays, (..., (rows + 1) (c1 - c0 + 1), kq), contiguous: a ray's neighbour on the
    right is the next one, below it the one ``c1 - c0 + 1`` on, so that each role's
    rays are a ``_flat`` window of it. A view where that needs no copy."""
    w = x[(slice(None),) * lead + (slice(y, y + rows + 1), slice(c0, c1 + 1), slice(0, kq))]
    w = np.ascontiguousarray(w)
    return w.reshape(*w.shape[:lead], -1, w.shape[-1])


def _chunk_folds(rays, window, kmax, limit):
    """(rows, cols) bool: the folds of the quads ``window`` = (y, rows, c0, c1), lattice
    rows y to y + rows - 1, columns c0 to c1 (excluded), in their sections k < ``kmax``
    and k < ``limit`` ((rows, cols) int; 0: not checked). The rays of rows y to y + rows
    are laid one after the other (``_window``), each row one ray longer than its quads,
    so that the quads are Q = rows (cols + 1) - 1 consecutive rays a and their roles'
    rays lie at fixed offsets on from them; the quad at the end of each row (whose b
    would be the next row's first ray) is computed with no section checked and dropped.
    The arithmetic runs over sections 0 to kq - 1, kq = min(kmax + 1, K), on those
    contiguous rays; the last is not checked where kq > kmax."""
    y, rows, c0, c1 = window
    cols = c1 - c0
    width = cols + 1
    quads = rows * width - 1
    kq = min(kmax + 1, rays.k)
    vertex = _window(rays.vertex, y, rows, c0, c1, kq)
    a = vertex[:, :quads]
    offsets = [dy * width + dx for dy, dx in ROLES]
    # the roles' rays, each (3, Q, kq): b, c, d
    q = [vertex[:, o : o + quads] for o in offsets]
    normal = _window(rays.normal, y, rows - 1, c0, c1, kq)[:, :quads]
    cum = _window(rays.cum, y, rows, c0, c1, kq, 0)
    ref = cum[:quads]
    active = _window(rays.active, y, rows, c0, c1, kq, 0)
    lim = np.zeros((rows, width), dtype=np.asarray(limit).dtype)
    lim[:, :cols] = limit
    live = active[:quads] & (np.arange(kq) < lim.ravel()[:quads, None])
    ends = rays.cum[y : y + rows + 1, c0 : c1 + 1, -1].ravel()

    def role(o):
        """The rows and columns in the band of the role's rays at offset ``o`` from
        quads ``ix`` ((N,) int) of the window."""
        return lambda ix: (y + (ix + o) // width, c0 + (ix + o) % width)

    roles = [(o, ends[o : o + quads, None], role(o)) for o in offsets]
    point, alive = _sections(rays, roles, (a, q, normal), (cum, ref, active), live)
    live &= alive.all(axis=0)
    flips = _flipped((point[:, 0], point[:, 1], point[:, 2]), normal, live)
    out = np.zeros(rows * width, dtype=bool)
    out[:quads] = flips
    return out.reshape(rows, width)[:, :cols]


def _sections(rays, roles, planes, lengths, live):
    """Where the three roles' rays (``ROLES``) cross a's sections: the points relative to
    a's vertices (3, 3, Q, kq: the coordinates, then the roles) and whether each
    point's segment is active (3, Q, kq). ``section_points``' walk, from the segment
    at a's arc length, settled at once where it takes at most one step from segment j0
    or j0 - 1; the other sections walk there (those checked, and the first, which
    every other is compared with). ``roles``: for each role, its rays' offset in the
    window's run of rays, their whole lengths ((Q, 1) float64) and the function giving
    the band's (rows, columns) of its rays for quads ``ix``; ``planes``: a's vertices,
    the roles' (a list) and a's normals, (3, Q, kq) each; ``lengths``: the arc lengths
    and activity of the window's rays (``_window``) and a's arc lengths."""
    a, q, normal = planes
    cum, ref, active = lengths
    cols = ref.shape[0]
    kq = ref.shape[-1]
    j0 = rays.j0
    plan = {name: rays.plan(name, kq) for name in ("m", "0", "1", "step", "step_m")}
    inner0, inner1, inner_m = (x[:kq] for x in rays.inner)
    shape = (3, 3, cols, kq)
    d_m, d_0, d_1 = np.empty(shape), np.empty(shape), np.empty(shape)
    for r in range(3):
        for d, name in ((d_m, "m"), (d_0, "0"), (d_1, "1")):
            _along(d[:, r], q[r], plan[name], a, np.subtract)
    normal = normal[:, None]
    s_m = dot_planes(d_m, normal)
    s_0 = dot_planes(d_0, normal)
    s_1 = dot_planes(d_1, normal)
    # the roles' arc lengths at jm, j0 and j0 + 1 (inf where the segment before the
    # first or after the last would be meant), and their activity at jm and j0
    c_m, c_0, c_1 = (np.empty((3, cols, kq)) for _ in range(3))
    act_m, act_0 = (np.empty((3, cols, kq), dtype=bool) for _ in range(2))
    for r, (o, _ends, _ray) in enumerate(roles):
        for out, name in ((c_m, "m"), (c_0, "0"), (c_1, "1")):
            _along(out[r], cum[o : o + cols], plan[name])
        for out, name in ((act_m, "m"), (act_0, "0")):
            _along(out[r], active[o : o + cols], plan[name])
    ends = [e for _o, e, _ray in roles]
    c_m[..., j0[:kq] == 0] = np.inf
    c_1[..., j0[:kq] == rays.k - 2] = np.inf
    # a's arc length (>= 0), clamped to each role's length: np.clip's bits
    want = np.minimum(ref, np.stack(ends))
    start_0 = (c_0 <= want) & (want < c_1)
    start_m = (c_m <= want) & (want < c_0)
    pos, neg = s_0 > 0, s_0 < 0
    # segments j0 and j0 - 1 hold the plane (a walk stops there)
    stop_0 = ~((pos & (s_1 > 0) & inner0) | (neg & (s_1 < 0) & inner1))
    stop_m = ~((pos & (s_m > 0) & inner_m) | (neg & (s_m < 0)))
    back = stop_m & (start_m | (start_0 & pos & ~stop_0))
    here = stop_0 & (start_0 | (start_m & ~stop_m & (s_m < 0)))
    s_a = np.where(back, s_m, s_0)
    den = s_a - np.where(back, s_0, s_1)
    w = np.where(den != 0, s_a / np.where(den != 0, den, 1.0), 0.0)
    # the crossing, on segment j0 - 1 (back) or j0: its first vertex's d plus the
    # segment's step (the bits of np.diff) times w
    step, step_m = np.empty(shape), np.empty(shape)
    for r in range(3):
        _along(step[:, r], q[r], plan["step"], q[r], np.subtract)
        _along(step_m[:, r], q[r], plan["step_m"], q[r], np.subtract)
    np.copyto(step, step_m, where=back)
    np.copyto(d_0, d_m, where=back)
    np.multiply(step, w, out=step)
    point = np.add(d_0, step, out=step)
    alive = np.where(back, act_m, act_0)
    first = np.arange(kq) == 0
    slow = ~(back | here) & (live | first)
    for r, (_o, _ends, ray) in enumerate(roles if slow.any() else ()):
        where = np.nonzero(slow[r])
        if len(where[0]):
            _walk(rays, ray, (a, normal[:, 0], ref), where, point[:, r], alive[r])
    return point, alive


def _walk(rays, q, plane, where, point, alive):
    """The sections ``where`` (index arrays into the chunk's (Q, kq)) not settled at
    once: walked as ``section_points`` walks, from the segment at a's arc length, on
    the band's planes of vertices (no polyline copied); their points (three planes) and
    ``alive`` updated in place. ``q``: the role's rays in the band, a function of the
    quads ``ix`` ((N,) int) giving their (rows, columns); ``plane``: a's vertices and
    the normals (three planes each), a's arc lengths."""
    a, normal, ref = plane
    ix, _k = where
    ray = q(ix)
    start = _segment_in(rays.cum, ray, ref[where])
    origin = np.stack([c[where] for c in a])
    nrm = np.stack([c[where] for c in normal])
    pt, j = _cross(rays.vertex, ray, origin, nrm, start)
    for i in range(3):
        point[i][where] = pt[i]
    alive[where] = rays.active[(*ray, j)]


def _flipped(points, normal, live):
    """(cols,) bool: quads one of whose corner triangles, in a live section, is turned
    against the first section. ``points``: b's, c's and d's section points relative to
    a's vertex (three planes each, (cols, kq)). The areas are those ``cross3`` and
    ``dot3`` make of the triangles' edges, bit for bit, up to a triangle's sign (an
    edge from a is a point, or a point negated; an area negated keeps its flips)."""
    p1, p2, p3 = points
    e21, e31, e32 = p2 - p1, p3 - p1, p3 - p2
    # a b c: (P1, P2); b c d: (P2 - P1, P3 - P1); c d a: (P3 - P2, -P2); d a b: (-P3, P1 - P3)
    flips = np.zeros(live.shape, dtype=bool)
    cross = np.empty((3, *live.shape))
    term = np.empty(live.shape)
    for e, f in ((p1, p2), (e21, e31), (e32, p2), (p3, e31)):
        for c, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):  # e[i] f[j] - e[j] f[i]
            np.multiply(e[i], f[j], out=cross[c])
            np.multiply(e[j], f[i], out=term)
            cross[c] -= term
        orient = np.sign(dot_planes(cross, normal))
        first = orient[..., :1]
        flips |= (orient != first) & (orient != 0) & (first != 0)
    flips &= live
    return flips.any(axis=-1)
