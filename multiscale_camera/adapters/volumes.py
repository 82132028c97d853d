"""Blender volume sources -> core ``ScalarVolume``s; camera transfer functions -> tables.

Two kinds of source:

- Volume objects (OpenVDB grids). Blender keeps their voxels out of Python's reach, so
  the grid is read from the object's .vdb file with the ``openvdb`` module Blender
  bundles (off ``sys.path`` in some builds; found in Blender's own site-packages).
  Volume modifiers are not applied: the file's grid is rendered.
- Any other object with Object Properties > Multiscale Volume > Volume File set: the
  file (.npy, .raw, .nrrd) fills the object's bounding box (an empty's display cube),
  and the object itself is not drawn as a surface.

Either way the object's world transform places the voxels.
"""

import functools
import glob
import importlib.util
import os

import bpy
import numpy as np

from ..core.errors import VolumeError
from ..core.volume import (
    TABLE_SIZE,
    ScalarVolume,
    block_ranges,
    box_to_index,
    default_table,
    gradient_directions,
    normalise,
)
from ..io.volume_files import read_volume

# Blender grid types the renderer can read, and the array type openvdb copies them to.
SCALAR_GRIDS = {"FLOAT": np.float32, "DOUBLE": np.float64, "INT": np.int32, "INT64": np.int64}
GRID_TYPE_NAMES = {
    "BOOLEAN": "boolean",
    "MASK": "mask (no values)",
    "VECTOR_FLOAT": "vector",
    "VECTOR_DOUBLE": "vector",
    "VECTOR_INT": "integer vector",
    "POINTS": "point",
    "UNKNOWN": "unknown",
}
NO_OPENVDB = (
    "Volume object '{name}': this Blender has no openvdb Python module, so the voxels of "
    "its grids cannot be read; save the grid as .npy, .raw or .nrrd and set it as the "
    "Volume File of an object (Object Properties > Multiscale Volume) instead"
)
# Newest volumes kept decoded (``VolumeGridCache``).
KEEP_VOLUMES = 2


@functools.cache  # looked up once, as an import is
def openvdb_module():
    """The ``openvdb`` module Blender bundles, or None where there is none."""
    module = None
    try:
        # here only: openvdb is optional (some Blender builds lack it; the bpy module has
        # it off sys.path, found below), and its absence is reported, not an error
        import openvdb as module
    except ImportError:
        base = bpy.utils.system_resource("PYTHON")
        pattern = os.path.join(base or "", "lib", "python3*", "site-packages", "openvdb*")
        for path in sorted(glob.glob(pattern)):
            if not path.endswith((".so", ".pyd")):
                continue
            try:
                spec = importlib.util.spec_from_file_location("openvdb", path)
                module = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(module)
                break
            except ImportError:
                module = None
    return module


class VolumeGridCache:
    """The newest ``keep`` decoded volume sources (values normalised to [0, 1], block
    ranges, gradient directions), keyed by their source: file, size and date, grid or
    layout, value range. Decoding a large grid takes seconds; a frame that reads the
    same unchanged sources again takes them from here.

    Parameters
    ----------
    keep : int, how many to keep; the least recently used go first.
    """

    def __init__(self, keep=KEEP_VOLUMES):
        self.keep = keep
        self._entries = {}

    def __len__(self):
        return len(self._entries)

    def get(self, key, make):
        """The value kept under ``key`` (now the newest), or ``make()``'s, then kept.

        Parameters
        ----------
        key : hashable, the source. make : callable () -> value, run on a miss.
        """
        if key in self._entries:
            self._entries[key] = self._entries.pop(key)
            return self._entries[key]
        value = make()
        self._entries[key] = value
        while len(self._entries) > self.keep:
            self._entries.pop(next(iter(self._entries)))
        return value

    def clear(self):
        """Forget every decoded volume."""
        self._entries.clear()


def _file_key(path):
    st = os.stat(path)
    return (path, st.st_mtime_ns, st.st_size)


def _value_range(settings):
    if settings is None or settings.auto_range:
        return None
    if settings.range_max <= settings.range_min:
        raise VolumeError(
            f"Object '{settings.id_data.name}': the value range {settings.range_min:g} .. "
            f"{settings.range_max:g} is empty; make Max greater than Min or use Auto Range"
        )
    return (settings.range_min, settings.range_max)


