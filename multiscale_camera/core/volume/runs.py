"""The segment stage of the volume march, pure numpy: every segment of every ray of a
chunk is tested against the blocks of voxels that the cameras its membership can weigh
make visible, and cut into pieces of samples, so that only the samples of occupied
pieces are taken (empty-space skipping).
"""

from dataclasses import dataclass

import numpy as np

from .scene import BLOCK, camera_runs

# A piece (the run of samples tested against the blocks at once) spans at most this
# many voxels: the box of its first and last sample then meets at most 2 blocks a side.
PIECE_VOXELS = BLOCK

# A membership this close to an integer i is taken as i when the tables are blended:
# the solved field's float noise (up to 1e-3 seen) would otherwise leave a preserved
# region's neighbouring camera a weight of that size, and with it that camera's opaque
# blocks, which then could not be skipped.
MEMBERSHIP_SNAP = 1e-3
# Rounding allowed for between a piece's end memberships and its samples' ones.
MEMBERSHIP_ROUNDING = 1e-5


@dataclass(frozen=True)
class Runs:
    """The lattice samples of a chunk's rays that may be visible, as C runs along
    straight segments of the polylines, in ray then arc order (``_runs``).

    ray, seg : (C,) int64, the ray (within the chunk) and its segment.
    j : (C,) int64, the lattice index of the run's first sample (arc length j * h).
    n : (C,) int64, samples in the run (>= 1).
    p, dp : (3, C) float64, voxel units: the first sample's position and the step from
        one sample to the next.
    nm, dnm : (C,) float64, the membership at the first sample and its change per sample.
    sure : (C,) bool, the run is one piece already known to be occupied.
    direction : (3, C) float32, the segment's unit direction, world space.
    """

    ray: np.ndarray
    seg: np.ndarray
    j: np.ndarray
    n: np.ndarray
    p: np.ndarray
    dp: np.ndarray
    nm: np.ndarray
    dnm: np.ndarray
    sure: np.ndarray
    direction: np.ndarray


@dataclass(frozen=True)
class Pieces:
    """Runs cut into P pieces of at most ``_per_piece`` samples, in ray then arc order
    (``_pieces``).

    run : (P,) int64, the piece's run (an index into ``Runs``' arrays).
    i : (P,) int64, the piece's first sample within its run.
    count : (P,) int64, samples in the piece (>= 1).
    busy : (P,) bool, the piece's box of blocks holds a block occupied under the
        cameras its membership can weigh.
    """

    run: np.ndarray
    i: np.ndarray
    count: np.ndarray
    busy: np.ndarray


