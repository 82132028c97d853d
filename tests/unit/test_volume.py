"""Volume ray casting (core/volume/) against a plain numpy ray caster, and the
transfer functions of a multiscale rig."""

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from fixtures import rigs
from multiscale_camera.core import volume as V
from multiscale_camera.core.geometry import Rig, pixel_centres
from multiscale_camera.core.methods import prepare
from multiscale_camera.core.quality import erode
from multiscale_camera.core.volume import runs as volume_runs

TARGET = np.array([0.0, 0.0, 0.5])


def blob_volume(n=40, half=1.5, seed=3):
    """A lumpy ball with a dense core, in a cube of side 2 * ``half`` about TARGET,
    tilted so the voxel axes are not the world's."""
    rng = np.random.default_rng(seed)
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, n)] * 3, indexing="ij")
    r = np.sqrt(x**2 + (y / 0.8) ** 2 + z**2)
    values = np.clip(1.2 - r, 0, 1) ** 0.7
    for _ in range(6):
        c = rng.uniform(-0.5, 0.5, 3)
        values += 0.5 * np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / 0.02)
    values = V.normalise(values)
    angle = np.radians(25)
    world = np.eye(4)
    world[:3, :3] = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    world[:3, 3] = TARGET
    return V.ScalarVolume(values, V.box_to_index(values.shape, [-half] * 3, [half] * 3, world))


def rainbow_table(size=V.TABLE_SIZE, opacity=0.15):
    return V.table_from_points(
        [
            (0.0, (0, 0, 0, 0)),
            (0.2, (0.1, 0.2, 0.9, 0.0)),
            (0.5, (0.2, 0.9, 0.3, 0.4 * opacity)),
            (0.8, (1.0, 0.6, 0.1, opacity)),
            (1.0, (1.0, 1.0, 1.0, 2 * opacity)),
        ],
        size,
    )


def reference_cast(vol, table, cam, step_voxels, length):
    """A plain straight-ray caster: every pixel's pinhole ray from camera 1's near plane
    sampled at arc lengths j * step, scipy's trilinear interpolation (zero outside the
    box), the table read with np.interp, opacity corrected, composited front to back
    to the end (no skipping, no early termination). (H, W, 4) premultiplied RGBA."""
    px, py = pixel_centres(cam.width, cam.height)
    d = cam.directions(px.ravel(), py.ravel())
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = cam.near_points(d)
    h = step_voxels * vol.voxel_size
    s = np.arange(int(length / h) + 1) * h
    pts = o[:, None, :] + s[None, :, None] * d[:, None, :]  # (P, S, 3)
    m = vol.world_to_index
    idx = pts @ m[:3, :3].T + m[:3, 3]
    n = np.array(vol.shape)
    inside = ((idx >= -0.5) & (idx <= n - 0.5)).all(-1)
    val = map_coordinates(
        vol.values.astype(np.float64), idx.reshape(-1, 3).T, order=1, mode="nearest"
    ).reshape(inside.shape)
    grid = np.linspace(0, 1, len(table))
    rgba = np.stack([np.interp(val, grid, table[:, c]) for c in range(4)], -1)
    a = np.where(inside, 1 - (1 - rgba[..., 3]) ** step_voxels, 0.0)
    colour = np.zeros((len(o), 3))
    acc = np.zeros(len(o))
    for j in range(len(s)):
        w = (1 - acc) * a[:, j]
        colour += w[:, None] * rgba[:, j, :3]
        acc += w
    return np.concatenate([colour, acc[:, None]], 1).reshape(cam.height, cam.width, 4)


def psnr(a, b):
    mse = float(np.mean((np.asarray(a, np.float64) - b) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-20))


def one_camera(width=64, height=48):
    cam = rigs.camera("C1", rigs.orbit(TARGET, 8.0, 10, 20), TARGET, width, height, clip_start=2.0)
    return cam, Rig((cam,), np.ones((1, height, width), bool))


def render(fld, scene, stop=None):
    w, h = fld.rig.size
    iy, ix = np.mgrid[0:h, 0:w]
    b = fld.rays(ix.ravel(), iy.ravel())
    res = V.march_volume(scene, b.vertices, b.membership, b.reach, stop)
    rgba = np.concatenate([res.colour, res.alpha[:, None]], 1).reshape(h, w, 4)
    return rgba, res


