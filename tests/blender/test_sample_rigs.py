"""The benchmarks' sample rigs (``fixtures.rigs.demo_rig``, ``galleon_rig``) are the rigs
the adapter reads from the sample scenes (``fixtures.blender.samples``)."""

import bpy
import numpy as np
import pytest

from fixtures import rigs
from fixtures.blender import samples
from fixtures.masks import radius
from multiscale_camera.adapters.scene import rig_from_scene

CASES = [(samples.build_demo, rigs.demo_rig), (samples.build_galleon, rigs.galleon_rig)]
FIELDS = ("lens", "sensor_width", "sensor_height", "sensor_fit", "shift_x", "shift_y")


@pytest.mark.parametrize("build, rig", CASES, ids=["demo", "galleon"])
def test_sample_rig_is_the_rig_read_from_the_scene(empty_scene, build, rig):
    build(empty_scene)
    bpy.context.view_layer.update()  # the cameras' world matrices
    read = rig_from_scene(empty_scene)
    width, height = read.cameras[0].width, read.cameras[0].height
    cams, masks = rig(width, height)
    assert [c.name for c in cams] == [c.name for c in read.cameras]
    for made, got in zip(cams, read.cameras):
        # Blender keeps the rotation as float32 Euler angles
        np.testing.assert_allclose(made.matrix_world, got.matrix_world, atol=2e-6 * made.clip_end)
        assert [getattr(made, f) for f in FIELDS] == [getattr(got, f) for f in FIELDS]
        np.testing.assert_allclose(
            [made.clip_start, made.clip_end], [got.clip_start, got.clip_end], rtol=1e-6
        )
        assert (made.width, made.height) == (got.width, got.height)
    np.testing.assert_array_equal(masks, read.masks)


@pytest.mark.parametrize("build, rig", CASES, ids=["demo", "galleon"])
def test_sample_rig_at_1080_is_the_scene_rendered_at_300_percent(empty_scene, build, rig):
    build(empty_scene)
    empty_scene.render.resolution_percentage = 300
    bpy.context.view_layer.update()
    read = rig_from_scene(empty_scene)
    _cams, masks = rig(1920, 1080)
    assert read.masks.shape == masks.shape == (3, 1080, 1920)
    # the file's 640x360 mask images resampled against circles drawn at 1920x1080: they
    # differ only along the circles' edges (at most one image pixel, 3 render pixels, wide)
    differ = read.masks != masks
    assert differ.sum() < 0.01 * masks[0].size
    r = radius(1920, 1080)
    edges = np.zeros_like(r, dtype=bool)
    for v in rigs_radii(rig).values():
        edges |= np.abs(r - v) < 3
    assert not (differ & ~edges).any()


def rigs_radii(rig):
    """The mask radii of ``rig`` in pixels at 1920x1080."""
    if rig is rigs.demo_rig:
        return {k: v * 1920 / rigs.DEMO_SIZE[0] for k, v in rigs.DEMO_RADII.items()}
    return {k: v * 1920 for k, v in rigs.GALLEON_RADII.items()}
