"""Direct volume rendering along bent rays (paper section 5.2), pure numpy.

A scalar volume is a dense (nx, ny, nz) array of values normalised to [0, 1] and an
affine map from world points to continuous voxel coordinates (an integer coordinate is
a voxel centre). Each camera has a transfer function, sampled into a lookup table of
RGBA rows over [0, 1]; its alpha is the opacity of one voxel length of material.

Rays are the polylines of a ``RayBundle``. Every ray is sampled at arc lengths
``j * step`` from its vertex 0 (a lattice fixed to the ray, so skipping samples never
shifts the others). At each sample the value is interpolated trilinearly, every
camera's table is read, and the tables are blended with eq. 6's weights w(N, i) of the
membership N interpolated along the polyline there; the opacity is corrected for the
step, optionally shaded by the gradient, and composited front to back. All rays of a
chunk step together; each keeps its own arc position, so a ray can jump across a block
of voxels that every transfer function makes transparent (empty-space skipping) and
stops once nearly opaque (early termination).
"""

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .errors import Cancelled
from .field import blend_weights

# Rows of a transfer function's lookup table: finer than 8-bit data, and a ramp's
# interpolation between them is linear, as ColorRamp's own LINEAR mode.
TABLE_SIZE = 256
# A ray stops once its accumulated opacity reaches this: what lies behind could change
# its colour by at most 0.5% of full scale.
EARLY_TERMINATION = 0.995
# Voxels per side of the blocks used for empty-space skipping: small enough to hug thin
# structures, large enough that a jump saves many samples.
BLOCK = 8
# Blocks per side of a coarse block: a ray in a wholly empty coarse block crosses it in
# one jump (in the sample phantom, 3.5 skipping passes per sampling pass without it).
COARSE = 4
# Share of a gradient-shaded sample's colour that does not depend on its orientation.
SHADE_AMBIENT = 0.35
# Vertices x rays processed at once: bounds the memory of a chunk's polylines
# (about 100 MB of float64 index-space copies).
CHUNK_VERTICES = 1 << 21


@dataclass(frozen=True)
class ScalarVolume:
    """A dense scalar volume placed in the world.

    Attributes
    ----------
    values : (nx, ny, nz) float32 in [0, 1], the transfer functions' domain.
    world_to_index : (4, 4) float64 affine map from world points (Blender units) to
        continuous voxel coordinates; voxel (i, j, k)'s centre is (i, j, k).
    name : str, for messages.
    """

    values: np.ndarray
    world_to_index: np.ndarray
    name: str = "volume"

    @property
    def shape(self):
        return self.values.shape

    @property
    def voxel_size(self):
        """World length of the shortest voxel edge (the unit of ``step`` and of a
        transfer function's opacity)."""
        edges = np.linalg.inv(self.world_to_index)[:3, :3]
        return float(np.linalg.norm(edges, axis=0).min())

    def corners(self):
        """(8, 3) float64 world corners of the volume's box (voxel faces)."""
        n = np.array(self.shape, dtype=np.float64)
        c = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T
        idx = c * n - 0.5
        m = np.linalg.inv(self.world_to_index)
        return idx @ m[:3, :3].T + m[:3, 3]


def box_to_index(shape, box_min, box_max, matrix_world):
    """World-to-voxel map of a volume that fills an object's local box exactly.

    Parameters
    ----------
    shape : (3,) int, voxels (nx, ny, nz). box_min, box_max : (3,) float, the object's
        local bounding box. matrix_world : (4, 4) float, object to world.

    Returns
    -------
    (4, 4) float64: voxel (i, j, k) is the cell of size (box_max - box_min) / shape
    whose centre is box_min + (i + 0.5, j + 0.5, k + 0.5) * cell.
    """
    n = np.asarray(shape, dtype=np.float64)
    lo = np.asarray(box_min, dtype=np.float64)
    size = np.asarray(box_max, dtype=np.float64) - lo
    if (size <= 0).any():
        raise ValueError("the box is flat")
    local = np.eye(4)
    local[:3, :3] = np.diag(n / size)
    local[:3, 3] = -lo * n / size - 0.5
    return local @ np.linalg.inv(np.asarray(matrix_world, dtype=np.float64))


