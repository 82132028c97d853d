"""Float EXR files through the OpenEXR package (bundled with the extension as a wheel).

Images are numpy arrays (H, W) per channel, row 0 at the TOP (EXR's own order), so no
flip happens here.
"""

import numpy as np


class ExrError(Exception):
    """The OpenEXR package is missing or a file cannot be read or written."""


def _openexr():
    try:
        # here only: OpenEXR is a wheel the extension bundles, which a bare checkout may
        # lack; without it only the EXR files fail, with an ExrError that says so
        import OpenEXR
    except ImportError as err:
        raise ExrError(f"The OpenEXR Python package is not available ({err})") from err
    return OpenEXR


def write_channels(path, channels, attributes=None, compress=True):
    """Write one single-part scanline EXR with 32-bit float channels.

    Parameters
    ----------
    path : str, the file to write (overwritten).
    channels : dict str -> (H, W) array, any float or int dtype (stored as float32).
        Every array must have the same shape; row 0 is the top row of the image.
    attributes : dict str -> str, int or float, optional extra header attributes.
    compress : bool, ZIP compression (True) or none (a file read once, soon after, is
        written and read faster uncompressed).

    Raises
    ------
    ExrError: the package is missing, the shapes differ or the file cannot be written.
    """
    openexr = _openexr()
    shapes = {np.shape(a) for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ExrError(f"EXR channels must share one (H, W) shape, got {sorted(shapes)}")
    compression = openexr.ZIP_COMPRESSION if compress else openexr.NO_COMPRESSION
    header = {"compression": compression, "type": openexr.scanlineimage}
    header.update(attributes or {})
    data = {
        name: np.ascontiguousarray(np.asarray(a, dtype=np.float32)) for name, a in channels.items()
    }
    try:
        openexr.File(header, data).write(str(path))
    except Exception as err:  # OpenEXR raises bare RuntimeErrors with the path in them
        raise ExrError(f"Cannot write '{path}': {err}") from err


def read_channels(path):
    """Read every channel of a single-part EXR.

    Returns
    -------
    channels : dict str -> (H, W) float32 array, row 0 at the top.
    attributes : dict str -> header value (as the OpenEXR package gives it).

    Raises
    ------
    ExrError: the package is missing or the file cannot be read.
    """
    openexr = _openexr()
    try:
        part = openexr.File(str(path), separate_channels=True).parts[0]
    except Exception as err:
        raise ExrError(f"Cannot read '{path}': {err}") from err
    channels = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in part.channels.items()}
    return channels, dict(part.header)