@pytest.mark.parametrize("step", [1.0, 0.5])
@pytest.mark.parametrize("method", ["SCALAR_FIELD", "IMAGE_BLEND"])
def test_one_camera_full_mask_matches_plain_ray_caster(method, step):
    cam, rig = one_camera()
    vol = blob_volume()
    table = rainbow_table()
    scene = V.VolumeScene.build(vol, table[None], step=step)
    got, res = render(prepare(rig, method), scene)
    ref = reference_cast(vol, table, cam, step, length=12.0)
    assert ref[..., 3].max() > 0.9  # the test sees opaque and clear pixels alike
    assert (ref[..., 3] < 0.01).mean() > 0.1
    assert psnr(got, ref) >= 40.0
    assert res.skipped > 0  # the clear space around the ball was skipped


def test_skipping_and_early_termination_change_nothing_visible():
    cam, rig = one_camera(48, 36)
    vol = blob_volume()
    table = rainbow_table(opacity=0.6)
    fld = prepare(rig, "IMAGE_BLEND")
    fast = V.VolumeScene.build(vol, table[None])
    full = V.VolumeScene(vol, fast.tables, np.ones_like(fast.occupied), 1.0)
    a, ra = render(fld, fast)
    b, rb = render(fld, full)
    assert ra.samples < rb.samples and ra.skipped > 0
    assert np.abs(a - b).max() <= 1 - V.EARLY_TERMINATION + 1e-6


def test_empty_transfer_function_skips_every_block():
    _cam, rig = one_camera(32, 24)
    scene = V.VolumeScene.build(blob_volume(), np.zeros((1, 16, 4), np.float32))
    assert not scene.occupied.any()
    rgba, res = render(prepare(rig, "IMAGE_BLEND"), scene)
    assert res.samples == 0 and not rgba.any()


def test_occupied_blocks_cover_every_readable_voxel():
    """A block is empty only if no trilinear sample in it can read an opaque value."""
    rng = np.random.default_rng(0)
    values = (rng.random((19, 12, 9)) > 0.97).astype(np.float32)
    table = np.zeros((1, 8, 4), np.float32)
    table[0, -1, 3] = 1.0  # only the value 1 is visible
    lo, hi = V.block_ranges(values, 4)
    occ = V.occupied_blocks(lo, hi, table)
    for i, j, k in zip(*np.nonzero(values)):
        for di in (0, -1):
            for dj in (0, -1):
                for dk in (0, -1):
                    b = (max(i + di, 0) // 4, max(j + dj, 0) // 4, max(k + dk, 0) // 4)
                    assert occ[b]


def test_surface_stops_the_march():
    cam, rig = one_camera(32, 24)
    vol = blob_volume()
    scene = V.VolumeScene.build(vol, rainbow_table()[None])
    fld = prepare(rig, "IMAGE_BLEND")
    open_, _ = render(fld, scene)
    w, h = rig.size
    near = np.full(w * h, 1e-3)
    blocked, res = render(fld, scene, stop=near)
    assert open_[..., 3].max() > 0.5 and not blocked.any() and res.samples == 0


def test_composite_over_orders_layers_by_entry():
    red = V.VolumeResult(
        np.array([[0.5, 0, 0]], np.float32),
        np.array([0.5], np.float32),
        np.array([2.0]),
        np.array([2.5]),
    )
    blue = V.VolumeResult(
        np.array([[0, 0, 1.0]], np.float32),
        np.array([1.0], np.float32),
        np.array([1.0]),
        np.array([1.2]),
    )
    col, alpha, depth = V.composite_over([red, blue], np.ones((1, 3)), np.ones(1))
    np.testing.assert_allclose(col, [[0, 0, 1]])  # blue is in front and opaque
    assert alpha[0] == 1 and depth[0] == 1.2
    col, alpha, _ = V.composite_over([red], np.array([[0, 1.0, 0]]), np.ones(1))
    np.testing.assert_allclose(col, [[0.5, 0.5, 0]])


def test_box_to_index_places_voxel_centres_in_cells():
    world = np.eye(4)
    world[:3, 3] = (1, 2, 3)
    m = V.box_to_index((4, 2, 8), (-1, -1, -2), (1, 1, 2), world)
    centre = np.array([1 - 1 + 0.25, 2 - 1 + 0.5, 3 - 2 + 0.25, 1.0])  # voxel (0, 0, 0)
    np.testing.assert_allclose(m @ centre, [0, 0, 0, 1], atol=1e-12)
    vol = V.ScalarVolume(np.zeros((4, 2, 8), np.float32), m)
    assert vol.voxel_size == pytest.approx(0.5)
    np.testing.assert_allclose(vol.corners().min(0), [0, 1, 1])


def slab_volume(shape=(48, 48, 10), seed=5):
    """Lumpy ground-like material in a wide flat box under the zoom rig's target, so
    both cameras' preserved regions see it."""
    rng = np.random.default_rng(seed)
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape], indexing="ij")
    values = np.zeros(shape)
    for _ in range(40):
        c = rng.uniform(-1, 1, 3)
        values += np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2) / 0.01 - (z - c[2]) ** 2 / 0.3)
    return V.ScalarVolume(
        V.normalise(values), V.box_to_index(shape, (-8, -8, -0.5), (8, 8, 1.0), np.eye(4))
    )