def normalise(values, value_range=None):
    """Values mapped linearly to [0, 1] float32 (clipped).

    value_range : (lo, hi) or None for the data's own minimum and maximum.
    """
    a = np.asarray(values)
    if value_range is None:
        lo, hi = float(np.nanmin(a)), float(np.nanmax(a))
    else:
        lo, hi = map(float, value_range)
    scale = 1.0 / (hi - lo) if hi > lo else 0.0
    out = (a.astype(np.float32) - np.float32(lo)) * np.float32(scale)
    np.clip(out, 0.0, 1.0, out=out)
    return np.nan_to_num(out, copy=False)


def table_from_points(points, size=TABLE_SIZE):
    """A transfer-function table from control points, linearly interpolated.

    points : sequence of (position in [0, 1], (r, g, b, a)).

    Returns
    -------
    (size, 4) float32, row t at value t / (size - 1).
    """
    pos = np.array([p for p, _c in points], dtype=np.float64)
    col = np.array([c for _p, c in points], dtype=np.float64)
    x = np.linspace(0.0, 1.0, size)
    return np.stack([np.interp(x, pos, col[:, c]) for c in range(4)], axis=1).astype(np.float32)


# The default transfer function: air transparent, then a faint warm grey rising to an
# opaque white at the top of the range (a generic CT-like look).
DEFAULT_POINTS = (
    (0.0, (0.0, 0.0, 0.0, 0.0)),
    (0.1, (0.0, 0.0, 0.0, 0.0)),
    (0.5, (0.8, 0.55, 0.45, 0.05)),
    (1.0, (1.0, 1.0, 1.0, 0.6)),
)


def default_table(size=TABLE_SIZE):
    """(size, 4) float32, the default transfer function (``DEFAULT_POINTS``)."""
    return table_from_points(DEFAULT_POINTS, size)


def block_ranges(values, block=BLOCK):
    """Per-block minimum and maximum of the values trilinear sampling can read.

    A sample at voxel coordinates p (clamped to the volume) lies in block floor(p /
    block) and reads voxels floor(p) and floor(p) + 1, so each block's range covers its
    own voxels and the next layer of voxels along each axis. Computed one x-row of
    blocks at a time (temporaries of a few layers).

    Returns
    -------
    lo, hi : (bx, by, bz) float32, bx = ceil(nx / block).
    """
    v = np.asarray(values, dtype=np.float32)
    nx = v.shape[0]
    rows_lo, rows_hi = [], []
    for a in range(0, nx, block):
        sub = v[a : min(a + block + 1, nx)]
        for op, rows in ((np.minimum, rows_lo), (np.maximum, rows_hi)):
            layer = op.reduce(sub, axis=0)  # (ny, nz), the x apron included
            layer = op(layer, np.concatenate([layer[1:], layer[-1:]], axis=0))
            layer = op(layer, np.concatenate([layer[:, 1:], layer[:, -1:]], axis=1))
            rows.append(_block_reduce(layer[None], block, op)[0])
    return np.stack(rows_lo), np.stack(rows_hi)


