"""Direct volume rendering along bent rays (paper section 5.2), pure numpy.

A scalar volume is a dense (nx, ny, nz) array of values normalised to [0, 1] and an
affine map from world points to continuous voxel coordinates (an integer coordinate is
a voxel centre). Each camera has a transfer function, sampled into a lookup table of
RGBA rows over [0, 1]; its alpha is the opacity of one voxel length of material.

Rays are the polylines of a ``RayBundle``. Every ray is sampled at arc lengths
``j * step`` from its vertex 0 (a lattice fixed to the ray, so skipping samples never
shifts the others). At each sample the value is interpolated trilinearly, the tables
of the one or two cameras next to the membership N interpolated along the polyline
there are read and blended with eq. 6's weights w(N, i); the opacity is corrected for
the step, optionally shaded by the gradient, and composited front to back.

A chunk of rays is handled in bulk: every segment of every ray is tested against the
blocks of voxels that the cameras its membership can weigh make visible, and only the
samples of occupied pieces are taken (empty-space skipping), in rounds of growing
size per ray until it is nearly opaque (early termination).
"""

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .errors import Cancelled

# Rows of a transfer function's lookup table: finer than 8-bit data, and a ramp's
# interpolation between them is linear, as ColorRamp's own LINEAR mode.
TABLE_SIZE = 256
# A ray stops once its accumulated opacity reaches this: what lies behind could change
# its colour by at most 0.5% of full scale.
EARLY_TERMINATION = 0.995
# Voxels per side of the blocks used for empty-space skipping: small enough to hug thin
# structures, large enough that one test clears many samples.
BLOCK = 8
# A piece (the run of samples tested against the blocks at once) spans at most this
# many voxels: the box of its first and last sample then meets at most 2 blocks a side.
PIECE_VOXELS = BLOCK
# Samples a ray takes in its first round of marching; each later round doubles it, up
# to ROUND_MAX, unless the opacity gathered so far says the ray ends sooner: rays that
# stop early (an opaque skin) waste few samples, rays through translucent material take
# few rounds.
ROUND_FIRST = 16
ROUND_MAX = 256
# A membership this close to an integer i is taken as i when the tables are blended:
# the solved field's float noise (up to 1e-3 seen) would otherwise leave a preserved
# region's neighbouring camera a weight of that size, and with it that camera's opaque
# blocks, which then could not be skipped.
MEMBERSHIP_SNAP = 1e-3
# Rounding allowed for between a piece's end memberships and its samples' ones.
MEMBERSHIP_ROUNDING = 1e-5
# Share of a gradient-shaded sample's colour that does not depend on its orientation.
SHADE_AMBIENT = 0.35
# Vertices x rays processed at once: bounds the memory of a chunk's segment stage
# (about 80 bytes a vertex: 170 MB for a full chunk of the demo's bent rays).
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


def camera_runs(count):
    """Which occupancy grid serves a run of cameras lo..hi (0-based, inclusive).

    Eq. 6 gives a sample weight only for the one or two cameras next to its membership,
    so a run is nearly always one camera or two neighbours: grid i serves camera i
    alone, grid count + i the pair (i, i + 1), grid 2 * count - 1 every camera (any
    longer run). Returns a function (lo, hi) -> grid index, int arrays in and out.
    """

    def grid(lo, hi):
        return np.where(hi == lo, lo, np.where(hi == lo + 1, count + lo, 2 * count - 1))

    return grid


def run_grids(camera_occupied, occupied):
    """Block occupancy for each run of ``camera_runs``: (2N, bx, by, bz) bool.

    camera_occupied : (N, bx, by, bz) bool, each camera's occupied blocks. occupied :
    (bx, by, bz) bool, blocks occupied under some camera.
    """
    n = len(camera_occupied)
    grids = list(camera_occupied)
    grids += [camera_occupied[i] | camera_occupied[i + 1] for i in range(n - 1)]
    grids.append(occupied)
    return np.stack(grids)