def solid_table(rgb, opacity=0.3):
    return V.table_from_points([(0.0, (*rgb, 0.0)), (0.3, (*rgb, opacity)), (1.0, (*rgb, 1.0))])


@pytest.mark.slow
def test_each_camera_uses_its_own_transfer_function_where_preserved():
    cams, masks = rigs.zoom_rig(96, 72)
    rig = Rig(cams, masks)
    vol = slab_volume()
    tables = np.stack([solid_table((1, 0, 0)), solid_table((0, 1, 0))])
    scene = V.VolumeScene.build(vol, tables)
    rgba, _ = render(prepare(rig, "SCALAR_FIELD"), scene)
    seen = rgba[..., 3] > 0.2
    for i, (own, other) in enumerate(((0, 1), (1, 0))):
        region = erode(masks[i]) & seen
        assert region.sum() > 50, f"camera {i + 1} sees too little of the volume"
        c = rgba[region]
        assert (c[:, own] > 0.2).all()
        # membership is i there up to float noise of the solved field (1e-3 seen)
        assert (c[:, other] <= 1e-2 * c[:, own]).all()
    # the transition between them blends the two
    between = ~masks.any(0) & seen
    assert ((rgba[between, 0] > 0.05) & (rgba[between, 1] > 0.05)).any()


def test_gradient_shading_darkens_surfaces_seen_edge_on():
    """A ball of one value with an opaque transfer function: shaded, its centre (surface
    facing the eye) keeps its colour and its rim (seen edge on) darkens toward the
    ambient share."""
    n = 48
    x, y, z = np.meshgrid(*[np.linspace(-1, 1, n)] * 3, indexing="ij")
    ball = np.clip((0.8 - np.sqrt(x**2 + y**2 + z**2)) * n / 4 + 0.5, 0, 1)
    at = np.eye(4)
    at[:3, 3] = TARGET
    vol = V.ScalarVolume(
        ball.astype(np.float32), V.box_to_index(ball.shape, [-1.5] * 3, [1.5] * 3, at)
    )
    table = V.table_from_points([(0.0, (1, 1, 1, 0)), (0.5, (1, 1, 1, 0)), (1.0, (1, 1, 1, 1))])
    cam, rig = one_camera(48, 48)
    fld = prepare(rig, "IMAGE_BLEND")
    flat, _ = render(fld, V.VolumeScene.build(vol, table[None]))
    lit, _ = render(fld, V.VolumeScene.build(vol, table[None], shading=True))
    seen = flat[..., 3] > 0.99
    ratio = lit[..., 0][seen] / flat[..., 0][seen]
    yy, xx = np.nonzero(seen)
    r = np.hypot(xx - xx.mean(), yy - yy.mean())
    centre, rim = ratio[r < 0.2 * r.max()], ratio[r > 0.9 * r.max()]
    assert centre.min() > 0.9
    assert rim.mean() < 0.75 and rim.min() >= V.SHADE_AMBIENT - 1e-6


def test_threads_change_nothing_and_should_stop_cancels():
    from multiscale_camera.core.errors import Cancelled

    _cam, rig = one_camera(40, 30)
    scene = V.VolumeScene.build(blob_volume(), rainbow_table()[None], shading=True)
    b = prepare(rig, "IMAGE_BLEND").rays(*np.mgrid[0:30, 0:40][::-1].reshape(2, -1))
    one = V.march_volume(scene, b.vertices, b.membership, b.reach, threads=1)
    two = V.march_volume(scene, b.vertices, b.membership, b.reach, threads=2)
    np.testing.assert_array_equal(one.colour, two.colour)
    assert one.samples == two.samples > 0
    with pytest.raises(Cancelled):
        V.march_volume(scene, b.vertices, b.membership, b.reach, should_stop=lambda: True)


