"""A volume prepared for one frame's rigs (``VolumeScene``), pure numpy: the value
range of each block of voxels and the blocks each camera's transfer function makes
visible (for empty-space skipping), the gradient directions for shading, and the
lookup tables with their opacity corrected for the step.
"""

from dataclasses import dataclass, field

import numpy as np

from .source import ScalarVolume

# Voxels per side of the blocks used for empty-space skipping: small enough to hug thin
# structures, large enough that one test clears many samples.
BLOCK = 8


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


def corrected_tables(tables, step):
    """Tables with alpha corrected for a step of ``step`` voxels: 1 - (1 - a)^step."""
    out = np.array(tables, dtype=np.float32, copy=True)
    out[..., 3] = 1.0 - np.power(np.clip(1.0 - out[..., 3], 0.0, 1.0), step)
    return out


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
