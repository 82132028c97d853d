"""Volume sources in Blender: placement by the world transform, transfer functions from
colour ramps, meshes composited by depth, and each bad input's exact message."""

import math

import bpy
import numpy as np
import pytest

from fixtures.blender.objects import add_camera, add_mesh, mask_image, transfer_function
from fixtures.masks import disk_masks
from fixtures.rigs import orbit
from multiscale_camera.adapters import volumes as adapters
from multiscale_camera.core import volume as V
from multiscale_camera.render import fields, pipeline
from multiscale_camera.render import volume as render_volume
from tests.unit.test_volume import erode, psnr, reference_cast, slab_volume

W, H = 48, 36
RAMP = [  # position, RGBA: what the test's camera sees
    (0.0, (0.0, 0.0, 0.0, 0.0)),
    (0.3, (0.1, 0.3, 0.9, 0.02)),
    (0.6, (0.9, 0.8, 0.2, 0.2)),
    (1.0, (1.0, 0.2, 0.1, 0.7)),
]


@pytest.fixture(autouse=True)
def fresh_caches():
    fields.SERVICE.volume_grids.clear()
    pipeline.clear_fields()
    yield


def lumpy(shape=(24, 20, 16), seed=2):
    rng = np.random.default_rng(seed)
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape], indexing="ij")
    v = np.clip(1.0 - np.sqrt(x**2 + y**2 + z**2), 0, 1)
    for _ in range(5):
        c = rng.uniform(-0.5, 0.5, 3)
        v += 0.6 * np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / 0.03)
    return (v * 1000).astype(np.float32)  # not in [0, 1]: auto range maps it there


def ramp_texture(points=RAMP):
    return transfer_function("TF test", points)


def one_camera_scene(scene):
    scene.render.resolution_x, scene.render.resolution_y = W, H
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    scene.render.engine = "MULTISCALE"
    cam = add_camera(scene, "C1", (2.0, -7.0, 3.0), (0.3, 0.2, 0.4), clip_start=1.0)
    item = scene.multiscale.cameras.add()
    item.camera = cam
    item.mask = mask_image("full", np.ones((H, W), bool))
    item.transfer_function = ramp_texture()
    scene.multiscale.volume_shading = False
    scene.camera = cam
    return cam