def test_gradient_directions_are_numpy_gradients_normalised_slab_by_slab():
    rng = np.random.default_rng(0)
    v = rng.random((37, 20, 9)).astype(np.float32)
    v[:, :, 4] = 0.5  # a flat layer... still has gradients from its neighbours
    g = np.stack(np.gradient(v), -1)
    n = np.linalg.norm(g, axis=-1, keepdims=True)
    ref = np.where(n > V.MIN_GRADIENT, np.rint(g / np.maximum(n, 1e-30) * 127), 0)
    for slab in (1, 4, 100):
        got = V.gradient_directions(v, slab=slab).view(np.int8).reshape(-1, 4)
        np.testing.assert_array_equal(got[:, :3], ref.astype(np.int8).reshape(-1, 3))
        assert not got[:, 3].any()
    flat = V.gradient_directions(np.ones((5, 4, 3), np.float32))
    assert not flat.any()  # no gradient, no direction


def test_block_ranges_are_the_ranges_of_each_block_and_its_far_layers():
    rng = np.random.default_rng(4)
    v = rng.random((19, 12, 9)).astype(np.float32)
    lo, hi = V.block_ranges(v, 4)
    assert lo.shape == (5, 3, 3)
    for i, j, k in np.ndindex(*lo.shape):
        box = v[4 * i : 4 * i + 5, 4 * j : 4 * j + 5, 4 * k : 4 * k + 5]
        assert lo[i, j, k] == box.min() and hi[i, j, k] == box.max()


def test_occupancy_of_block_boxes_matches_brute_force():
    """One read of the bit table for boxes of at most two blocks a side, the summed
    table for wider ones: both give whether any block of the box is occupied under the
    cameras between the box's lowest and highest."""
    rng = np.random.default_rng(7)
    cams = rng.random((3, 6, 5, 7)) > 0.93
    tables = np.zeros((3, 8, 4), np.float32)
    scene = V.VolumeScene(
        V.ScalarVolume(np.zeros((48, 40, 56), np.float32), np.eye(4)),
        tables,
        cams.any(0),
        camera_occupied=cams,
    )
    shape = np.array(cams.shape[1:])
    b0 = rng.integers(0, shape, (4000, 3))
    reach = np.where(rng.random((4000, 1)) < 0.7, 1, 5)
    b1 = np.clip(b0 + rng.integers(-reach, reach + 1, (4000, 3)), 0, shape - 1)
    lo_cam = rng.integers(0, 3, 4000)
    hi_cam = np.minimum(lo_cam + rng.integers(0, 3, 4000), 2)
    got = volume_runs._occupied(
        scene,
        list(b0.T.astype(np.int32)),
        list(b1.T.astype(np.int32)),
        (lo_cam.astype(np.int32), hi_cam.astype(np.int32)),
    )
    lo, hi = np.minimum(b0, b1), np.maximum(b0, b1) + 1
    want = [
        cams[c0 : c1 + 1, x0:x1, y0:y1, z0:z1].any()
        for (x0, y0, z0), (x1, y1, z1), c0, c1 in zip(lo, hi, lo_cam, hi_cam)
    ]
    assert (np.abs(b0 - b1) > 1).any(1).sum() > 500  # both paths are exercised
    np.testing.assert_array_equal(got, want)


@pytest.mark.slow
def test_skipping_by_each_cameras_own_table_changes_nothing_visible():
    """Blocks clear under the tables a ray's membership weighs are skipped even where
    another camera's table would show them: the image is the one marched without any
    skipping, with fewer samples."""
    cams, masks = rigs.zoom_rig(64, 48)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD")
    vol = slab_volume()
    wide = solid_table((1, 0, 0), opacity=0.3)
    narrow = V.table_from_points(
        [(0.0, (0, 1, 0, 0.0)), (0.6, (0, 1, 0, 0.0)), (0.8, (0, 1, 0, 0.5)), (1.0, (0, 1, 0, 1))]
    )
    fast = V.VolumeScene.build(vol, np.stack([wide, narrow]))
    assert (fast.camera_occupied[0] & ~fast.camera_occupied[1]).any()
    union = V.VolumeScene.build(vol, np.stack([wide, narrow]))
    union.__init__(vol, fast.tables, fast.occupied)  # every camera: the union's blocks
    full = V.VolumeScene(vol, fast.tables, np.ones_like(fast.occupied))
    a, ra = render(fld, fast)
    b, rb = render(fld, union)
    c, rc = render(fld, full)
    assert a[..., 3].max() > 0.5
    assert ra.samples < rb.samples <= rc.samples
    assert np.abs(a - c).max() <= 1 - V.EARLY_TERMINATION + 1e-6
    assert np.abs(b - c).max() <= 1 - V.EARLY_TERMINATION + 1e-6
