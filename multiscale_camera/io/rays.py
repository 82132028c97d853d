"""``multiscale.export_rays``: the per-pixel ray tables as one multi-channel EXR and the
polylines as ``.npz``. The formats are documented in docs/ray_tables.md."""

import os

import numpy as np

from ..render.tables import ray_tables
from .exr import ExrError, write_channels

# Bumped when a channel or array changes meaning or goes away (adding is compatible).
FORMAT_VERSION = 1
# Written where a ray hits nothing (distance and depth), as Blender's Depth pass does.
MISS = 1e10


def table_channels(tables):
    """The EXR channels of ``RayTables``: name -> (H, W) float32, row 0 at the top."""
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


def export_rays(frame, path, should_stop=None):
    """March ``frame`` and write ``path`` (EXR) and the same name with ``.npz``.

    Parameters
    ----------
    frame : pipeline.Frame. path : str ending in .exr (absolute).
    should_stop : callable -> bool, or None.

    Returns
    -------
    (exr_path, npz_path) : str.

    Raises
    ------
    OSError: the folder does not exist or cannot be written. ExrError: writing failed.
    """
    folder = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        raise OSError(f"Cannot write '{path}': the folder '{folder}' does not exist")
    if not os.access(folder, os.W_OK):
        raise OSError(f"Cannot write '{path}': the folder '{folder}' is not writable")
    tables, lines = ray_tables(frame, should_stop, keep_polylines=True)
    width, height = frame.size
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
