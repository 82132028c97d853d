"""Each camera's Clip End bounds what its preserved region shows, as Cycles' pinhole
camera clips (at depth clip_end along its axis); in transitions the far planes blend
with the rays' own weights, so there is no hard cut at a mask's edge."""

import bpy
import numpy as np
import pytest
from mathutils.bvhtree import BVHTree
from scipy.ndimage import binary_erosion

from fixtures.blender.handoff import cycles_settings
from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.meshes import scene_geometry
from multiscale_camera.adapters.scene import rig_from_scene
from multiscale_camera.io.cache import FieldCache
from multiscale_camera.render import cycles, fields, pipeline
from tests.exr import read_passes

WIDTH, HEIGHT = 96, 72
SPHERE = 3  # pass indices in two_camera_scene: plane 1, cube 2, sphere 3
# C2 looks at the sphere (radius 0.3) 3.36 away: a far plane at 3.15 cuts through it,
# so the sphere's middle shows and its rim, the cube and the ground behind do not
CLIP_END = 3.15


@pytest.fixture
def scene(empty_scene, tmp_path, monkeypatch):
    monkeypatch.setattr(fields.SERVICE, "cache", FieldCache(str(tmp_path / "cache")))
    two_camera_scene(empty_scene, WIDTH, HEIGHT)
    empty_scene.multiscale.method = "IMAGE_BLEND"
    empty_scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    return empty_scene


def render(scene, path):
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_passes(path)


def pinhole_index(scene, cam, limit=True):
    """(H, W) pass index a straight pinhole camera ``cam`` (core PinholeCamera) sees
    through each pixel centre, from its eye, each ray cut at depth clip_end along the
    axis (clip_end / cos of its angle off the axis) when ``limit``: Cycles' clipping."""
    geometry = scene_geometry(bpy.context.evaluated_depsgraph_get())
    tree = BVHTree.FromPolygons(
        geometry.vertices.tolist(), geometry.triangles.tolist(), all_triangles=True
    )
    index = np.zeros((HEIGHT, WIDTH))
    for y in range(HEIGHT):
        for x in range(WIDTH):
            d = cam.directions(np.array(x + 0.5), np.array(y + 0.5))
            cos = float(d @ cam.forward)
            start = cam.eye + d * (cam.clip_start / cos)
            length = (cam.clip_end - cam.clip_start) / cos if limit else 1e9
            _loc, _nor, tri, _dist = tree.ray_cast(start.tolist(), d.tolist(), length)
            if tri is not None:
                index[y, x] = geometry.pass_index[tri]
    return index


def test_camera_whose_clip_end_lies_before_an_object_shows_background_there(scene, tmp_path):
    scene.objects["C2"].data.clip_end = CLIP_END
    bpy.context.view_layer.update()
    rig = rig_from_scene(scene)
    cam = rig.cameras[1]
    preserved = binary_erosion(rig.masks[1], iterations=2)
    index = render(scene, tmp_path / "clipped.exr")["IndexOB"][..., 0]
    expected = pinhole_index(scene, cam)
    unclipped = pinhole_index(scene, cam, limit=False)
    assert preserved.sum() > 100
    # the test means something: the clip leaves the sphere's middle and removes the rest
    assert (expected[preserved] == SPHERE).sum() > 10
    assert (expected[preserved] == 0).sum() > 10
    assert (unclipped[preserved] != expected[preserved]).sum() > 10
    np.testing.assert_array_equal(index[preserved], expected[preserved])


def ray_ends(seg):
    """(R, 3): where each ray ends (the far end of its last segment of non-zero length)."""
    ends = seg.origin + seg.direction * seg.length[:, None]
    last = np.zeros(len(seg), dtype=np.int64)
    np.maximum.at(last, seg.ray, np.where(seg.length > 0, np.arange(len(seg.ray)), 0))
    return ends[last]


def test_a_transition_between_two_clip_ends_has_no_hard_cut(scene):
    """Along a row from camera 2's preserved middle out into camera 1's region, in steps
    of a tenth of a pixel, the rays' ends move from camera 2's far plane to camera 1's by
    small steps, not at once at a mask's edge."""
    scene.objects["C1"].data.clip_end = 30.0
    scene.objects["C2"].data.clip_end = CLIP_END
    bpy.context.view_layer.update()
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    c1, c2 = frame.rig.cameras
    sx = np.linspace(0.5 * WIDTH, 0.95 * WIDTH, 432)
    sy = np.full(len(sx), 0.5 * HEIGHT)
    seg = frame.sampler.segments(sx, sy)
    assert seg.clipped.all()
    ends = ray_ends(seg)
    on_c2 = np.abs((ends - c2.eye) @ c2.forward - c2.clip_end) < 1e-6
    on_c1 = np.abs((ends - c1.eye) @ c1.forward - c1.clip_end) < 1e-6
    assert on_c2[:20].all() and on_c1[-20:].all()  # each preserved region: its own plane
    between = ~on_c1 & ~on_c2
    assert between.sum() > 50  # the transition's rays end between the two planes
    gap = np.linalg.norm(ends[-1] - ends[0])
    steps = np.linalg.norm(np.diff(ends, axis=0), axis=1)
    print(f"largest step {steps.max():.3f} of a gap of {gap:.3f}, {between.sum()} between")
    assert steps.max() < 0.05 * gap


@pytest.mark.skipif(cycles.unsupported_reason() is not None, reason="needs Cycles with OSL")
def test_cycles_handoff_shows_what_plain_cycles_shows_within_clip_end(scene, tmp_path):
    """The hand-off's camera 2 region against a plain Cycles render of camera 2 with the
    same Clip End: the same objects (Object Index) in its eroded mask."""
    scene.objects["C2"].data.clip_end = CLIP_END
    cycles_settings(scene, samples=1)
    bpy.context.view_layer.update()
    rig = rig_from_scene(scene)
    preserved = binary_erosion(rig.masks[1], iterations=2)
    scene.multiscale.shading = "CYCLES"
    handoff = render(scene, tmp_path / "handoff.exr")["IndexOB"][..., 0]
    scene.render.engine = "CYCLES"
    scene.camera = scene.objects["C2"]
    plain = render(scene, tmp_path / "plain.exr")["IndexOB"][..., 0]
    assert (plain[preserved] == SPHERE).sum() > 10 and (plain[preserved] == 0).sum() > 10
    agree = (handoff == plain)[preserved]
    print(f"Object Index agreement {agree.mean():.4f} of {preserved.sum()} px")
    assert agree.mean() >= 0.99
