"""multiscale.export_rays: the files read back with OpenEXR and numpy, checked against
straight rays cast with Blender's own scene.ray_cast (not our BVH)."""

import bpy
import numpy as np
import OpenEXR
import pytest
from mathutils import Vector

from fixtures.blender.objects import add_camera, add_mesh, mask_image
from fixtures.blender.scenes import two_camera_scene

CHANNELS = {
    "origin.X",
    "origin.Y",
    "origin.Z",
    "direction.X",
    "direction.Y",
    "direction.Z",
    "distance",
    "depth",
    "membership",
    "hit",
    "object_index",
}


def read_exr(path):
    part = OpenEXR.File(str(path), separate_channels=True).parts[0]
    return {name: ch.pixels for name, ch in part.channels.items()}, part.header


def vec(ch, name):
    return np.stack([ch[f"{name}.{c}"] for c in "XYZ"], axis=-1).astype(np.float64)


def scene_cast(origin, direction, distance=1e9):
    """First hit of a straight ray with Blender's scene.ray_cast: (location, object) or None."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    found, loc, _n, _i, obj, _m = bpy.context.scene.ray_cast(
        depsgraph, Vector(origin), Vector(direction), distance=distance
    )
    return (np.array(loc), obj) if found else None


def pixel_rays(cam, scene, width, height):
    """(H, W, 3) unit pinhole directions through pixel centres, and the eye."""
    tr, _br, bl, tl = (cam.matrix_world @ v for v in cam.data.view_frame(scene=scene))
    tr, bl, tl = (np.array(v) for v in (tr, bl, tl))
    eye = np.array(cam.matrix_world.translation)
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    pts = tl + u[None, :, None] * (tr - tl) + v[:, None, None] * (bl - tl)
    d = pts - eye
    return d / np.linalg.norm(d, axis=-1, keepdims=True), eye


def test_one_camera_tables_are_its_straight_rays(empty_scene, tmp_path):
    scene = empty_scene
    width, height = 40, 30
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    add_mesh("plane", (0, 0, 0), 1, size=6)
    add_mesh("cube", (0.5, 0, 0.5), 2)
    cam = add_camera(scene, "C1", (1.0, -8.0, 4.0), (0, 0, 0.5), clip_start=2.0)
    item = scene.multiscale.cameras.add()
    item.camera = cam
    item.mask = mask_image("full", np.ones((height, width), bool))
    scene.camera = cam
    bpy.context.view_layer.update()
    path = tmp_path / "rays.exr"
    assert bpy.ops.multiscale.export_rays(filepath=str(path)) == {"FINISHED"}
    ch, header = read_exr(path)
    assert set(ch) == CHANNELS and ch["depth"].shape == (height, width)
    assert header["multiscaleRaysVersion"] == 1 and header["multiscaleSpace"] == "world"
    origin, direction = vec(ch, "origin"), vec(ch, "direction")
    pinhole, eye = pixel_rays(cam, scene, width, height)
    # one straight segment from camera 1's near plane along the pinhole direction
    # sine of the angle (arccos near 1 would only measure float32 rounding)
    assert np.linalg.norm(np.cross(direction, pinhole), axis=-1).max() < 2e-6
    along = ((origin - eye) * -np.array(cam.matrix_world.col[2][:3])).sum(-1)
    np.testing.assert_allclose(along, 2.0, atol=1e-4)
    hit = ch["hit"] > 0.5
    assert 0 < hit.sum() < width * height  # the plane does not fill the view
    for y in range(height):
        for x in range(width):
            ref = scene_cast(eye, pinhole[y, x])
            assert hit[y, x] == (ref is not None), (x, y)
            if ref is None:
                assert ch["distance"][y, x] == 1e10 and ch["depth"][y, x] == 1e10
                assert ch["object_index"][y, x] == 0
                continue
            loc, obj = ref
            found = origin[y, x] + ch["distance"][y, x] * direction[y, x]
            assert np.linalg.norm(found - loc) < 1e-3, (x, y)
            assert ch["depth"][y, x] == pytest.approx(np.linalg.norm(loc - eye), abs=1e-3)
            assert ch["object_index"][y, x] == obj.pass_index
    np.testing.assert_allclose(ch["membership"], 1.0, atol=1e-6)


def polyline_first_hit(points, reach):
    """First hit along a polyline (the last segment runs on by ``reach``), cast segment by
    segment with scene.ray_cast: (location, object, arc length) or None."""
    walked = 0.0
    for k in range(len(points) - 1):
        seg = points[k + 1] - points[k]
        length = np.linalg.norm(seg)
        if length == 0:
            continue
        run = length + (reach if k == len(points) - 2 else 0.0)
        ref = scene_cast(points[k], seg / length, run)
        if ref is not None:
            return ref[0], ref[1], walked + np.linalg.norm(ref[0] - points[k])
        walked += length
    return None


def test_two_camera_tables_agree_with_the_polylines(empty_scene, tmp_path):
    """Each pixel's table ray lies on its polyline (.npz) and ends where a straight cast
    along that polyline first hits; depth is the arc length there."""
    scene = empty_scene
    width, height = 48, 36
    c1, _c2 = two_camera_scene(scene, width, height)
    path = tmp_path / "sub" / "bent.exr"
    path.parent.mkdir()
    assert bpy.ops.multiscale.export_rays(filepath=str(path)) == {"FINISHED"}
    ch, _ = read_exr(path)
    lines = np.load(tmp_path / "sub" / "bent.npz")
    assert int(lines["version"]) == 1 and list(lines["size"]) == [width, height]
    offsets, points = lines["offsets"], lines["points"].astype(np.float64)
    assert offsets.shape == (width * height + 1,) and offsets[-1] == len(points)
    r = np.arange(width * height)
    np.testing.assert_array_equal(lines["pixels"], np.stack([r % width, r // width], 1))
    # every ray starts on camera 1's near plane, start_depth from its eye
    eye = np.array(c1.matrix_world.translation)
    axis = -np.array(c1.matrix_world.col[2][:3])
    first = points[offsets[:-1]]
    np.testing.assert_allclose((first - eye) @ axis, c1.data.clip_start, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(first - eye, axis=1), lines["start_depth"], rtol=1e-5)
    assert lines["membership"].min() >= 1.0 - 1e-4 and lines["membership"].max() > 1.9
    origin, direction = vec(ch, "origin"), vec(ch, "direction")
    rng = np.random.default_rng(4)
    bent = 0
    for ray in rng.choice(width * height, 150, replace=False):
        x, y = ray % width, ray // width
        pts = points[offsets[ray] : offsets[ray + 1]]
        bent += len(pts) > 2
        ref = polyline_first_hit(pts, float(lines["reach"][ray]))
        assert (ch["hit"][y, x] > 0.5) == (ref is not None), (x, y)
        # the table's origin is a vertex of the polyline
        assert np.linalg.norm(pts - origin[y, x], axis=1).min() < 1e-4, (x, y)
        if ref is None:
            continue
        loc, obj, arc = ref
        found = origin[y, x] + ch["distance"][y, x] * direction[y, x]
        assert np.linalg.norm(found - loc) < 1e-3, (x, y)
        assert ch["depth"][y, x] == pytest.approx(lines["start_depth"][ray] + arc, abs=1e-3)
        assert ch["object_index"][y, x] == obj.pass_index
    assert bent > 10  # the sample holds bent rays, not only straight ones


def test_export_rays_bad_input(empty_scene, tmp_path):
    scene = empty_scene
    assert not bpy.ops.multiscale.export_rays.poll()  # no cameras in the list
    two_camera_scene(scene)
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.export_rays(filepath="")
    assert "Error: Export Rays needs a file path" in str(info.value)
    missing = tmp_path / "nowhere" / "rays.exr"
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.export_rays(filepath=str(missing))
    assert f"Error: Cannot write '{missing}': the folder '{missing.parent}' does not exist" in str(
        info.value
    )
    scene.multiscale.cameras[1].camera = None
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.export_rays(filepath=str(tmp_path / "rays.exr"))
    assert "Camera list item 2 has no camera" in str(info.value)
    assert not (tmp_path / "rays.exr").exists()
    # the extension is added when missing
    scene.multiscale.cameras[1].camera = bpy.data.objects["C2"]
    assert bpy.ops.multiscale.export_rays(filepath=str(tmp_path / "plain")) == {"FINISHED"}
    assert (tmp_path / "plain.exr").is_file() and (tmp_path / "plain.npz").is_file()