def _block_reduce(a, block, op):
    """Reduce (1, ny, nz) over block x block tiles of its last two axes (edge-padded)."""
    pad = [(0, 0)] + [(0, (-s) % block) for s in a.shape[1:]]
    a = np.pad(a, pad, mode="edge")
    _, ny, nz = a.shape
    a = a.reshape(1, ny // block, block, nz // block, block)
    return op.reduce(op.reduce(a, axis=4), axis=2)


def coarse_blocks(occupied, factor=COARSE):
    """(cx, cy, cz) bool: whether any block of each ``factor``^3 group is occupied."""
    pad = [(0, (-n) % factor) for n in occupied.shape]
    a = np.pad(occupied, pad)
    cx, cy, cz = (n // factor for n in a.shape)
    return a.reshape(cx, factor, cy, factor, cz, factor).any(axis=(1, 3, 5))


def occupied_blocks(lo, hi, tables):
    """(bx, by, bz) bool: blocks where some transfer function gives some opacity.

    lo, hi : block value ranges (``block_ranges``). tables : (N, T, 4) float32.
    """
    t = tables.shape[1]
    alpha = tables[:, :, 3].max(axis=0)
    # range_max[a, b] = max(alpha[a..b]) for a <= b
    upper = np.triu(np.ones((t, t), dtype=bool))
    range_max = np.maximum.accumulate(np.where(upper, alpha[None, :], 0.0), axis=1)
    a = np.clip(np.floor(lo * (t - 1)).astype(np.int64), 0, t - 1)
    b = np.clip(np.ceil(hi * (t - 1)).astype(np.int64), 0, t - 1)
    return range_max[a, b] > 0


# Gradients shorter than this (value units per voxel) are noise of a uniform material:
# they get no direction, and samples near them stay unshaded.
MIN_GRADIENT = 1e-3
# An interpolated direction shorter than this (of unit length at best) means the
# neighbouring voxels disagree or have none: such a sample stays unshaded.
MIN_DIRECTION = 0.25


def gradient_directions(values, slab=16):
    """Unit gradient directions of a volume, quantised for shading.

    Central differences on the grid (one-sided at the faces), in voxel units,
    normalised and scaled to int8 (127 = 1); zero where the gradient is shorter than
    ``MIN_GRADIENT``. Computed ``slab`` x-layers at a time, so the temporaries stay a
    small part of the volume's own size.

    Returns
    -------
    (nx * ny * nz,) int32 in the C order of ``values``, each the four bytes (gx, gy, gz,
    0) as int8: one gather fetches a voxel's direction (view as (P, 4) int8).
    """
    v = np.asarray(values, dtype=np.float32)
    nx = v.shape[0]
    out = np.zeros(v.shape + (4,), dtype=np.int8)
    for a in range(0, nx, slab):
        b = min(a + slab, nx)
        lo, hi = max(a - 1, 0), min(b + 1, nx)
        part = v[lo:hi]
        g = np.zeros(part.shape + (3,), dtype=np.float32)
        for axis in range(3):
            if part.shape[axis] > 1:
                g[..., axis] = np.gradient(part, axis=axis)
        g = g[a - lo : a - lo + (b - a)]
        n = np.sqrt((g * g).sum(-1, keepdims=True))
        scale = np.where(n > MIN_GRADIENT, np.float32(127.0) / np.maximum(n, 1e-30), 0.0)
        out[a:b, ..., :3] = np.rint(g * scale.astype(np.float32))
    return out.reshape(-1, 4).view(np.int32).ravel()


@dataclass
class VolumeScene:
    """One volume ready to render with a rig's transfer functions (built once per frame).

    volume : ScalarVolume. tables : (N, T, 4) float32, camera i's table in row i.
    occupied : (bx, by, bz) bool (``occupied_blocks``). step : float, samples apart in
    voxels. shading : bool, gradient shading. cubic : bool, eq. 6's cubic weights.
    normals : (nx * ny * nz,) int32 or None, ``gradient_directions`` (when shading).
    """

    volume: ScalarVolume
    tables: np.ndarray
    occupied: np.ndarray
    step: float = 1.0
    shading: bool = False
    cubic: bool = False
    normals: np.ndarray = None
    coarse: np.ndarray = None

    def __post_init__(self):
        if self.coarse is None:
            self.coarse = coarse_blocks(self.occupied)

    @classmethod
    def build(cls, volume, tables, step=1.0, shading=False, cubic=False, ranges=None, normals=None):
        """Prepare ``volume`` for rendering; ``ranges`` are its ``block_ranges`` and
        ``normals`` its ``gradient_directions`` if known (else they are computed)."""
        tables = np.ascontiguousarray(tables, dtype=np.float32)
        if tables.ndim != 3 or tables.shape[2] != 4 or tables.shape[1] < 2:
            raise ValueError(f"tables must be (N, T >= 2, 4), got {tables.shape}")
        if not step > 0:
            raise ValueError(f"the step must be positive, got {step}")
        lo, hi = ranges if ranges is not None else block_ranges(volume.values)
        if shading and normals is None:
            normals = gradient_directions(volume.values)
        occupied = occupied_blocks(lo, hi, tables)
        return cls(volume, tables, occupied, float(step), shading, cubic, normals)


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


def _extended(vertices, reach):
    """(R, K+1, 3) float32: the polylines with their last segment run on by ``reach``."""
    v = np.asarray(vertices, dtype=np.float32)
    last = (v[:, -1] - v[:, -2]).astype(np.float64)
    n = np.linalg.norm(last, axis=-1, keepdims=True)
    last = np.where(n > 0, last / np.where(n > 0, n, 1.0), 0.0)
    end = v[:, -1] + last * np.asarray(reach, dtype=np.float64)[:, None]
    return np.concatenate([v, end[:, None].astype(np.float32)], axis=1)


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
        colour[sl], alpha[sl], entry[sl], depth[sl] = out[:4]
        samples += out[4]
        skipped += out[5]
    return VolumeResult(colour, alpha, entry, depth, samples, skipped)


def _cell(strides, shape, q):
    """Base voxel index (P,) int64, the seven other corners' offsets and the fractions
    (P, 3) float32 of clamped voxel coordinates q (P, 3) inside [0, n - 1]."""
    top = np.array([max(n - 2, 0) for n in shape])
    i0 = np.minimum(q.astype(np.int64), top)
    f = (q - i0).astype(np.float32)
    base = i0 @ np.asarray(strides, dtype=np.int64)
    ox, oy, oz = (st * (n > 1) for st, n in zip(strides, shape))
    return base, (0, ox, oy, ox + oy, oz, ox + oz, oy + oz, ox + oy + oz), f


def _fetch(flat, index):
    """float32 values of ``flat`` at ``index``; packed directions (int32) as (P, 3)."""
    if flat.dtype == np.int32:
        return flat[index].view(np.int8).reshape(-1, 4)[:, :3].astype(np.float32)
    return flat[index].astype(np.float32, copy=False)


def _trilinear(flat, cell):
    """(P,) trilinear samples of a flat C-ordered array (or (P, 3) of packed directions,
    ``gradient_directions``) in the cells ``_cell`` gave."""
    base, offsets, f = cell
    c = [_fetch(flat, base + off) for off in offsets]
    if c[0].ndim > 1:
        f = f[:, None, :]
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    c00 = c[0] + (c[1] - c[0]) * fx
    c10 = c[2] + (c[3] - c[2]) * fx
    c01 = c[4] + (c[5] - c[4]) * fx
    c11 = c[6] + (c[7] - c[6]) * fx
    c0 = c00 + (c10 - c00) * fy
    c1 = c01 + (c11 - c01) * fy
    return c0 + (c1 - c0) * fz


def corrected_tables(tables, step):
    """Tables with alpha corrected for a step of ``step`` voxels: 1 - (1 - a)^step."""
    out = np.array(tables, dtype=np.float32, copy=True)
    out[..., 3] = 1.0 - np.power(np.clip(1.0 - out[..., 3], 0.0, 1.0), step)
    return out


def _classify(scene, tables, val, nval):
    """(P, 4) float32 RGBA of values ``val`` under the tables blended by eq. 6 at
    memberships ``nval``; alpha already corrected for the step."""
    ncam, tsize = tables.shape[:2]
    x = np.clip(val, 0.0, 1.0).astype(np.float32) * np.float32(tsize - 1)
    lo = np.minimum(x.astype(np.int32), tsize - 2)
    t = (x - lo)[:, None]
    if ncam == 1:
        return tables[0, lo] * (1 - t) + tables[0, lo + 1] * t
    w = blend_weights(nval, ncam, scene.cubic)
    w = (w / np.maximum(w.sum(0), 1e-30)).astype(np.float32)
    rgba = np.zeros((len(val), 4), dtype=np.float32)
    for i in range(ncam):
        used = w[i] > 0
        count = int(np.count_nonzero(used))
        if count == len(val):
            rgba += w[i, :, None] * (tables[i, lo] * (1 - t) + tables[i, lo + 1] * t)
        elif count:
            sel = np.flatnonzero(used)
            li, ti = lo[sel], t[sel]
            rgba[sel] += w[i, sel, None] * (tables[i, li] * (1 - ti) + tables[i, li + 1] * ti)
    return rgba


# Consecutive samples each ray takes per pass of the marching loop: amortises numpy's
# per-call cost; a ray that turns opaque mid-pass wastes at most this many - 1 samples.
SAMPLES_PER_PASS = 4


def _march_chunk(scene, vertices, membership, reach, stop):
    vol = scene.volume
    values = vol.values
    shape = values.shape
    flat = values.ravel()
    strides = (shape[1] * shape[2], shape[2], 1)
    m = vol.world_to_index
    voxel = vol.voxel_size
    h = scene.step * voxel
    r = len(vertices)
    tables = corrected_tables(scene.tables, scene.step)

    vw = _extended(vertices, reach)  # (R, K1, 3) world, float32
    k1 = vw.shape[1]
    dw = np.diff(vw, axis=1)
    seglen = np.sqrt((dw * dw).sum(-1))  # (R, K1-1) float32
    cum = np.zeros((r, k1))
    np.cumsum(seglen, axis=1, dtype=np.float64, out=cum[:, 1:])
    m3 = m[:3, :3].T.astype(np.float32)
    vi = vw @ m3 + m[:3, 3].astype(np.float32)  # voxel space
    del vw
    dvi = dw @ m3  # voxel units per world unit once divided by the length
    del dw
    np.divide(dvi, seglen[..., None], out=dvi, where=seglen[..., None] > 0)
    dvi[seglen == 0] = 0.0
    mem = np.concatenate([membership, membership[:, -1:]], axis=1).astype(np.float64)

    # the arc-length interval each ray spends in the box: segments whose ends are both
    # beyond the same face (Cohen-Sutherland outcodes) cannot touch it; slab-test the rest
    below = vi < -0.5
    above = vi > np.array(shape, dtype=np.float32) - 0.5
    beyond = (below[:, :-1] & below[:, 1:]) | (above[:, :-1] & above[:, 1:])
    cand = np.flatnonzero(~beyond.any(axis=-1) & (seglen > 0))
    t0, t1 = _box_interval(vi[:, :-1].reshape(-1, 3)[cand], dvi.reshape(-1, 3)[cand], shape)
    t0 = np.maximum(t0, 0.0)
    t1 = np.minimum(t1, seglen.ravel()[cand])
    hit = t1 >= t0
    start = cum[:, :-1].ravel()[cand]
    enter = np.full(r * (k1 - 1), np.inf)
    leave = np.full(r * (k1 - 1), -np.inf)
    enter[cand] = np.where(hit, start + t0, np.inf)
    leave[cand] = np.where(hit, start + t1, -np.inf)
    s_in = enter.reshape(r, k1 - 1).min(axis=1)
    s_out = np.minimum(leave.reshape(r, k1 - 1).max(axis=1), stop)
    j0 = np.ceil(s_in / h)
    alive = np.isfinite(s_in) & (j0 * h <= s_out)

    colour = np.zeros((r, 3), dtype=np.float32)
    alpha = np.zeros(r, dtype=np.float32)
    entry = np.full(r, np.inf)
    depth = np.full(r, np.inf)
    samples = skipped = 0
    rows = np.flatnonzero(alive)
    if not len(rows):
        return colour, alpha, entry, depth, 0, 0
    s = j0[rows] * h
    entry[rows] = s
    # flat per-vertex arrays: row r's vertex k at r * k1 + k
    cum_f = cum.ravel()
    vi_f = vi.reshape(-1, 3)
    dvi_f = np.concatenate([dvi, np.zeros((r, 1, 3), np.float32)], axis=1).reshape(-1, 3)
    len_f = np.concatenate([seglen, np.ones((r, 1), np.float32)], axis=1).ravel()
    mem_f = mem.ravel()
    # one searchsorted finds every sample's segment: rows are offset by more than a ray
    span = float(cum[:, -1].max()) + 1.0
    keys = (cum + np.arange(r)[:, None] * span).ravel()
    inv = np.linalg.inv(m)[:3, :3]
    block = BLOCK
    occ = scene.occupied
    bshape = np.array(occ.shape)
    bstride = np.array([bshape[1] * bshape[2], bshape[2], 1])
    occ_flat = occ.ravel()
    coarse = scene.coarse
    cshape = np.array(coarse.shape)
    cstride = np.array([cshape[1] * cshape[2], cshape[2], 1])
    coarse_flat = coarse.ravel()
    n_hi = np.array(shape, dtype=np.float64) - 1
    steps = np.arange(SAMPLES_PER_PASS) * h

    def search(sv, rv):
        """Flat index of the segment holding arc length ``sv`` of rays ``rv``."""
        base = rv * k1
        kk = np.searchsorted(keys, sv + rv * span, side="right") - 1 - base
        return np.clip(kk, 0, k1 - 2) + base

    def advance(fi, sv, rv):
        """The segment holding ``sv``, from a segment ``fi`` at or before it: a step
        crosses at most a vertex or two, so two cheap moves, then a search for the rest."""
        last = rv * k1 + k1 - 2
        for _ in range(2):
            late = (sv > cum_f[fi + 1]) & (fi < last)
            if not late.any():
                return fi
            fi = fi + late
        late = np.flatnonzero((sv > cum_f[fi + 1]) & (fi < last))
        if len(late):
            fi[late] = search(sv[late], rv[late])
        return fi

    def locate(fi, sv):
        """Offset along segments ``fi``, their direction and the voxel position at
        arc lengths ``sv``."""
        local = sv - cum_f[fi]
        d = dvi_f[fi]
        return local, d, vi_f[fi] + local[:, None] * d

    seg = search(s, rows)
    while len(rows):
        fi0 = seg = advance(seg, s, rows)
        _local0, d0, p0 = locate(fi0, s)
        # a bent ray may leave the box and come back: samples outside it read nothing
        inside0 = ((p0 >= -0.5) & (p0 <= n_hi + 0.5)).all(axis=1)
        pc0 = np.clip(p0, 0.0, n_hi)
        b0 = np.minimum((pc0 * (1.0 / block)).astype(np.int64), bshape - 1)
        busy = occ_flat[b0 @ bstride] | ~inside0
        next_s = s + SAMPLES_PER_PASS * h

        # the first sample in an empty block: jump to the first lattice sample past the
        # block (or past the segment, where the direction changes)
        free = np.flatnonzero(~busy)
        if len(free):
            df = d0[free]
            bf = b0[free]
            cb = bf // COARSE
            wide = ~coarse_flat[cb @ cstride]  # the whole coarse block is empty
            size = np.where(wide, block * COARSE, block).astype(np.float64)[:, None]
            lo_b = np.where(wide[:, None], cb * COARSE, bf) * float(block)
            pf = p0[free]
            with np.errstate(divide="ignore", invalid="ignore"):
                exit_t = np.where(
                    df > 0, (lo_b + size - pf) / df, np.where(df < 0, (lo_b - pf) / df, np.inf)
                ).min(axis=1)
            sf = s[free]
            jump = np.minimum(np.maximum(exit_t, 0.0), cum_f[fi0[free] + 1] - sf)
            target = np.maximum(np.ceil((sf + jump) / h) * h, sf + h)
            skipped += int(np.round((target - sf) / h).sum()) - len(free)
            next_s[free] = target

        # otherwise: sample, classify and composite SAMPLES_PER_PASS samples
        on = np.flatnonzero(busy)
        if len(on):
            ro = rows[on]
            sj = (s[on, None] + steps).ravel()
            rj = np.repeat(ro, SAMPLES_PER_PASS)
            fo = advance(np.repeat(fi0[on], SAMPLES_PER_PASS), sj, rj)
            local, d, p = locate(fo, sj)
            ok = ((p >= -0.5) & (p <= n_hi + 0.5)).all(axis=1) & (sj <= s_out[rj])
            cell = _cell(strides, shape, np.clip(p, 0.0, n_hi))
            val = _trilinear(flat, cell)
            t = np.clip(local / len_f[fo], 0.0, 1.0)
            nval = mem_f[fo] + (mem_f[fo + 1] - mem_f[fo]) * t
            rgba = _classify(scene, tables, val, nval)
            rgba[:, 3] *= ok
            samples += int(ok.sum())
            rgb = rgba[:, :3]
            if scene.shading:
                lit = np.flatnonzero(rgba[:, 3] > 0)
                sub = (cell[0][lit], cell[1], cell[2][lit])
                gi = _trilinear(scene.normals, sub)  # voxel space, unit = 127
                g = gi @ m[:3, :3].astype(np.float32)
                gn = np.linalg.norm(g, axis=1)
                dw = (d[lit] @ inv.T).astype(np.float32)  # unit world direction
                cos = np.abs((g * dw).sum(1)) / np.maximum(gn, 1e-30)
                shade = SHADE_AMBIENT + (1.0 - SHADE_AMBIENT) * cos
                length = np.linalg.norm(gi, axis=1)
                shade = np.where(length > MIN_DIRECTION * 127, shade, 1.0)
                rgb[lit] *= shade[:, None].astype(rgb.dtype)
            rgb = rgb.reshape(len(on), SAMPLES_PER_PASS, 3)
            a_s = rgba[:, 3].reshape(len(on), SAMPLES_PER_PASS)
            acc = alpha[ro]
            col = colour[ro]
            dep = depth[ro]
            s_on = s[on]
            for j in range(SAMPLES_PER_PASS):
                w = (1.0 - acc) * a_s[:, j]
                col += w[:, None] * rgb[:, j]
                new = acc + w
                dep = np.where((acc < 0.5) & (new >= 0.5), s_on + j * h, dep)
                acc = new
            alpha[ro], colour[ro], depth[ro] = acc, col, dep
            next_s[on[acc >= EARLY_TERMINATION]] = np.inf

        s = next_s
        keep = s <= s_out[rows]
        rows, s, seg = rows[keep], s[keep], seg[keep]
    return colour, alpha, entry, depth, samples, skipped


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
