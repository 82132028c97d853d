"""``multiscale.export_rays``: march every pixel of a frame and write its ray tables and
polylines (``io/rays.py`` writes the files; docs/ray_tables.md gives their format)."""

from ..io.rays import check_folder, write_rays
from .tables import ray_tables


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
    check_folder(path)
    tables, lines = ray_tables(frame, should_stop, keep_polylines=True)
    return write_rays(path, tables, lines, frame.size)