def _decoded(cache, key, read, value_range):
    """(values in [0, 1] float32, block ranges, gradient directions, extra) of a source,
    from ``cache`` (a VolumeGridCache) when the source and range are unchanged;
    ``read()`` returns (array, extra)."""

    def make():
        array, extra = read()
        values = normalise(array, value_range)
        return values, block_ranges(values), gradient_directions(values), extra

    return cache.get(key + (value_range,), make)


def _object_box(obj):
    """(box_min, box_max) local bounding box of a box object: an empty's display cube,
    else the object's own bounds."""
    if obj.type == "EMPTY":
        size = float(obj.empty_display_size)
        return (-size,) * 3, (size,) * 3
    corners = np.array([tuple(c) for c in obj.bound_box], dtype=np.float64)
    return corners.min(0), corners.max(0)


def file_volume(obj, matrix_world, cache):
    """The volume file attached to ``obj`` (``obj.multiscale_volume``) placed in its box.

    Parameters
    ----------
    obj : bpy.types.Object, evaluated. matrix_world : (4, 4) float64, its instance's.
    cache : VolumeGridCache, where the decoded file is looked up and kept.

    Returns
    -------
    (ScalarVolume, (lo, hi) block ranges, gradient directions)
    """
    settings = obj.original.multiscale_volume
    name = obj.original.name
    path = bpy.path.abspath(settings.filepath, library=obj.original.library)
    if not settings.filepath:
        raise VolumeError(
            f"Object '{name}' is marked as a volume but has no file: set its Volume File in "
            "Object Properties > Multiscale Volume (.npy, .raw or .nrrd)"
        )
    if not os.path.isfile(path):
        raise VolumeError(
            f"Object '{name}': the volume file '{path}' does not exist; fix the path in "
            "Object Properties > Multiscale Volume"
        )
    dims = tuple(settings.dims)
    key = ("file",) + _file_key(path) + (dims, settings.value_type, settings.little_endian)
    try:
        values, ranges, normals, _ = _decoded(
            cache,
            key,
            lambda: (read_volume(path, dims, settings.value_type, settings.little_endian), None),
            _value_range(settings),
        )
    except VolumeError as err:
        raise VolumeError(f"Object '{name}': {err}") from None
    lo, hi = _object_box(obj)
    try:
        to_index = box_to_index(values.shape, lo, hi, matrix_world)
    except (ValueError, np.linalg.LinAlgError):
        raise VolumeError(
            f"Object '{name}' has a flat bounding box or a zero scale; a volume needs a box "
            "with depth in every direction"
        ) from None
    return ScalarVolume(values, to_index, name), ranges, normals


def _pick_grid(obj, wanted):
    grids = obj.data.grids
    if len(grids) == 0 and not grids.is_loaded:
        grids.load()
    name = obj.original.name
    if len(grids) == 0:
        why = f" ({grids.error_message})" if grids.error_message else ""
        raise VolumeError(
            f"Volume object '{name}' has no grids{why}: set a .vdb file in its Object Data "
            "properties, or remove it from the scene"
        )
    by_name = {g.name: g for g in grids}
    if wanted:
        if wanted not in by_name:
            raise VolumeError(
                f"Volume object '{name}' has no grid named '{wanted}'; its grids are: "
                + ", ".join(by_name)
            )
        return by_name[wanted]
    if "density" in by_name:
        return by_name["density"]
    scalar = [g for g in grids if g.data_type in SCALAR_GRIDS]
    return scalar[0] if scalar else grids[0]