def _box_interval(p, d, n):
    """Slab test of segments against the volume's box [-0.5, n - 0.5] in voxel space.

    p : (..., 3) start points; d : (..., 3) direction per unit of the segment parameter.
    Returns t0, t1 (...,): the parameter interval inside the box (t0 > t1 when missed).
    A zero component of d gives infinities of the right signs (inside that slab: the
    whole line; outside: nothing); NaN (a start exactly on a face) is ignored.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        a = (-0.5 - p) * inv
        b = (np.asarray(n, dtype=p.dtype) - 0.5 - p) * inv
    near = np.fmin(a, b)
    far = np.fmax(a, b)
    return np.fmax(np.fmax(near[..., 0], near[..., 1]), near[..., 2]), np.fmin(
        np.fmin(far[..., 0], far[..., 1]), far[..., 2]
    )


def _starts(counts):
    """(M,) int64 exclusive running sum of ``counts`` (where each group begins)."""
    out = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=out[1:])
    return out


def _within(counts):
    """(sum(counts),) int64: 0, 1, ..., counts[g] - 1 for each group g in turn."""
    total = int(counts.sum())
    return np.arange(total, dtype=np.int64) - np.repeat(_starts(counts), counts)


def _planes(vertices, reach):
    """(3, R, K + 1) float32 world x, y, z of the polylines, the last segment run on by
    ``reach`` (R,)."""
    v = np.asarray(vertices, dtype=np.float32)
    r, k = v.shape[:2]
    out = np.empty((3, r, k + 1), np.float32)
    out[:, :, :k] = v.transpose(2, 0, 1)
    last = (v[:, -1] - v[:, -2]).astype(np.float64)
    n = np.linalg.norm(last, axis=-1, keepdims=True)
    last = np.where(n > 0, last / np.where(n > 0, n, 1.0), 0.0)
    out[:, :, k] = (v[:, -1] + last * np.asarray(reach, dtype=np.float64)[:, None]).T
    return out


def _camera_bounds(scene, low, high):
    """Lowest and highest camera (0-based, int32 arrays) whose table can have weight
    between memberships ``low`` and ``high`` (float32 arrays of one shape).

    Eq. 6 weighs camera i where |N - i| < 1 once N is snapped (``_snap``): cameras
    floor(N) and ceil(N), one of them within ``MEMBERSHIP_SNAP`` of an integer. The
    bounds are floor(low + snap) and ceil(high - snap) widened by
    ``MEMBERSHIP_ROUNDING`` (the highest taken as floor + 1, one more than needed at an
    exact integer), clamped to the cameras.
    """
    ncam = len(scene.tables)
    lo = (low + np.float32(MEMBERSHIP_SNAP - MEMBERSHIP_ROUNDING)).astype(np.int32)
    hi = (high - np.float32(MEMBERSHIP_SNAP - MEMBERSHIP_ROUNDING)).astype(np.int32)
    np.clip(lo, 1, ncam, out=lo)
    np.clip(hi, 0, ncam - 1, out=hi)
    lo -= 1
    return lo, hi


def _snap(nval):
    """(P,) float32 memberships, those within ``MEMBERSHIP_SNAP`` of an integer set to
    it."""
    whole = np.rint(nval)
    return np.where(np.abs(nval - whole) < MEMBERSHIP_SNAP, whole, nval).astype(np.float32)


def _occupied(scene, b0, b1, cams=None):
    """(P,) bool: whether the boxes of blocks between b0 and b1 hold a block occupied
    under the cameras ``cams`` (lo, hi) can weigh.

    b0, b1 : three (P,) int16 arrays each (or any one shape), block coordinates of two
    corners of each box. cams : two int32 arrays of that shape, the lowest and highest
    camera, or None (one camera).
    Boxes of at most two blocks a side take one read of ``scene.bits``, the others eight
    of ``scene.sums``.
    """
    bits = scene.bits
    _, bx, by, bz = bits.shape
    if cams is None:
        grid = np.zeros(np.shape(b0[0]), np.int32)
    else:
        n = len(scene.tables)
        table = camera_runs(n)(*np.divmod(np.arange(n * n), n)).astype(np.int32)
        grid = table.take(cams[0] * n + cams[1])
    lo = [np.minimum(p, q) for p, q in zip(b0, b1)]
    span = [np.abs(p - q) for p, q in zip(b0, b1)]
    variant = span[0] + 2 * span[1] + 4 * span[2]
    index = ((grid * bx + lo[0]) * by + lo[1]) * bz + lo[2]
    busy = (bits.ravel().take(index) >> np.minimum(variant, 7).astype(np.uint8)) & 1 > 0
    wide = np.nonzero((span[0] > 1) | (span[1] > 1) | (span[2] > 1))
    if len(wide[0]):
        _, sx, sy, sz = scene.sums.shape
        flat = scene.sums.ravel()
        g = grid[wide].astype(np.int64) * (sx * sy * sz)
        lo = [x[wide].astype(np.int64) for x in lo]
        hi = [lo[a] + span[a][wide] + 1 for a in range(3)]
        x0, x1 = lo[0] * (sy * sz) + g, hi[0] * (sy * sz) + g
        y0, y1 = lo[1] * sz, hi[1] * sz
        z0, z1 = lo[2], hi[2]
        a, b, c, d = x1 + y1, x0 + y1, x1 + y0, x0 + y0
        total = flat.take(a + z1) - flat.take(a + z0)
        total -= flat.take(b + z1) - flat.take(b + z0)
        total -= flat.take(c + z1) - flat.take(c + z0)
        total += flat.take(d + z1) - flat.take(d + z0)
        busy[wide] = total > 0
    return busy


def _blocks(shape, p):
    """Block coordinates (int16) of three coordinate arrays, clamped into the grid."""
    return [
        (np.clip(p[a], 0.0, shape[a] - 1) * np.float32(1.0 / BLOCK)).astype(np.int16)
        for a in range(3)
    ]


def _runs(scene, vertices, membership, reach, stop, h):
    """The lattice samples of each ray that may be visible, as runs along straight
    segments of the polylines.

    Every segment (the last one run on by ``reach``) is tested at once, in flat planes
    of one value per vertex (segment i runs from vertex i to i + 1): its ends in voxel
    space, whether it touches the box [-0.5, n - 0.5]
    (not both ends beyond one face), whether both ends are inside, and whether the box
    of blocks between its ends holds a block occupied under the cameras its membership
    can weigh. Segments that touch the box and are occupied or cross a face are clipped
    to the box and to the ray's ``stop`` and become runs: the samples j * h of their
    clipped arc interval [a, b) (half-open, so a sample on a vertex belongs to one
    segment). The samples of the other segments inside the box are skipped.

    Returns
    -------
    runs : Runs, or None when no segment needs sampling.
    skipped : (R, K + 1) int64, samples skipped so far along each ray (entry k counts
        the empty segments 0..k).
    entry : (R,) float64, arc length of each ray's first sample in the box (inf: none).
    """
    vol = scene.volume
    shape = vol.shape
    m = vol.world_to_index
    w = _planes(vertices, reach)
    r, k1 = w.shape[1:]
    nv = r * k1
    # flat planes: segment i runs from vertex i to i + 1 (none from a ray's last vertex)
    w = w.reshape(3, nv)
    d = np.zeros((3, nv), np.float32)
    np.subtract(w[:, 1:], w[:, :-1], out=d[:, :-1])
    d.reshape(3, r, k1)[:, :, -1] = 0.0
    seglen = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    vox = np.empty_like(w)
    for a in range(3):
        vox[a] = w[0] * float(m[a, 0])
        vox[a] += w[1] * float(m[a, 1])
        vox[a] += w[2] * float(m[a, 2])
        vox[a] += float(m[a, 3])
    del w
    beyond = np.zeros(nv, bool)
    inside = np.ones(nv, bool)
    for a in range(3):
        below = vox[a] < -0.5
        above = vox[a] > shape[a] - 0.5
        beyond[:-1] |= below[:-1] & below[1:]
        beyond[:-1] |= above[:-1] & above[1:]
        inside &= ~(below | above)
    touch = ~beyond & (seglen > 0)
    full = np.zeros(nv, bool)
    np.logical_and(inside[:-1], inside[1:], out=full[:-1])
    del beyond, inside, below, above
    blk = _blocks(shape, vox)
    mem = np.empty((r, k1), np.float32)
    mem[:, :-1] = membership
    mem[:, -1] = mem[:, -2]
    mem = mem.ravel()
    cams = None
    if len(scene.tables) > 1:
        cams = _camera_bounds(scene, np.minimum(mem[:-1], mem[1:]), np.maximum(mem[:-1], mem[1:]))
    busy = np.zeros(nv, bool)
    busy[:-1] = _occupied(scene, [b[:-1] for b in blk], [b[1:] for b in blk], cams)
    del blk, cams
    cum = np.zeros((r, k1))
    np.cumsum(seglen.reshape(r, k1)[:, :-1], axis=1, dtype=np.float64, out=cum[:, 1:])
    cum = cum.ravel()
    # samples of the empty segments wholly inside the box, up to the ray's stop
    first = np.ceil(cum / h).astype(np.int32)
    count = np.zeros(nv, np.int32)
    if np.isfinite(stop).any():
        ends = np.minimum(first.reshape(r, k1), np.ceil(stop / h).astype(np.int32)[:, None])
        np.subtract(ends.ravel()[1:], first[:-1], out=count[:-1])
        np.maximum(count, 0, out=count)
    else:
        np.subtract(first[1:], first[:-1], out=count[:-1])
    count *= touch & full & ~busy
    skipped = np.cumsum(count.reshape(r, k1), axis=1)
    entry = np.full(r, np.inf)
    seen = (count > 0).reshape(r, k1)
    has = seen.any(axis=1)
    at = seen.argmax(axis=1)[has]
    entry[has] = first.reshape(r, k1)[has, at] * h

    cand = np.flatnonzero(touch & (busy | ~full))
    if not len(cand):
        return None, skipped, entry
    v0 = cand
    ray, seg = np.divmod(cand, k1)
    a = np.stack([vox[c].ravel().take(v0) for c in range(3)]).astype(np.float64)
    dv = np.stack([vox[c].ravel().take(v0 + 1) for c in range(3)]) - a
    length = seglen.ravel().take(cand).astype(np.float64)
    start = cum.ravel().take(v0)
    u0 = np.zeros(len(cand))
    u1 = np.ones(len(cand))
    cross = np.flatnonzero(~full.ravel().take(cand))
    if len(cross):
        t0, t1 = _box_interval(a[:, cross].T, dv[:, cross].T, shape)
        u0[cross] = np.maximum(t0, 0.0)
        u1[cross] = np.minimum(t1, 1.0)
    sa = start + u0 * length
    sb = np.minimum(start + u1 * length, stop[ray])
    ja = np.ceil(sa / h)
    n = np.ceil(sb / h) - ja
    keep = np.flatnonzero(n > 0)
    if not len(keep):
        return None, skipped, entry
    ray, seg, cand, v0, a, dv, length, start, ja, n = (
        x[..., keep] for x in (ray, seg, cand, v0, a, dv, length, start, ja, n)
    )
    n = n.astype(np.int64)
    rise = h / length
    local = (ja * h - start) / length  # fraction of the segment before the first sample
    m0 = mem.ravel().take(v0).astype(np.float64)
    dm = mem.ravel().take(v0 + 1) - m0
    first_run = np.flatnonzero(np.r_[True, ray[1:] != ray[:-1]])
    entry[ray[first_run]] = np.minimum(entry[ray[first_run]], ja[first_run] * h)
    runs = Runs(
        ray=ray,
        seg=seg,
        j=ja.astype(np.int64),
        n=n,
        p=a + dv * local,
        dp=dv * rise,
        nm=m0 + dm * local,
        dnm=dm * rise,
        sure=full.ravel().take(cand) & (n <= _per_piece(scene)),
        direction=np.stack([d[c].ravel().take(cand) for c in range(3)]) / seglen.ravel().take(cand),
    )
    return runs, skipped, entry


def _per_piece(scene):
    """Samples in a piece: they span at most ``PIECE_VOXELS`` voxels."""
    return max(1, int(PIECE_VOXELS / scene.step))


def _pieces(scene, runs):
    """Cut runs into pieces of at most ``_per_piece`` samples and test each piece's box
    of blocks (its first and last sample's) under the cameras its membership can weigh.

    Parameters
    ----------
    scene : VolumeScene. runs : Runs.

    Returns
    -------
    Pieces
    """
    per = _per_piece(scene)
    n = runs.n
    pcs = -(-n // per)
    run = np.repeat(np.arange(len(n)), pcs)
    i = _within(pcs) * per
    count = np.minimum(per, n.take(run) - i)
    busy = runs.sure.take(run)
    test = np.flatnonzero(~busy)
    if len(test):
        rt, it, ct = run[test], i[test], count[test]
        p = [runs.p[c].take(rt) + it * runs.dp[c].take(rt) for c in range(3)]
        q = [p[c] + (ct - 1) * runs.dp[c].take(rt) for c in range(3)]
        bp, bq = _blocks(scene.volume.shape, p), _blocks(scene.volume.shape, q)
        cams = None
        if len(scene.tables) > 1:
            n0 = runs.nm.take(rt) + it * runs.dnm.take(rt)
            n1 = n0 + (ct - 1) * runs.dnm.take(rt)
            low = np.minimum(n0, n1).astype(np.float32)
            cams = _camera_bounds(scene, low, np.maximum(n0, n1).astype(np.float32))
        busy[test] = _occupied(scene, bp, bq, cams)
    return Pieces(run=run, i=i, count=count, busy=busy)