def trs(location, rotation_deg, scale):
    """(4, 4) world matrix from location, XYZ Euler degrees and scale, in numpy."""
    ax, ay, az = np.radians(rotation_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rz @ ry @ rx @ np.diag(scale)
    m[:3, 3] = location
    return m


PLACE = ((0.3, 0.2, 0.4), (20.0, -15.0, 35.0), (1.2, 0.8, 1.0))


def render_passes(scene):
    bpy.context.view_layer.update()
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    return frame, pipeline.render_rows(frame, 0, frame.size[1])


def expected(cam_obj, values, world_to_index, step=1.0):
    from multiscale_camera.adapters.cameras import pinhole_from_object

    scene = bpy.context.scene
    vol = V.ScalarVolume(V.normalise(values), world_to_index)
    table = V.table_from_points(RAMP)
    return reference_cast(vol, table, pinhole_from_object(cam_obj, scene), step, 20.0)


def file_box(scene, path, empty=True):
    if empty:
        obj = bpy.data.objects.new("Box", None)
        obj.empty_display_type = "CUBE"
        obj.empty_display_size = 1.0
        scene.collection.objects.link(obj)
    else:
        obj = add_mesh("cube", (0, 0, 0), 4)  # a 2-unit cube
        obj.name = "Box"
    obj.location, obj.scale = PLACE[0], PLACE[2]
    obj.rotation_euler = [math.radians(a) for a in PLACE[1]]
    obj.multiscale_volume.use = True
    obj.multiscale_volume.filepath = str(path)
    return obj


@pytest.mark.parametrize("empty", [True, False])
def test_file_volume_fills_the_object_box(empty_scene, tmp_path, empty):
    """A .npy in a rotated, scaled box matches the plain caster on the same voxels placed
    by a matrix built here in numpy; a mesh box is not drawn as a surface."""
    scene = empty_scene
    cam = one_camera_scene(scene)
    values = lumpy()
    np.save(tmp_path / "v.npy", values)
    file_box(scene, tmp_path / "v.npy", empty)
    frame, passes = render_passes(scene)
    assert len(frame.geometry) == 0 and pipeline.NO_MESH not in frame.notices
    to_index = V.box_to_index(values.shape, (-1, -1, -1), (1, 1, 1), trs(*PLACE))
    ref = expected(cam, values, to_index)
    got = passes["Combined"]
    assert ref[..., 3].max() > 0.5 and (ref[..., 3] < 0.01).mean() > 0.1
    assert psnr(got, ref) >= 40.0


def write_vdb(path, values, voxel, grids=("density",), vector=False):
    vdb = adapters.openvdb_module()
    out = []
    for name in grids:
        g = vdb.Vec3SGrid() if vector else vdb.FloatGrid()
        data = np.repeat(values[..., None], 3, -1) if vector else values
        g.copyFromArray(np.ascontiguousarray(data), ijk=(5, -3, 7))
        g.transform = vdb.createLinearTransform(voxelSize=voxel)
        g.name = name
        out.append(g)
    vdb.write(str(path), grids=out)


def volume_object(scene, path, name="Vol"):
    data = bpy.data.volumes.new(name)
    data.filepath = str(path)
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    return obj


def test_grid_cache_keeps_the_newest_sources():
    cache = adapters.VolumeGridCache(keep=2)
    made = []
    for key in ("a", "b", "a", "c", "a", "b"):
        assert cache.get(key, lambda key=key: made.append(key) or key.upper()) == key.upper()
    # "a" was read again before "c" came, so "b" went first; "c" went when "b" came back
    assert made == ["a", "b", "c", "b"] and len(cache) == 2
    cache.clear()
    assert len(cache) == 0


def test_frames_share_the_decoded_volume(empty_scene, tmp_path, monkeypatch):
    """Two frames of an unchanged volume file read and decode it once."""
    scene = empty_scene
    one_camera_scene(scene)
    path = tmp_path / "v.npy"
    np.save(path, lumpy())
    file_box(scene, path)
    reads = []
    read = adapters.read_volume
    monkeypatch.setattr(adapters, "read_volume", lambda *args: reads.append(args) or read(*args))
    for _ in range(2):
        bpy.context.view_layer.update()
        volumes, _ = render_volume.prepare_volumes(bpy.context.evaluated_depsgraph_get())
        assert len(volumes.scenes) == 1
    assert len(reads) == 1 and len(fields.SERVICE.volume_grids) == 1


def test_openvdb_is_found_in_this_blender():
    assert adapters.openvdb_module() is not None


def test_volume_object_grid_is_placed_by_its_transforms(empty_scene, tmp_path):
    """A .vdb grid (index origin and voxel size of its own) under a rotated object: the
    voxel at index (5, -3, 7) + (i, j, k) sits at voxel * that index in object space."""
    scene = empty_scene
    cam = one_camera_scene(scene)
    values = lumpy()
    write_vdb(tmp_path / "v.vdb", values, voxel=0.1)
    obj = volume_object(scene, tmp_path / "v.vdb")
    obj.location, obj.scale = PLACE[0], PLACE[2]
    obj.rotation_euler = [math.radians(a) for a in PLACE[1]]
    _frame, passes = render_passes(scene)
    index_to_object = np.diag([0.1, 0.1, 0.1, 1.0])
    index_to_object[:3, 3] = np.array([5, -3, 7]) * 0.1
    to_index = np.linalg.inv(trs(*PLACE) @ index_to_object)
    ref = expected(cam, values, to_index)
    assert ref[..., 3].max() > 0.5
    assert psnr(passes["Combined"], ref) >= 40.0


def test_meshes_and_volumes_composite_by_depth(empty_scene, tmp_path):
    """A plane in front of the volume hides it; a plane behind it shows through:
    there the image is the volume alone laid over the plane alone."""
    scene = empty_scene
    cam = one_camera_scene(scene)
    np.save(tmp_path / "v.npy", lumpy())
    box = file_box(scene, tmp_path / "v.npy")
    front = add_mesh("plane", (1.55, -3.76, 2.1), 7, (0.0, 1.0, 0.0), size=0.4)
    back = add_mesh("plane", (-1.0, 4.0, -0.5), 8, (1.0, 0.0, 1.0), size=30)
    for plane in (front, back):
        plane.rotation_euler = cam.rotation_euler
    bpy.ops.object.light_add(type="SUN", rotation=cam.rotation_euler)
    both = render_passes(scene)[1]
    box.multiscale_volume.use = False
    planes = render_passes(scene)[1]
    box.multiscale_volume.use = True
    for plane in (front, back):
        bpy.data.objects.remove(plane)
    alone = render_passes(scene)[1]
    index = both["IndexOB"][..., 0]
    assert (index == 7).sum() > 20 and (index == 8).sum() > 20
    np.testing.assert_array_equal(index, planes["IndexOB"][..., 0])
    hidden, behind = index == 7, index == 8
    assert alone["Combined"][hidden, 3].max() > 0.3  # the volume is there, behind the plane
    np.testing.assert_allclose(both["Combined"][hidden], planes["Combined"][hidden], atol=1e-6)
    a_v = alone["Combined"][behind, 3:]
    over = alone["Combined"][behind, :3] + (1 - a_v) * planes["Combined"][behind, :3]
    assert a_v.max() > 0.5 and a_v.min() < 0.01
    np.testing.assert_allclose(both["Combined"][behind, :3], over, atol=1e-5)
    # depth: the volume's half-opacity point where it is dense, the plane elsewhere
    d_both, d_planes = both["Depth"][..., 0], planes["Depth"][..., 0]
    dense = behind & (alone["Combined"][..., 3] > 0.6)
    assert (d_both[dense] < d_planes[dense] - 0.1).all()
    clear = behind & (alone["Combined"][..., 3] < 0.4)
    np.testing.assert_allclose(d_both[clear], d_planes[clear])


def render_error():
    with pytest.raises(RuntimeError) as info:
        bpy.ops.render.render()
    return str(info.value)


def test_volume_object_without_grids(empty_scene):
    scene = empty_scene
    one_camera_scene(scene)
    volume_object(scene, "", name="Cloud")
    msg = (
        "Volume object 'Cloud' has no grids: set a .vdb file in its Object Data properties, "
        "or remove it from the scene"
    )
    assert f"Error: Multiscale: {msg}" in render_error()


def test_volume_object_with_a_vector_grid(empty_scene, tmp_path):
    scene = empty_scene
    one_camera_scene(scene)
    write_vdb(tmp_path / "wind.vdb", lumpy(), 0.1, grids=("velocity",), vector=True)
    volume_object(scene, tmp_path / "wind.vdb", name="Wind")
    msg = (
        "Volume object 'Wind': grid 'velocity' holds vector values; only scalar grids "
        "(float, double, int) can be rendered: name a scalar grid in Object Properties > "
        "Multiscale Volume > Grid"
    )
    assert f"Error: Multiscale: {msg}" in render_error()


def test_volume_object_without_openvdb(empty_scene, tmp_path, monkeypatch):
    scene = empty_scene
    one_camera_scene(scene)
    write_vdb(tmp_path / "v.vdb", lumpy(), 0.1)
    volume_object(scene, tmp_path / "v.vdb", name="Smoke")
    monkeypatch.setattr(adapters, "openvdb_module", lambda: None)
    msg = adapters.NO_OPENVDB.format(name="Smoke")
    assert msg.startswith("Volume object 'Smoke': this Blender has no openvdb Python module")
    assert f"Error: Multiscale: {msg}" in render_error()


def test_raw_file_of_the_wrong_size(empty_scene, tmp_path):
    scene = empty_scene
    one_camera_scene(scene)
    np.zeros(1000, np.uint8).tofile(tmp_path / "ct.raw")
    box = file_box(scene, tmp_path / "ct.raw")
    box.multiscale_volume.dims = (10, 10, 11)
    msg = (
        "Object 'Box': 'ct.raw' holds 1000 bytes, but 10x10x11 voxels of uint8 need 1100: "
        "check the dimensions and the value type"
    )
    assert f"Error: Multiscale: {msg}" in render_error()
    assert box.multiscale_volume.filepath.endswith("ct.raw")  # nothing the user made is lost


def test_missing_volume_file(empty_scene, tmp_path):
    scene = empty_scene
    one_camera_scene(scene)
    path = tmp_path / "gone.nrrd"
    file_box(scene, path)
    msg = (
        f"Object 'Box': the volume file '{path}' does not exist; fix the path in "
        "Object Properties > Multiscale Volume"
    )
    assert f"Error: Multiscale: {msg}" in render_error()
    with pytest.raises(RuntimeError) as info:
        bpy.ops.multiscale.validate()
    assert f"Error: {msg}" in str(info.value)  # Check Rig says it before a render


def test_transfer_function_operator_gives_the_default_ramp(empty_scene):
    scene = empty_scene
    one_camera_scene(scene)
    item = scene.multiscale.cameras[0]
    item.transfer_function = None
    assert bpy.ops.multiscale.transfer_function_new() == {"FINISHED"}
    tex = item.transfer_function
    assert tex is not None and tex.type == "BLEND" and tex.use_color_ramp
    np.testing.assert_allclose(adapters.ramp_table(tex), V.default_table(), atol=1e-6)
    tables, notices = adapters.transfer_tables(scene.multiscale)
    assert tables.shape == (1, V.TABLE_SIZE, 4) and not notices
    tex.use_color_ramp = False
    tables, notices = adapters.transfer_tables(scene.multiscale)
    assert notices == [
        "Camera 'C1': the transfer function texture 'TF C1' has no colour ramp (enable it "
        "in the panel); the default transfer function is used"
    ]


def test_engine_writes_the_volume_into_the_render_result(empty_scene, tmp_path):
    from tests.exr import read_passes

    scene = empty_scene
    one_camera_scene(scene)
    np.save(tmp_path / "v.npy", lumpy())
    file_box(scene, tmp_path / "v.npy")
    _frame, passes = render_passes(scene)
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.filepath = str(tmp_path / "out.exr")
    bpy.ops.render.render(write_still=True)
    got = read_passes(tmp_path / "out.exr")
    assert passes["Combined"][..., 3].max() > 0.5
    np.testing.assert_allclose(got["Combined"], passes["Combined"], atol=1e-5)


def test_volume_modifiers_are_named_as_not_applied(empty_scene, tmp_path):
    scene = empty_scene
    one_camera_scene(scene)
    write_vdb(tmp_path / "v.vdb", lumpy(), 0.1)
    obj = volume_object(scene, tmp_path / "v.vdb", name="Smoke")
    obj.modifiers.new("Displace", "VOLUME_DISPLACE")
    frame, passes = render_passes(scene)
    assert (
        "Volume object 'Smoke': its modifiers are not applied here; the grid in its file "
        "is rendered"
    ) in frame.notices
    assert passes["Combined"][..., 3].max() > 0.5


def test_raw_and_nrrd_files_render_as_the_npy_does(empty_scene, tmp_path):
    from multiscale_camera.io.volume_files import write_nrrd

    scene = empty_scene
    one_camera_scene(scene)
    values = np.round(lumpy() / 3).astype(np.uint16)
    np.save(tmp_path / "v.npy", values)
    np.ascontiguousarray(values.transpose(2, 1, 0)).astype(">u2").tofile(tmp_path / "v.raw")
    write_nrrd(tmp_path / "v.nrrd", values)
    box = file_box(scene, tmp_path / "v.npy")
    images = {}
    for name in ("v.npy", "v.raw", "v.nrrd"):
        box.multiscale_volume.filepath = str(tmp_path / name)
        box.multiscale_volume.dims = values.shape
        box.multiscale_volume.value_type = "UINT16"
        box.multiscale_volume.little_endian = False
        images[name] = render_passes(scene)[1]["Combined"]
    assert images["v.npy"][..., 3].max() > 0.5
    np.testing.assert_array_equal(images["v.raw"], images["v.npy"])
    np.testing.assert_array_equal(images["v.nrrd"], images["v.npy"])


@pytest.mark.slow
def test_each_camera_shows_its_own_colour_ramp_where_preserved(empty_scene, tmp_path):
    """Two cameras, a red ramp and a green ramp on their textures: in each camera's
    eroded mask the image has that camera's colour only; between them, both."""
    scene = empty_scene
    w, h = 96, 72
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.resolution_percentage = 100
    scene.render.engine = "MULTISCALE"
    target = (0.0, 0.0, 0.5)
    masks = disk_masks(w, h, 0.2 * w, 0.35 * w)
    for name, dist, turn, clip, mask, rgb in (
        ("C1", 20.0, 0, 8.0, masks[0], (1.0, 0.0, 0.0)),
        ("C2", 5.0, 20, 2.5, masks[1], (0.0, 1.0, 0.0)),
    ):
        cam = add_camera(scene, name, tuple(orbit(target, dist, turn, 25)), target, clip_start=clip)
        item = scene.multiscale.cameras.add()
        item.camera, item.mask = cam, mask_image(f"{name} mask", mask)
        ramp = [(0.0, (*rgb, 0.0)), (0.3, (*rgb, 0.3)), (1.0, (*rgb, 1.0))]
        item.transfer_function = ramp_texture(ramp)
    scene.camera = scene.multiscale.cameras[0].camera
    scene.multiscale.volume_shading = False  # colours as the ramps give them
    scene.render.film_transparent = True
    np.save(tmp_path / "slab.npy", slab_volume().values)
    box = bpy.data.objects.new("Slab", None)
    box.empty_display_type = "CUBE"
    scene.collection.objects.link(box)
    box.location, box.scale = (0.0, 0.0, 0.25), (8.0, 8.0, 0.75)
    box.multiscale_volume.use = True
    box.multiscale_volume.filepath = str(tmp_path / "slab.npy")
    rgba = render_passes(scene)[1]["Combined"]
    seen = rgba[..., 3] > 0.2
    for i, (own, other) in enumerate(((0, 1), (1, 0))):
        region = erode(masks[i]) & seen
        assert region.sum() > 50, f"camera {i + 1} sees too little of the slab"
        c = rgba[region]
        assert (c[:, own] > 0.2).all()
        assert (c[:, other] <= 1e-2 * c[:, own]).all()
    between = ~masks.any(0)
    assert ((rgba[between, 0] > 0.05) & (rgba[between, 1] > 0.05)).any()
