"""Golden renders: every method's low-resolution image, compared with a committed one.

Each method renders the same shaded two-camera scene at 64x48 (two rays a pixel, so the
anti-aliasing path is in it too), and its passes are compared with the snapshot under
``__snapshots__/test_golden/``. A change to any image shows here, whatever caused it.

Tolerance, per pass: at least 99.9% of the pixels (all but 3 of 3072) within 1e-4 of
the snapshot (Depth: 1e-4 relative), and none off by more than 0.05 (Depth: 5%), so a
different rounding of the same rays passes and a moved ray does not. IndexOB is compared
exactly on the same share of pixels. A commit that changes an image on purpose
regenerates the snapshots (``pytest tests/blender/test_golden.py --snapshot-update``),
says why in its message and shows the before and after; the tolerances never loosen.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import bpy
import numpy as np
import pytest
from syrupy.extensions.single_file import SingleFileSnapshotExtension

from fixtures.blender.scenes import two_camera_scene
from tests.exr import read_passes

METHODS = ("AUTO", "IMAGE_BLEND", "LINEAR", "VECTOR_FIELD", "SCALAR_FIELD")
PASSES = ("Combined", "Depth", "Normal", "IndexOB", "Membership")
# Share of pixels that must agree closely; the rest may differ, but never by much.
CLOSE_SHARE = 0.999
ABS_TOL = 1e-4
WORST_TOL = 0.05


@dataclass(frozen=True)
class PassDiff:
    """How one pass differs from its snapshot: share of close pixels, worst difference."""

    name: str
    close_share: float
    worst: float

    @property
    def ok(self) -> bool:
        return self.close_share >= CLOSE_SHARE and self.worst <= WORST_TOL


def _load(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data)) as npz:
        return {k: npz[k] for k in npz.files}


def compare(new: dict[str, np.ndarray], old: dict[str, np.ndarray]) -> list[PassDiff]:
    """PassDiff per pass of ``old`` (float32 (H, W, C) arrays by pass name); a pass
    missing from ``new`` or of another shape gets close_share 0."""
    diffs = []
    for name, ref in old.items():
        got = new.get(name)
        if got is None or got.shape != ref.shape:
            diffs.append(PassDiff(name, 0.0, float("inf")))
            continue
        err = np.abs(got.astype(np.float64) - ref).max(axis=-1)
        if name == "IndexOB":
            close = err == 0
            worst = 0.0 if close.all() else 1.0 - close.mean()
        elif name == "Depth":
            rel = err / np.maximum(np.abs(ref[..., 0]), 1.0)
            close, worst = rel <= ABS_TOL, float(rel.max())
        else:
            close, worst = err <= ABS_TOL, float(err.max())
        diffs.append(PassDiff(name, float(close.mean()), worst))
    return diffs


class PassesSnapshot(SingleFileSnapshotExtension):
    """A render's passes as one .npz file, compared with the tolerances above."""

    file_extension = "npz"

    def serialize(self, data, **kwargs) -> bytes:
        buf = io.BytesIO()
        np.savez_compressed(buf, **{k: np.asarray(v, np.float32) for k, v in data.items()})
        return buf.getvalue()

    def matches(self, *, serialized_data, snapshot_data) -> bool:
        if snapshot_data is None:
            return False
        new, old = _load(serialized_data), _load(snapshot_data)
        return set(new) == set(old) and all(d.ok for d in compare(new, old))

    def diff_snapshots(self, serialized_data, snapshot_data) -> str:
        new, old = _load(serialized_data), _load(snapshot_data)
        rows = [f"passes: {sorted(new)} against {sorted(old)}"]
        rows += [
            f"{d.name}: {d.close_share:.4%} of pixels within tolerance "
            f"(needs {CLOSE_SHARE:.1%}), worst {d.worst:.3g} (at most {WORST_TOL})"
            for d in compare(new, old)
        ]
        return "\n".join(rows)

    def diff_lines(self, serialized_data, snapshot_data):
        yield from self.diff_snapshots(serialized_data, snapshot_data).splitlines()


@pytest.fixture
def passes_snapshot(snapshot):
    return snapshot.use_extension(PassesSnapshot)


def golden_scene(scene, method):
    two_camera_scene(scene, 64, 48)
    sphere = scene.objects["Sphere"]
    sphere.data.polygons.foreach_set("use_smooth", [True] * len(sphere.data.polygons))
    sphere.data.update()
    scene.world = bpy.data.worlds.new("sky")
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (
        0.05,
        0.07,
        0.1,
        1.0,
    )
    ms = scene.multiscale
    ms.method = method
    ms.quality = "PREVIEW"
    ms.samples = 2
    bpy.context.view_layer.update()


def rendered_passes(scene, path):
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    passes = read_passes(path)
    return {name: passes[name] for name in PASSES}


@pytest.mark.parametrize("method", METHODS)
def test_golden_render(empty_scene, tmp_path, passes_snapshot, method):
    golden_scene(empty_scene, method)
    passes = rendered_passes(empty_scene, tmp_path / "golden.exr")
    # The image is a picture, not a blank: the sphere (camera 2's subject) is in it.
    assert (passes["IndexOB"][..., 0] == 3).sum() > 50
    assert passes == passes_snapshot


def test_golden_compare_flags_a_moved_object():
    """The comparison itself: a shifted IndexOB or a brighter patch fails, rounding passes."""
    rng = np.random.default_rng(1)
    ref = {
        "Combined": rng.random((48, 64, 4), np.float32),
        "IndexOB": np.zeros((48, 64, 1), np.float32),
    }
    ref["IndexOB"][10:20, 10:20] = 3
    rounded = {k: v + np.float32(1e-6) * (k == "Combined") for k, v in ref.items()}
    assert all(d.ok for d in compare(rounded, ref))
    moved = dict(ref, IndexOB=np.roll(ref["IndexOB"], 1, axis=1))
    assert not all(d.ok for d in compare(moved, ref))
    brighter = dict(ref, Combined=ref["Combined"].copy())
    brighter["Combined"][0:2, 0:2] += 0.1
    assert not all(d.ok for d in compare(brighter, ref))
