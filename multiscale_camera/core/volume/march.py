"""Direct volume rendering along bent rays (paper section 5.2), pure numpy.

Rays are the polylines of a ``RayBundle``. Every ray is sampled at arc lengths
``j * step`` from its vertex 0 (a lattice fixed to the ray, so skipping samples never
shifts the others). At each sample the value is interpolated trilinearly, the tables
of the one or two cameras next to the membership N interpolated along the polyline
there are read and blended with eq. 6's weights w(N, i); the opacity is corrected for
the step, optionally shaded by the gradient, and composited front to back.

A chunk of rays is handled in bulk: only the samples of the pieces that ``runs`` finds
occupied are taken (empty-space skipping), in rounds of growing size per ray until it
is nearly opaque (early termination).
"""

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..errors import Cancelled
from .runs import _pieces, _runs, _snap, _starts, _within
from .scene import MIN_DIRECTION

# A ray stops once its accumulated opacity reaches this: what lies behind could change
# its colour by at most 0.5% of full scale.
EARLY_TERMINATION = 0.995

# Samples a ray takes in its first round of marching; each later round doubles it, up
# to ROUND_MAX, unless the opacity gathered so far says the ray ends sooner: rays that
# stop early (an opaque skin) waste few samples, rays through translucent material take
# few rounds.
ROUND_FIRST = 16
ROUND_MAX = 256

# Share of a gradient-shaded sample's colour that does not depend on its orientation.
SHADE_AMBIENT = 0.35
# Vertices x rays processed at once: bounds the memory of a chunk's segment stage
# (about 80 bytes a vertex: 170 MB for a full chunk of the demo's bent rays).
CHUNK_VERTICES = 1 << 21


@dataclass(frozen=True)
class VolumeResult:
    """What R rays gathered in one volume.

    colour : (R, 3) float32, premultiplied by alpha (linear RGB).
    alpha : (R,) float32, accumulated opacity.
    entry : (R,) float64, arc length of the ray's first sample in the volume's box (inf
        when it has none).
    depth : (R,) float64, arc length where the accumulated opacity reached 0.5 (inf
        when it never did).
    samples : int, samples taken (trilinear reads); skipped : int, samples skipped in
        empty blocks.
    """

    colour: np.ndarray
    alpha: np.ndarray
    entry: np.ndarray
    depth: np.ndarray
    samples: int = 0
    skipped: int = 0


