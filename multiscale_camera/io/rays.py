"""The ray tables' files: the per-pixel first-hit rays as one multi-channel EXR and the
polylines as ``.npz``. The formats are documented in docs/ray_tables.md; the export
that marches the rays is ``render/export.py``."""

import os

import numpy as np

from .exr import ExrError, write_channels

# Bumped when a channel or array changes meaning or goes away (adding is compatible).
FORMAT_VERSION = 1
# Written where a ray hits nothing (distance and depth), as Blender's Depth pass does.
MISS = 1e10


def table_channels(tables):
    """The EXR channels of first-hit tables: name -> (H, W) float32, row 0 at the top.

    Parameters
    ----------
    tables : the tables of an H x W image (``RayTables`` of render/tables.py): origin,
        direction (H, W, 3); distance, depth, membership, object_index (H, W); hit (H, W)
        bool.
    """
    channels = {}
    for axis, c in enumerate("XYZ"):
        channels[f"origin.{c}"] = tables.origin[..., axis]
    for axis, c in enumerate("XYZ"):
        channels[f"direction.{c}"] = tables.direction[..., axis]
    channels["distance"] = np.where(tables.hit, tables.distance, MISS)
    channels["depth"] = np.where(tables.hit, tables.depth, MISS)
    channels["membership"] = tables.membership
    channels["hit"] = tables.hit
    channels["object_index"] = tables.object_index
    return {k: np.asarray(v, dtype=np.float32) for k, v in channels.items()}


def check_folder(path):
    """Raise OSError, saying why, when ``path``'s folder does not exist or is not writable
    (before minutes of marching are spent on files that cannot be written).

    Parameters
    ----------
    path : str, the EXR to write.
    """
    folder = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        raise OSError(f"Cannot write '{path}': the folder '{folder}' does not exist")
    if not os.access(folder, os.W_OK):
        raise OSError(f"Cannot write '{path}': the folder '{folder}' is not writable")


def write_rays(path, tables, lines, size):
    """Write ``path`` (EXR: ``table_channels``) and the same name with ``.npz`` (the
    polylines).

    Parameters
    ----------
    path : str ending in .exr (absolute).
    tables : first-hit tables (``table_channels``).
    lines : the polylines (``Polylines`` of render/tables.py): points (V, 3) float32,
        offsets (R + 1,) int64, membership (V,) float32, reach, start_depth (R,) float32,
        pixels (R, 2) int32.
    size : (width, height) int, pixels of the image.

    Returns
    -------
    (exr_path, npz_path) : str.

    Raises
    ------
    ExrError: writing failed.
    """
    width, height = size
    write_channels(
        path,
        table_channels(tables),
        {"multiscaleRaysVersion": FORMAT_VERSION, "multiscaleSpace": "world"},
    )
    npz_path = os.path.splitext(path)[0] + ".npz"
    try:
        np.savez_compressed(
            npz_path,
            version=np.int32(FORMAT_VERSION),
            size=np.array([width, height], dtype=np.int32),
            points=lines.points,
            offsets=lines.offsets,
            membership=lines.membership,
            reach=lines.reach,
            start_depth=lines.start_depth,
            pixels=lines.pixels,
        )
    except OSError as err:
        raise ExrError(f"Cannot write '{npz_path}': {err}") from err
    return path, npz_path
