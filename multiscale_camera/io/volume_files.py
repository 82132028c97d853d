"""Scalar volume files -> (nx, ny, nz) numpy arrays indexed [x, y, z] (numpy only).

- ``.npy``: a 3D array, indexed [x, y, z].
- ``.raw``: headerless voxels, x varying fastest (then y, then z), of a given type,
  byte order and dimensions.
- ``.nrrd`` / ``.nhdr``: NRRD with raw or gzip encoding (attached or detached data),
  3 axes (or 4 with a first axis of size 1), x fastest as the format defines.

Errors are ``VolumeError`` with a message that names the file and what to change.
"""

import gzip
import os

import numpy as np

from ..core.errors import VolumeError

RAW_TYPES = {
    "UINT8": np.uint8,
    "INT8": np.int8,
    "UINT16": np.uint16,
    "INT16": np.int16,
    "UINT32": np.uint32,
    "INT32": np.int32,
    "FLOAT32": np.float32,
    "FLOAT64": np.float64,
}
EXTENSIONS = (".npy", ".raw", ".nrrd", ".nhdr")

_NRRD_TYPES = {
    np.int8: ("signed char", "int8", "int8_t"),
    np.uint8: ("uchar", "unsigned char", "uint8", "uint8_t"),
    np.int16: ("short", "short int", "signed short", "signed short int", "int16", "int16_t"),
    np.uint16: ("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"),
    np.int32: ("int", "signed int", "int32", "int32_t"),
    np.uint32: ("uint", "unsigned int", "uint32", "uint32_t"),
    np.int64: ("longlong", "long long", "long long int", "int64", "int64_t"),
    np.uint64: ("ulonglong", "unsigned long long", "unsigned long long int", "uint64"),
    np.float32: ("float",),
    np.float64: ("double",),
}
NRRD_TYPES = {name: t for t, names in _NRRD_TYPES.items() for name in names}


def _check_file(path):
    if not path:
        raise VolumeError("No volume file is set")
    if not os.path.isfile(path):
        raise VolumeError(f"The volume file '{path}' does not exist")


def read_volume(path, dims=None, dtype="UINT8", little_endian=True):
    """Read a volume file by its extension.

    Parameters
    ----------
    path : str, an absolute path. dims : (3,) int, (nx, ny, nz) for ``.raw``.
    dtype : str, a key of ``RAW_TYPES``, for ``.raw``. little_endian : bool, for ``.raw``.

    Returns
    -------
    (nx, ny, nz) array of the file's own type.
    """
    ext = os.path.splitext(path)[1].lower()
    if ext not in EXTENSIONS:
        raise VolumeError(
            f"'{os.path.basename(path)}' is not a volume file this add-on reads: use "
            + ", ".join(EXTENSIONS)
        )
    _check_file(path)
    if ext == ".npy":
        return read_npy(path)
    if ext == ".raw":
        return read_raw(path, dims, dtype, little_endian)
    return read_nrrd(path)


def read_npy(path):
    """A 3D ``.npy`` array, indexed [x, y, z]."""
    _check_file(path)
    try:
        a = np.load(path, allow_pickle=False)
    except ValueError as err:
        raise VolumeError(
            f"'{os.path.basename(path)}' is not a readable .npy file ({err})"
        ) from None
    a = np.squeeze(a) if a.ndim > 3 else a
    if a.ndim != 3 or a.dtype.kind not in "uifb":
        raise VolumeError(
            f"'{os.path.basename(path)}' holds a {a.dtype} array of shape {a.shape}; "
            "a volume needs a 3D array of numbers, indexed [x, y, z]"
        )
    return a


def read_raw(path, dims, dtype="UINT8", little_endian=True):
    """Headerless voxels, x fastest; the file's size must match exactly."""
    _check_file(path)
    dims = tuple(int(n) for n in dims)
    if len(dims) != 3 or min(dims) < 1:
        raise VolumeError(f"Raw volume dimensions must be three positive numbers, not {dims}")
    t = np.dtype(RAW_TYPES[dtype]).newbyteorder("<" if little_endian else ">")
    need = dims[0] * dims[1] * dims[2] * t.itemsize
    size = os.path.getsize(path)
    if size != need:
        raise VolumeError(
            f"'{os.path.basename(path)}' holds {size} bytes, but {dims[0]}x{dims[1]}x{dims[2]} "
            f"voxels of {dtype.lower()} need {need}: check the dimensions and the value type"
        )
    a = np.fromfile(path, dtype=t)
    return a.reshape(dims[::-1]).transpose(2, 1, 0).astype(t.newbyteorder("="))