def march_volume(scene, vertices, membership, reach, stop=None, should_stop=None, threads=1):
    """Composite ``scene``'s volume front to back along bent rays.

    Parameters
    ----------
    scene : VolumeScene.
    vertices : (R, K, 3) float32 polylines, world units (a ``RayBundle``'s).
    membership : (R, K) float32, the membership N at each vertex.
    reach : (R,) float, how far the last segment runs on past vertex K-1.
    stop : (R,) float or None, arc length where each ray ends (an opaque surface's
        hit); inf or None for no surface.
    should_stop : callable or None; True between chunks raises ``Cancelled``.
    threads : int, chunks marched at once (numpy releases the GIL in its loops).

    Returns
    -------
    VolumeResult
    """
    vertices = np.asarray(vertices)
    r, k = vertices.shape[:2]
    stop = np.full(r, np.inf) if stop is None else np.asarray(stop, dtype=np.float64)
    reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), (r,))
    colour = np.zeros((r, 3), np.float32)
    alpha = np.zeros(r, np.float32)
    entry = np.full(r, np.inf)
    depth = np.full(r, np.inf)
    samples = skipped = 0
    chunk = max(64, min(CHUNK_VERTICES // max(k + 1, 1), -(-r // max(threads, 1))))
    parts = [slice(a, min(a + chunk, r)) for a in range(0, r, chunk)]

    def run(sl):
        return sl, _march_chunk(scene, vertices[sl], membership[sl], reach[sl], stop[sl])

    # ``should_stop`` is only ever called here, on the caller's thread (it may be bpy's)
    done = []
    pool = ThreadPoolExecutor(threads) if threads > 1 and len(parts) > 1 else None
    try:
        for first in range(0, len(parts), max(threads, 1)):
            if should_stop is not None and should_stop():
                raise Cancelled()
            group = parts[first : first + max(threads, 1)]
            done += list(pool.map(run, group)) if pool else [run(sl) for sl in group]
    finally:
        if pool is not None:
            pool.shutdown()
    for sl, out in done:
        colour[sl], alpha[sl], entry[sl], depth[sl] = out.colour, out.alpha, out.entry, out.depth
        samples += out.samples
        skipped += out.skipped
    return VolumeResult(colour, alpha, entry, depth, samples, skipped)


def _cell(shape, p):
    """Trilinear cells of clamped voxel coordinates.

    p : three (P,) float32 arrays, x, y and z inside [0, n - 1].

    Returns
    -------
    base : (P,) int64, flat C-order index of the cell's first corner; offsets : 8 ints,
    the corners' flat offsets (x fastest in the corner order); f : three (P,) float32
    fractions.
    """
    strides = (shape[1] * shape[2], shape[2], 1)
    base = None
    f = []
    for axis, n in enumerate(shape):
        i0 = np.minimum(p[axis].astype(np.int64), max(n - 2, 0))
        f.append(p[axis] - i0.astype(np.float32))
        if base is None:
            base = i0 * strides[0]
        else:
            base += i0 * strides[axis] if axis < 2 else i0
    ox, oy, oz = (st * (n > 1) for st, n in zip(strides, shape))
    return base, (0, ox, oy, ox + oy, oz, ox + oz, oy + oz, ox + oy + oz), f


def _mix(a, b, t, out=None):
    """a + (b - a) t, into ``out`` (which may be ``b``) or a new array."""
    out = np.subtract(b, a, out=out)
    out *= t
    out += a
    return out


def _lerp8(c, f):
    """Trilinear blend of eight corner arrays ``c`` (x fastest) by fractions ``f``; the
    corners are left as they are, four new arrays are made."""
    fx, fy, fz = f
    x0, x1 = _mix(c[0], c[1], fx), _mix(c[2], c[3], fx)
    x2, x3 = _mix(c[4], c[5], fx), _mix(c[6], c[7], fx)
    y0, y1 = _mix(x0, x1, fy, out=x1), _mix(x2, x3, fy, out=x3)
    return _mix(y0, y1, fz, out=y1)


def _corners(flat, cell):
    """(8, P) values of ``flat`` at the eight corners of each cell."""
    base, offsets, _f = cell
    return flat.take(base + np.array(offsets, dtype=np.int64)[:, None])


def _trilinear(flat, cell):
    """(P,) float32 trilinear samples of a flat C-ordered float32 array in ``cell``."""
    return _lerp8(_corners(flat, cell), cell[2])


def _directions(packed, cell):
    """(3, P) float32 trilinear blend of packed int8 directions (``gradient_directions``;
    unit = 127) in ``cell``."""
    g = _corners(packed, cell)  # (8, P) int32, four int8 each
    g = g.view(np.int8).reshape(8, -1, 4).transpose(2, 0, 1)[:3].astype(np.float32, order="C")
    return _lerp8(g.transpose(1, 0, 2), cell[2])


def _classify(scene, val, nval):
    """(4, P) float32 RGBA planes of values ``val`` (P,) under the tables blended by
    eq. 6 at memberships ``nval`` (P,); alpha already corrected for the step.

    Eq. 6 weighs only the cameras i with |N - i| < 1: the two next to N (one at the
    ends), whose weights are normalised to sum to one as ``blend_weights``' are. N is
    snapped first (``_snap``), so a preserved region's samples use its camera alone.
    """
    ncam, tsize = scene.tables.shape[:2]
    x = np.clip(val, 0.0, 1.0).astype(np.float32) * np.float32(tsize - 1)
    lo = np.minimum(x.astype(np.int32), tsize - 2)
    t = x - lo
    look = scene.lookup
    out = np.empty((4, len(val)), np.float32)
    if ncam == 1:
        for c in range(4):
            out[c] = look[4 + c].take(lo) * t + look[c].take(lo)
        return out
    nval = _snap(np.asarray(nval, np.float32))
    first = np.clip(np.floor(nval), 1, ncam - 1)  # cameras first and first + 1 (1-based)
    w0 = np.clip(1.0 - np.abs(nval - first), 0.0, 1.0)
    w1 = np.clip(1.0 - np.abs(nval - first - 1.0), 0.0, 1.0)
    if scene.cubic:
        w0 = w0 * w0 * (3.0 - 2.0 * w0)
        w1 = w1 * w1 * (3.0 - 2.0 * w1)
    total = np.maximum(w0 + w1, np.float32(1e-30))
    w0 /= total
    w1 /= total
    row0 = (first.astype(np.int32) - 1) * tsize + lo
    row1 = row0 + tsize
    for c in range(4):
        a = look[4 + c].take(row0) * t + look[c].take(row0)
        a *= w0
        b = look[4 + c].take(row1) * t + look[c].take(row1)
        b *= w1
        np.add(a, b, out=out[c])
    return out


def _march_chunk(scene, vertices, membership, reach, stop):
    """March one chunk of R rays (``march_volume``'s arguments, sliced).

    Returns
    -------
    VolumeResult of the chunk's R rays.
    """
    vol = scene.volume
    shape = vol.shape
    h = scene.step * vol.voxel_size
    r = len(vertices)
    colour = np.zeros((3, r), dtype=np.float32)
    trans = np.ones(r, dtype=np.float32)  # transmittance so far
    depth = np.full(r, np.inf)

    runs, dense_skipped, entry = _runs(scene, vertices, membership, reach, stop, h)

    def result(samples, skipped):
        alpha = (1.0 - trans).astype(np.float32)
        return VolumeResult(colour.T.copy(), alpha, entry, depth, samples, skipped)

    skipped = int(dense_skipped[:, -1].sum())
    if runs is None:
        return result(0, skipped)
    pieces = _pieces(scene, runs)
    busy = pieces.busy
    # the pieces' skipped samples, less those behind where a ray stopped
    empty = np.zeros(len(busy) + 1, np.int64)
    np.cumsum(np.where(busy, 0, pieces.count), out=empty[1:])
    skipped += int(empty[-1])
    piece_ray = runs.ray.take(pieces.run)
    sel = np.flatnonzero(busy)
    if not len(sel):
        return result(0, skipped)

    # the busy pieces, with what their samples need
    run = pieces.run[sel]
    i = pieces.i[sel]
    count = pieces.count[sel]
    p0 = [(runs.p[c].take(run) + i * runs.dp[c].take(run)).astype(np.float32) for c in range(3)]
    dp = [runs.dp[c].take(run).astype(np.float32) for c in range(3)]
    n0 = (runs.nm.take(run) + i * runs.dnm.take(run)).astype(np.float32)
    dn = runs.dnm.take(run).astype(np.float32)
    j0 = runs.j.take(run) + i
    wdir = [runs.direction[c].take(run).astype(np.float32) for c in range(3)]
    bseg = runs.seg.take(run)
    bray = piece_ray[sel]
    done_at = np.zeros(len(sel) + 1, np.int64)  # samples in busy pieces before each
    np.cumsum(count, out=done_at[1:])

    # each ray's busy pieces are sel[first:last]; all its pieces end at piece_end
    first = np.flatnonzero(np.r_[True, bray[1:] != bray[:-1]])
    last = np.r_[first[1:], len(sel)]
    rid = bray[first]
    piece_end = np.searchsorted(piece_ray, rid, side="right")
    ptr = first

    flat = vol.values.ravel()
    top = [np.float32(n - 1) for n in shape]
    m_lin = vol.world_to_index[:3, :3]
    kseg = dense_skipped.shape[1]
    samples = 0
    budget = np.full(len(rid), ROUND_FIRST, np.int64)
    taken = np.zeros(len(rid), np.int64)
    while len(rid):
        # this round: each ray's next busy pieces, up to ``budget`` samples (at least one)
        upto = np.searchsorted(done_at, done_at[ptr] + budget, side="right") - 1
        upto = np.clip(upto, ptr + 1, last)
        took = upto - ptr
        pid = np.repeat(ptr - _starts(took), took) + np.arange(int(took.sum()))
        cnt = count.take(pid)
        per_ray = done_at[upto] - done_at[ptr]
        kf = _within(cnt).astype(np.float32)
        ps = np.repeat(pid, cnt)
        samples += len(ps)
        p = []
        for c in range(3):
            x = dp[c].take(ps)
            x *= kf
            x += p0[c].take(ps)
            p.append(np.clip(x, 0.0, top[c], out=x))
        cell = _cell(shape, p)
        val = _trilinear(flat, cell)
        nval = dn.take(ps)
        nval *= kf
        nval += n0.take(ps)
        rgba = _classify(scene, val, nval)
        a = rgba[3]
        if scene.shading:
            lit = np.flatnonzero(a > 0)
            sub = (cell[0].take(lit), cell[1], [f.take(lit) for f in cell[2]])
            gi = _directions(scene.normals, sub)  # voxel space, unit = 127
            g = [gi[0] * m_lin[0, c] + gi[1] * m_lin[1, c] + gi[2] * m_lin[2, c] for c in range(3)]
            ls = ps.take(lit)
            dot = g[0] * wdir[0].take(ls) + g[1] * wdir[1].take(ls) + g[2] * wdir[2].take(ls)
            gn = np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
            cos = np.abs(dot) / np.maximum(gn, np.float32(1e-30))
            shade = np.float32(SHADE_AMBIENT) + np.float32(1.0 - SHADE_AMBIENT) * cos
            strong = (gi * gi).sum(0) > (MIN_DIRECTION * 127) ** 2
            shade = np.where(strong, shade, np.float32(1.0))
            for c in range(3):
                rgba[c, lit] *= shade

        # front to back within the round: rays in rows, their samples in columns
        rows = len(rid)
        width = int(per_ray.max()) + 1
        row = np.repeat(np.arange(rows), per_ray)
        at = row * width + _within(per_ray)
        keep = np.ones(rows * width, np.float32)
        keep[at + 1] = 1.0 - a
        keep = np.cumprod(keep.reshape(rows, width), axis=1).ravel()
        t_ray = trans[rid]
        t_row = t_ray.take(row)
        before = keep.take(at) * t_row  # transmittance in front of each sample
        after = keep.take(at + 1) * t_row
        wgt = before * a
        starts = _starts(per_ray)
        for c in range(3):
            colour[c, rid] += np.add.reduceat(wgt * rgba[c], starts)
        half = np.flatnonzero((before > 0.5) & (after <= 0.5))
        depth[rid[row[half]]] = (j0[ps[half]] + kf[half]) * h
        t_ray *= keep.reshape(rows, width)[:, -1]
        trans[rid] = t_ray

        stopped = (1.0 - t_ray) >= EARLY_TERMINATION
        if stopped.any():  # the skipped samples behind a stopped ray were never reached
            at_piece = upto[stopped] - 1
            behind = sel[at_piece] + 1
            skipped -= int((empty[piece_end[stopped]] - empty[behind]).sum())
            tail = dense_skipped.ravel()
            rs = rid[stopped]
            skipped -= int((tail[rs * kseg + kseg - 1] - tail[rs * kseg + bseg[at_piece]]).sum())
        going = ~stopped & (upto < last)
        rid, ptr, last, piece_end = rid[going], upto[going], last[going], piece_end[going]
        # next round: twice this one, or fewer if the opacity gathered so far says the
        # ray is near its end (samples taken x ln(T / T_end) / -ln(T))
        taken = taken[going] + per_ray[going]
        t_left = t_ray[going].astype(np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            need = taken * np.log(t_left / (1.0 - EARLY_TERMINATION)) / -np.log(t_left)
        need = np.where(t_left < 1.0, np.ceil(np.minimum(need, ROUND_MAX)), ROUND_MAX)
        budget = np.clip(np.minimum(2 * budget[going], need), ROUND_FIRST, ROUND_MAX)
        budget = budget.astype(np.int64)
    return result(samples, skipped)


def composite_over(layers, behind_colour, behind_alpha):
    """Composite volume layers over what lies behind them, nearest first per ray.

    Parameters
    ----------
    layers : list of VolumeResult for the same R rays.
    behind_colour : (R, 3) float, premultiplied by ``behind_alpha``.
    behind_alpha : (R,) float.

    Returns
    -------
    colour : (R, 3) float32, premultiplied. alpha : (R,) float32.
    depth : (R,) float64, arc length where the layers' accumulated opacity reached 0.5
        (inf where it did not).
    """
    r = len(behind_alpha)
    col = np.zeros((r, 3))
    acc = np.zeros(r)
    depth = np.full(r, np.inf)
    if layers:
        entries = np.stack([lay.entry for lay in layers])  # (L, R)
        order = np.argsort(entries, axis=0, kind="stable")
        rows = np.arange(r)
        cols = np.stack([lay.colour for lay in layers]).astype(np.float64)
        alps = np.stack([lay.alpha for lay in layers]).astype(np.float64)
        deps = np.stack([lay.depth for lay in layers])
        for rank in range(len(layers)):
            li = order[rank]
            c, a_l, d = cols[li, rows], alps[li, rows], deps[li, rows]
            col += (1.0 - acc)[:, None] * c
            depth = np.where(np.isinf(depth) & (acc + (1 - acc) * a_l >= 0.5), d, depth)
            acc = acc + (1.0 - acc) * a_l
    col += (1.0 - acc)[:, None] * np.asarray(behind_colour, np.float64)
    acc = acc + (1.0 - acc) * np.asarray(behind_alpha, np.float64)
    return col.astype(np.float32), acc.astype(np.float32), depth
