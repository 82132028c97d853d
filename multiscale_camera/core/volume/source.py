"""A scalar volume and its transfer functions, pure numpy.

A scalar volume is a dense (nx, ny, nz) array of values normalised to [0, 1] and an
affine map from world points to continuous voxel coordinates (an integer coordinate is
a voxel centre). Each camera has a transfer function, sampled into a lookup table of
RGBA rows over [0, 1]; its alpha is the opacity of one voxel length of material.
"""

from dataclasses import dataclass

import numpy as np

# Rows of a transfer function's lookup table: finer than 8-bit data, and a ramp's
# interpolation between them is linear, as ColorRamp's own LINEAR mode.
TABLE_SIZE = 256


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