def _nrrd_header(f, name):
    magic = f.readline()
    if not magic.startswith(b"NRRD000"):
        raise VolumeError(f"'{name}' is not a NRRD file (no NRRD magic line)")
    fields = {}
    while True:
        line = f.readline()
        if not line or line in (b"\n", b"\r\n"):
            break
        text = line.decode("latin-1").rstrip("\r\n")
        if text.startswith("#") or ":=" in text:
            continue
        key, sep, value = text.partition(":")
        if sep:
            fields[key.strip().lower()] = value.strip()
    return fields


def read_nrrd(path):
    """A NRRD volume (raw or gzip encoding), indexed [x, y, z]."""
    _check_file(path)
    name = os.path.basename(path)
    with open(path, "rb") as f:
        fields = _nrrd_header(f, name)
        offset = f.tell()
    try:
        kind = NRRD_TYPES[fields["type"].lower()]
        sizes = [int(v) for v in fields["sizes"].split()]
    except KeyError as err:
        raise VolumeError(
            f"'{name}': NRRD field {err} is missing or not a supported type"
        ) from None
    encoding = fields.get("encoding", "raw").lower()
    if encoding not in ("raw", "gzip", "gz"):
        raise VolumeError(
            f"'{name}' uses the NRRD encoding '{encoding}'; only raw and gzip are read"
        )
    if len(sizes) == 4 and sizes[0] == 1:
        sizes = sizes[1:]
    if len(sizes) != 3:
        raise VolumeError(f"'{name}' has {len(sizes)} axes of sizes {sizes}; a volume needs 3")
    endian = fields.get("endian", "little").lower()
    t = np.dtype(kind).newbyteorder("<" if endian == "little" else ">")
    data_path, data_offset = path, offset
    detached = fields.get("data file") or fields.get("datafile")
    if detached:
        data_path = os.path.join(os.path.dirname(path), detached)
        data_offset = 0
        if not os.path.isfile(data_path):
            raise VolumeError(f"'{name}' names the data file '{detached}', which does not exist")
    with open(data_path, "rb") as f:
        f.seek(data_offset)
        payload = f.read()
    if encoding != "raw":
        try:
            payload = gzip.decompress(payload)
        except (OSError, EOFError) as err:
            raise VolumeError(f"'{name}': the gzip data cannot be read ({err})") from None
    skip = int(fields.get("byte skip", "0"))
    need = sizes[0] * sizes[1] * sizes[2] * t.itemsize
    payload = payload[len(payload) - need :] if skip == -1 else payload[skip:]
    if len(payload) < need:
        raise VolumeError(
            f"'{name}' holds {len(payload)} bytes of voxels, but sizes {sizes} of "
            f"{fields['type']} need {need}: the file is truncated"
        )
    a = np.frombuffer(payload[:need], dtype=t)
    return a.reshape(sizes[::-1]).transpose(2, 1, 0).astype(t.newbyteorder("="))


def write_nrrd(path, array, gzip_level=6):
    """Write an [x, y, z] array as an attached NRRD (gzip encoding when ``gzip_level``)."""
    a = np.asarray(array)
    names = {np.dtype(t): n[0] for t, n in _NRRD_TYPES.items()}
    kind = names[a.dtype.newbyteorder("=")]
    header = (
        "NRRD0004\n"
        f"type: {kind}\ndimension: 3\nsizes: {a.shape[0]} {a.shape[1]} {a.shape[2]}\n"
        f"encoding: {'gzip' if gzip_level else 'raw'}\nendian: little\n\n"
    )
    data = np.ascontiguousarray(a.transpose(2, 1, 0)).astype(a.dtype.newbyteorder("<"))
    payload = data.tobytes()
    if gzip_level:
        payload = gzip.compress(payload, gzip_level)
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(payload)