def grid_volume(obj, matrix_world, cache):
    """The chosen scalar grid of a Volume object (``obj`` evaluated), as a volume.

    Parameters
    ----------
    obj : bpy.types.Object, evaluated. matrix_world : (4, 4) float64, its instance's.
    cache : VolumeGridCache, where the decoded grid is looked up and kept.

    Returns
    -------
    (ScalarVolume, (lo, hi) block ranges, gradient directions)
    """
    name = obj.original.name
    settings = obj.original.multiscale_volume
    grid = _pick_grid(obj, settings.grid.strip())
    if grid.data_type not in SCALAR_GRIDS:
        kind = GRID_TYPE_NAMES.get(grid.data_type, grid.data_type.lower())
        raise VolumeError(
            f"Volume object '{name}': grid '{grid.name}' holds {kind} values; only scalar "
            "grids (float, double, int) can be rendered: name a scalar grid in Object "
            "Properties > Multiscale Volume > Grid"
        )
    vdb = openvdb_module()
    if vdb is None:
        raise VolumeError(NO_OPENVDB.format(name=name))
    path = bpy.path.abspath(obj.data.grids.frame_filepath, library=obj.original.data.library)
    if not os.path.isfile(path):
        raise VolumeError(
            f"Volume object '{name}': its file '{path}' does not exist (grids made by "
            "modifiers or packed files cannot be read here); save the volume to a .vdb file"
        )
    dtype = SCALAR_GRIDS[grid.data_type]

    def read():
        g = vdb.read(path, grid.name)
        if g.empty():
            raise VolumeError(f"Volume object '{name}': grid '{grid.name}' has no voxels")
        lo, hi = g.evalActiveVoxelBoundingBox()
        a = np.zeros([h - lo_ + 1 for lo_, h in zip(lo, hi)], dtype=dtype)
        g.copyToArray(a, ijk=lo)
        return a, np.array(lo, dtype=np.float64)

    key = ("vdb",) + _file_key(path) + (grid.name,)
    values, ranges, normals, origin = _decoded(cache, key, read, _value_range(settings))
    index_to_object = np.array([list(r) for r in grid.matrix_object], dtype=np.float64)
    shift = np.eye(4)
    shift[:3, 3] = -origin
    to_index = shift @ np.linalg.inv(np.asarray(matrix_world) @ index_to_object)
    return ScalarVolume(values, to_index, name), ranges, normals


def is_volume_source(obj):
    """Whether ``obj`` renders as a volume (a Volume object, or a volume file's box)."""
    if obj.type == "VOLUME":
        return True
    settings = getattr(obj.original, "multiscale_volume", None)
    return bool(settings is not None and settings.use)


def scene_volumes(depsgraph, cache):
    """Every render-visible volume source of an evaluated depsgraph.

    Parameters
    ----------
    depsgraph : bpy.types.Depsgraph, evaluated.
    cache : VolumeGridCache, where decoded sources are looked up and kept.

    Returns
    -------
    list of (ScalarVolume, (lo, hi) block ranges, gradient directions); notices : list of
    str.

    Raises
    ------
    VolumeError naming the object and what to change.
    """
    out, notices = [], []
    for inst in depsgraph.object_instances:
        obj = inst.object
        if not is_volume_source(obj):
            continue
        matrix = np.array(inst.matrix_world, dtype=np.float64)
        if obj.type == "VOLUME":
            out.append(grid_volume(obj, matrix, cache))
            if len(obj.original.modifiers):
                notices.append(
                    f"Volume object '{obj.original.name}': its modifiers are not applied "
                    "here; the grid in its file is rendered"
                )
        else:
            out.append(file_volume(obj, matrix, cache))
    return out, notices


def ramp_table(texture, size=TABLE_SIZE):
    """(size, 4) float32: the texture's colour ramp sampled at size values over [0, 1]."""
    ramp = texture.color_ramp
    return np.array(
        [ramp.evaluate(x) for x in np.linspace(0.0, 1.0, size).tolist()], dtype=np.float32
    )


def transfer_tables(settings, size=TABLE_SIZE):
    """Every camera's transfer function as a table, sampled once per frame.

    settings : ``scene.multiscale``.

    Returns
    -------
    tables : (N, size, 4) float32. notices : list of str.
    """
    tables, notices = [], []
    for number, item in enumerate(settings.cameras, start=1):
        tex = item.transfer_function
        label = item.camera.name if item.camera is not None else f"item {number}"
        if tex is None:
            tables.append(default_table(size))
        elif not tex.use_color_ramp:
            notices.append(
                f"Camera '{label}': the transfer function texture '{tex.name}' has no colour "
                "ramp (enable it in the panel); the default transfer function is used"
            )
            tables.append(default_table(size))
        else:
            tables.append(ramp_table(tex, size))
    return np.stack(tables), notices