def occupancy_sums(grids):
    """Summed-volume tables of ``run_grids``: (G, bx + 1, by + 1, bz + 1) int32, S[g, x,
    y, z] counting grid g's occupied blocks in [0, x) x [0, y) x [0, z), so any box of
    blocks is tested with eight reads."""
    out = np.zeros((len(grids),) + tuple(d + 1 for d in grids.shape[1:]), np.int32)
    out[:, 1:, 1:, 1:] = grids.astype(np.int32).cumsum(1).cumsum(2).cumsum(3)
    return out


def occupancy_bits(grids):
    """Occupancy of the boxes of at most two blocks a side: (G, bx, by, bz) uint8 whose
    bit sx + 2 sy + 4 sz tells whether grid g has an occupied block in [x, x + sx] x
    [y, y + sy] x [z, z + sz] (sx, sy, sz in {0, 1}), so such a box is one read."""
    out = np.zeros(grids.shape, np.uint8)
    for bit in range(8):
        sx, sy, sz = bit & 1, (bit >> 1) & 1, (bit >> 2) & 1
        box = grids.copy()
        if sx:
            box[:, :-1] |= grids[:, 1:]
        if sy:
            box[:, :, :-1] |= box[:, :, 1:].copy()
        if sz:
            box[:, :, :, :-1] |= box[:, :, :, 1:].copy()
        out |= box.astype(np.uint8) << bit
    return out


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
    occupied : (bx, by, bz) bool, blocks where some camera's table gives some opacity
    (``occupied_blocks``). step : float, samples apart in voxels. shading : bool,
    gradient shading. cubic : bool, eq. 6's cubic weights. normals : (nx * ny * nz,)
    int32 or None, ``gradient_directions`` (when shading). camera_occupied : (N, bx, by,
    bz) bool or None, each camera's own occupied blocks (None: ``occupied`` for all).

    Derived: ``sums`` and ``bits`` (``occupancy_sums``, ``occupancy_bits`` of the
    ``run_grids``) and ``lookup`` (8, N * T) float32, column
    i * T + t holding camera i's step-corrected RGBA at row t and its increase to row
    t + 1 (a linear interpolation is two reads a channel).
    """

    volume: ScalarVolume
    tables: np.ndarray
    occupied: np.ndarray
    step: float = 1.0
    shading: bool = False
    cubic: bool = False
    normals: np.ndarray = None
    camera_occupied: np.ndarray = None
    sums: np.ndarray = field(init=False, repr=False)
    bits: np.ndarray = field(init=False, repr=False)
    lookup: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        n = len(self.tables)
        cams = self.camera_occupied
        if cams is None:
            cams = np.broadcast_to(self.occupied, (n,) + self.occupied.shape)
        grids = run_grids(np.asarray(cams, bool), np.asarray(self.occupied, bool))
        self.sums = occupancy_sums(grids)
        self.bits = occupancy_bits(grids)
        tab = corrected_tables(self.tables, self.step)
        delta = np.concatenate([np.diff(tab, axis=1), np.zeros_like(tab[:, :1])], axis=1)
        self.lookup = np.ascontiguousarray(np.concatenate([tab, delta], axis=2).reshape(-1, 8).T)

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
        cams = np.stack([occupied_blocks(lo, hi, t[None]) for t in tables])
        return cls(
            volume, tables, cams.any(0), float(step), shading, cubic, normals, camera_occupied=cams
        )


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


def _starts(counts):
    """(M,) int64 exclusive running sum of ``counts`` (where each group begins)."""
    out = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=out[1:])
    return out


def _within(counts):
    """(sum(counts),) int64: 0, 1, ..., counts[g] - 1 for each group g in turn."""
    total = int(counts.sum())
    return np.arange(total, dtype=np.int64) - np.repeat(_starts(counts), counts)


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


def corrected_tables(tables, step):
    """Tables with alpha corrected for a step of ``step`` voxels: 1 - (1 - a)^step."""
    out = np.array(tables, dtype=np.float32, copy=True)
    out[..., 3] = 1.0 - np.power(np.clip(1.0 - out[..., 3], 0.0, 1.0), step)
    return out


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
    runs : None when no segment needs sampling, else a dict of (C,) arrays, C runs in
        ray then arc order: ``ray``, ``seg`` int64 (segment within the ray); ``j``
        int64, the first sample's lattice index; ``n`` int64, samples; ``p``, ``dp``
        (3, C) float64, the first sample's voxel position and the step between samples;
        ``nm``, ``dnm`` float64, the membership at the first sample and its change per
        sample; ``sure`` bool, one piece already known to be occupied; ``dir`` (3, C)
        float32, the segment's unit world direction.
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
    runs = {
        "ray": ray,
        "seg": seg,
        "j": ja.astype(np.int64),
        "n": n,
        "p": a + dv * local,
        "dp": dv * rise,
        "nm": m0 + dm * local,
        "dnm": dm * rise,
        "sure": full.ravel().take(cand) & (n <= _per_piece(scene)),
        "dir": np.stack([d[c].ravel().take(cand) for c in range(3)]) / seglen.ravel().take(cand),
    }
    return runs, skipped, entry


def _per_piece(scene):
    """Samples in a piece: they span at most ``PIECE_VOXELS`` voxels."""
    return max(1, int(PIECE_VOXELS / scene.step))


def _pieces(scene, runs):
    """Cut runs into pieces of at most ``_per_piece`` samples and test each piece's box
    of blocks (its first and last sample's) under the cameras its membership can weigh.

    Returns
    -------
    dict of (P,) arrays, pieces in ray then arc order: ``run`` int64 (index into the
    runs), ``i`` int64 (first sample within its run), ``count`` int64, ``busy`` bool.
    """
    per = _per_piece(scene)
    n = runs["n"]
    pcs = -(-n // per)
    run = np.repeat(np.arange(len(n)), pcs)
    i = _within(pcs) * per
    count = np.minimum(per, n.take(run) - i)
    busy = runs["sure"].take(run)
    test = np.flatnonzero(~busy)
    if len(test):
        rt, it, ct = run[test], i[test], count[test]
        p = [runs["p"][c].take(rt) + it * runs["dp"][c].take(rt) for c in range(3)]
        q = [p[c] + (ct - 1) * runs["dp"][c].take(rt) for c in range(3)]
        bp, bq = _blocks(scene.volume.shape, p), _blocks(scene.volume.shape, q)
        cams = None
        if len(scene.tables) > 1:
            n0 = runs["nm"].take(rt) + it * runs["dnm"].take(rt)
            n1 = n0 + (ct - 1) * runs["dnm"].take(rt)
            low = np.minimum(n0, n1).astype(np.float32)
            cams = _camera_bounds(scene, low, np.maximum(n0, n1).astype(np.float32))
        busy[test] = _occupied(scene, bp, bq, cams)
    return {"run": run, "i": i, "count": count, "busy": busy}


def _march_chunk(scene, vertices, membership, reach, stop):
    """March one chunk of R rays (``march_volume``'s arguments, sliced).

    Returns
    -------
    colour (R, 3) float32 premultiplied, alpha (R,) float32, entry (R,) float64, depth
    (R,) float64, samples taken and samples skipped (int), as in ``VolumeResult``.
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
        return colour.T.copy(), alpha, entry, depth, samples, skipped

    skipped = int(dense_skipped[:, -1].sum())
    if runs is None:
        return result(0, skipped)
    pieces = _pieces(scene, runs)
    busy = pieces["busy"]
    # the pieces' skipped samples, less those behind where a ray stopped
    empty = np.zeros(len(busy) + 1, np.int64)
    np.cumsum(np.where(busy, 0, pieces["count"]), out=empty[1:])
    skipped += int(empty[-1])
    piece_ray = runs["ray"].take(pieces["run"])
    sel = np.flatnonzero(busy)
    if not len(sel):
        return result(0, skipped)

    # the busy pieces, with what their samples need
    run = pieces["run"][sel]
    i = pieces["i"][sel]
    count = pieces["count"][sel]
    p0 = [
        (runs["p"][c].take(run) + i * runs["dp"][c].take(run)).astype(np.float32) for c in range(3)
    ]
    dp = [runs["dp"][c].take(run).astype(np.float32) for c in range(3)]
    n0 = (runs["nm"].take(run) + i * runs["dnm"].take(run)).astype(np.float32)
    dn = runs["dnm"].take(run).astype(np.float32)
    j0 = runs["j"].take(run) + i
    wdir = [runs["dir"][c].take(run).astype(np.float32) for c in range(3)]
    bseg = runs["seg"].take(run)
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
