"""Built ray fields as flat dicts of numpy arrays and back, for the field cache on disk
(``cache``): ``field_to_arrays`` for ``np.savez``, ``field_from_arrays`` for what
``np.load`` gives back.
"""

import dataclasses
import json

import numpy as np

from ..core.field import Grid, Traced
from ..core.methods import CurveBlendField, LinearField, TracedField

# Version of the array layout below; a cache entry of another version is rebuilt.
ARRAYS_VERSION = 1
# Fields that belong to the base class or are rebuilt from the scene, not stored.
# Not stored: the rig (the key is its digest), and what only re-tracing needs (nested
# grids' membership and the step function): ``rays`` reads the traced rays alone.
_NOT_STORED = ("rig", "domain", "step")


def _field_classes():
    return {cls.__name__: cls for cls in (TracedField, CurveBlendField, LinearField)}


def field_to_arrays(fld):
    """A prepared RayField as a flat dict of numpy arrays (for ``np.savez``).

    The rig is not stored: the cache key is a digest of it, so whoever loads the field
    already holds the same rig. A ``report`` attribute (the build report dict, set by
    whoever measured the field) is kept too. Arrays keep their dtype and shape; the ``Traced`` rays
    and the ``Grid`` are split into their arrays; everything else (method, timings,
    warnings, stats, ints) goes into a JSON string under ``"meta"``.

    Returns
    -------
    dict str -> np.ndarray.
    """
    out = {}
    meta = {"version": ARRAYS_VERSION, "class": type(fld).__name__, "plain": {}}
    for f in dataclasses.fields(fld):
        if f.name in _NOT_STORED:
            continue
        value = getattr(fld, f.name)
        if isinstance(value, np.ndarray):
            out[f"array.{f.name}"] = value
        elif isinstance(value, Traced):
            for t in dataclasses.fields(value):
                part = getattr(value, t.name)
                if t.name == "step" and part is None:  # a step that followed the cells
                    part = np.nan
                if t.name == "bands" and part is None:  # every ray the whole step
                    continue
                out[f"traced.{f.name}.{t.name}"] = np.asarray(part)
        elif isinstance(value, Grid):
            out[f"grid.{f.name}"] = np.concatenate(
                [value.origin, [value.cell], np.asarray(value.shape, dtype=np.float64)]
            )
        else:
            meta["plain"][f.name] = value
    if getattr(fld, "report", None) is not None:  # the build report, when one was made
        meta["report"] = fld.report
    out["meta"] = np.frombuffer(
        json.dumps(
            meta, default=lambda o: o.item() if isinstance(o, np.generic) else str(o)
        ).encode(),
        dtype=np.uint8,
    )
    return out


def field_from_arrays(arrays, rig):
    """The RayField ``field_to_arrays`` stored, for ``rig`` (the rig it was built for).

    Parameters
    ----------
    arrays : mapping str -> np.ndarray (a dict or an ``np.load`` result).
    rig : Rig.

    Raises
    ------
    ValueError when the arrays are of another layout version or an unknown class.
    """
    meta = json.loads(bytes(np.asarray(arrays["meta"], dtype=np.uint8)).decode())
    if meta.get("version") != ARRAYS_VERSION:
        raise ValueError(f"field arrays of version {meta.get('version')}, not {ARRAYS_VERSION}")
    cls = _field_classes().get(meta.get("class"))
    if cls is None:
        raise ValueError(f"unknown field class {meta.get('class')!r}")
    kwargs = dict(meta["plain"])
    traced = {}
    for key in arrays.keys():
        kind, _, rest = key.partition(".")
        if kind == "array":
            kwargs[rest] = np.asarray(arrays[key])
        elif kind == "grid":
            g = np.asarray(arrays[key], dtype=np.float64)
            kwargs[rest] = Grid(g[:3], float(g[3]), tuple(int(n) for n in g[4:7]))
        elif kind == "traced":
            name, _, part = rest.partition(".")
            traced.setdefault(name, {})[part] = np.asarray(arrays[key])
    for name, parts in traced.items():
        step = float(parts["step"])
        parts["step"] = None if np.isnan(step) else step
        kwargs[name] = Traced(**parts)
    fld = cls(rig=rig, **kwargs)
    if "report" in meta:
        fld.report = meta["report"]
    return fld
