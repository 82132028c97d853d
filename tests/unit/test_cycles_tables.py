"""The hand-off's table helpers in plain numpy: camera space, the two-plane table, edge
padding and the blocks of pinhole rays."""

import re

import bpy  # noqa: F401 (the render layer needs mathutils, which bpy provides)
import numpy as np

from fixtures.rigs import look_at, three_camera_rig
from multiscale_camera.render.cycles_rays import (
    PAD,
    PINHOLE_TOLERANCE_PX,
    UNUSABLE,
    UNUSABLE_LIMIT,
    camera_space,
    pad_edges,
    pinhole_affine,
    pinhole_blocks,
    pinhole_classes,
    pinhole_rays,
    plane_rays,
)
from multiscale_camera.render.cycles_shader import OSL_PATH, shader_source
from multiscale_camera.render.tables import RayTables


def test_camera_space_is_cycles_camera_frame():
    """+Z toward what the camera looks at, +X to its right, +Y up; the object's scale is
    not part of the frame (Cycles drops it)."""
    eye, target = np.array([3.0, -7.0, 2.0]), np.array([0.5, 1.0, 0.0])
    m = look_at(eye, target)
    scaled = m.copy()
    scaled[:3, :3] *= np.array([2.0, 0.5, 3.0])  # column scales, as an object scale gives
    right, up = m[:3, 0], m[:3, 1]
    dist = np.linalg.norm(target - eye)
    points = np.array([target, eye + right, eye + 2 * up])
    vectors = np.array([target - eye, right, -up])
    for matrix in (m, scaled):
        p, v = camera_space(points, vectors, matrix)
        np.testing.assert_allclose(p, [[0, 0, dist], [1, 0, 0], [0, 2, 0]], atol=1e-12)
        np.testing.assert_allclose(v, [[0, 0, dist], [1, 0, 0], [0, -1, 0]], atol=1e-12)


def test_pad_edges_extrapolates_linear_tables_exactly():
    h, w = 5, 7
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    table = np.stack([2 * xx - 1, 0.5 * yy + 3, xx * 0.25 - yy], axis=-1)
    padded = pad_edges(table, PAD)
    yy, xx = np.mgrid[-PAD : h + PAD, -PAD : w + PAD].astype(np.float64)
    expected = np.stack([2 * xx - 1, 0.5 * yy + 3, xx * 0.25 - yy], axis=-1)
    np.testing.assert_allclose(padded, expected, atol=1e-12)
    column = np.arange(4.0).reshape(4, 1, 1)
    np.testing.assert_array_equal(pad_edges(column, 1)[1:-1, :, 0], np.repeat(column[..., 0], 3, 1))


def test_shader_maps_pixel_centres_to_texel_centres():
    """The shader's lookup: raster (x + 0.5) / W -> texel x + PAD of the padded table,
    and raster row 0 at the bottom -> the table's bottom row (tables are top-first)."""
    source = shader_source(None)
    assert "float s = (raster[0] * width + pad) / (width + 2 * pad);" in source
    assert "float t = 1.0 - (raster[1] * height + pad) / (height + 2 * pad);" in source
    w, h = 40, 30
    x, y_top = np.arange(w), np.arange(h)
    s = ((x + 0.5) / w * w + PAD) / (w + 2 * PAD)
    raster_y = 1.0 - (y_top + 0.5) / h  # the raster position of top-first row y_top
    t = 1.0 - (raster_y * h + PAD) / (h + 2 * PAD)
    np.testing.assert_allclose(s * (w + 2 * PAD) - 0.5, x + PAD)
    np.testing.assert_allclose(t * (h + 2 * PAD) - 0.5, y_top + PAD)


def test_plane_rays_hold_each_ray_on_its_line():
    """Each held ray crosses z = depth at the stored point, heads along the stored slopes,
    and reaches its origin ``back`` further on; depth is the nearest held origin."""
    rng = np.random.default_rng(3)
    direction = rng.normal(size=(6, 5, 3))
    direction[..., 2] = np.abs(direction[..., 2]) + 0.2
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    origin = rng.uniform(-2.0, 2.0, size=(6, 5, 3)) + [0.0, 0.0, 5.0]
    depth, table, back = plane_rays(origin, direction)
    assert depth == origin[..., 2].min()
    assert (back >= 0).all() and back.min() == 0.0
    start = np.concatenate([table[..., :2], np.full((6, 5, 1), depth)], axis=-1)
    np.testing.assert_allclose(start + back[..., None] * direction, origin, atol=1e-12)
    slopes = np.concatenate([table[..., 2:], np.ones((6, 5, 1))], axis=-1)
    unit = slopes / np.linalg.norm(slopes, axis=-1, keepdims=True)
    np.testing.assert_allclose(unit, direction, atol=1e-12)


def test_plane_rays_of_a_pinhole_are_affine_in_the_pixel():
    """A pinhole's rays from its near plane: both the crossing point and the slopes are
    affine in the pixel position, so bilinear lookups between texels give the pinhole's
    own ray at any sub-pixel position."""
    yy, xx = np.mgrid[0:7, 0:9].astype(np.float64)
    lx, ly = 0.1 * xx - 0.4, 0.3 - 0.08 * yy
    ray = np.stack([lx, ly, np.ones_like(lx)], axis=-1)
    direction = ray / np.linalg.norm(ray, axis=-1, keepdims=True)
    origin = ray * 2.5  # on the near plane z = 2.5
    depth, table, back = plane_rays(origin, direction)
    assert depth == 2.5
    np.testing.assert_allclose(back, 0.0, atol=1e-12)
    expected = np.stack([2.5 * lx, 2.5 * ly, lx, ly], axis=-1)
    np.testing.assert_allclose(table, expected, atol=1e-12)


def test_plane_rays_mark_rays_that_do_not_head_forward():
    origin = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 3.0], [0.0, 0.0, 0.5], [0.0, 0.0, 0.2]])
    direction = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    depth, table, back = plane_rays(origin, direction)
    assert depth == 1.0  # the rays it does not hold do not move the plane
    np.testing.assert_array_equal(table[0], [0.0, 0.0, 0.0, 0.0])
    assert (table[1:] == UNUSABLE).all() and (back[1:] == 0).all()
    # padding extrapolated from a marked texel is marked too (the shader reads the
    # origin and direction tables there), never an ordinary-looking ray
    padded = pad_edges(table[None, :2], PAD)  # one row: a held texel, a marked one
    marked = (np.abs(padded) > UNUSABLE_LIMIT).all(axis=-1)
    expected = np.ones(padded.shape[:2], dtype=bool)
    expected[:, PAD] = False  # the held texel's column (one row is repeated up and down)
    np.testing.assert_array_equal(marked, expected)
    np.testing.assert_array_equal(padded[:, PAD], np.zeros((1 + 2 * PAD, 4)))
    assert np.isfinite(padded).all()
    assert f"< {UNUSABLE_LIMIT!r})" in shader_source(None) and UNUSABLE < 1e38  # float32 holds it


def tables_of(origin, direction):
    """RayTables holding only the rays (the other fields unused by the classification)."""
    shape = origin.shape[:2]
    zeros = np.zeros(shape)
    return RayTables(origin, direction, zeros, zeros, zeros > 0, zeros, zeros, 0)


def test_pinhole_affine_gives_each_cameras_rays_at_any_raster_position():
    """The shader's affine rays at raster (rx, ry) are the rig camera's own rays through
    that image point, in the render camera's space (the direction up to its length)."""
    cameras, _ = three_camera_rig(48, 27)
    render = cameras[0].matrix_world
    rng = np.random.default_rng(3)
    rx, ry = rng.uniform(-0.05, 1.05, (2, 50))  # the pixel filter reaches past the edges
    for cam in cameras:
        a = pinhole_affine(cam, render)
        origin = a[0:3] + rx[:, None] * a[3:6] + ry[:, None] * a[6:9]
        direction = a[9:12] + rx[:, None] * a[12:15] + ry[:, None] * a[15:18]
        world, _ = pinhole_rays(cam, rx * cam.width, (1.0 - ry) * cam.height)
        o, d = camera_space(
            world, pinhole_rays(cam, rx * cam.width, (1.0 - ry) * cam.height)[1], render
        )
        np.testing.assert_allclose(origin, o, atol=1e-9)
        np.testing.assert_allclose(direction, d, atol=1e-12)
        # the origin is on the camera's near plane
        np.testing.assert_allclose((world - cam.eye) @ cam.forward, cam.clip_start)


def pinhole_tables(cam, width, height):
    px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    origin, direction = pinhole_rays(cam, px, py)
    return origin, direction / np.linalg.norm(direction, axis=-1)[..., None]


def test_pinhole_classes_find_each_cameras_own_rays_and_nothing_else():
    cameras, _ = three_camera_rig(48, 27)
    w, h = 48, 27
    origin, direction = pinhole_tables(cameras[0], w, h)
    o2, d2 = pinhole_tables(cameras[1], w, h)
    origin[:, 20:], direction[:, 20:] = o2[:, 20:], d2[:, 20:]
    # segments further along the same straight ray count (the march found nothing
    # before them); a start before the camera's near plane does not
    origin[0, :10] += direction[0, :10] * 0.7
    origin[1, :10] -= direction[1, :10] * 0.01
    # a turn of a tenth of camera 1's pixel is too much, a hundredth is not
    xmin, xmax, _, _ = cameras[0].view_plane()
    pixel = (xmax - xmin) / w
    side = np.cross(direction[2:4, :10], [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side, axis=-1)[..., None]
    turned = direction[2:4, :10] + side * pixel * np.array([0.1, 0.01])[:, None, None]
    direction[2:4, :10] = turned / np.linalg.norm(turned, axis=-1)[..., None]
    direction[5, 5] = 0.0  # a pixel without a ray
    classes = pinhole_classes(tables_of(origin, direction), cameras)
    expected = np.ones((h, w), dtype=np.int32)
    expected[:, 20:] = 2
    expected[1, :10] = expected[2, :10] = expected[5, 5] = 0
    np.testing.assert_array_equal(classes, expected)
    assert PINHOLE_TOLERANCE_PX < 0.1


def test_pinhole_blocks_keep_only_blocks_of_one_camera():
    cameras, _ = three_camera_rig(48, 27)
    classes = np.zeros((27, 48), dtype=np.int32)
    classes[:, :20] = 1
    classes[10:, 30:] = 3
    blocks = pinhole_blocks(classes, cameras, cameras[0].matrix_world, max_blocks=100)
    assert blocks.size == 4 and blocks.classes.shape == (7, 12)
    expected = np.zeros((7, 12), dtype=np.int32)
    expected[:, :5] = 1  # columns 0..19
    expected[3:, 8:] = 3  # rows 12.., columns 32..; the last row of blocks is 24..27
    np.testing.assert_array_equal(blocks.classes, expected)
    assert blocks.pinhole.shape == (3, 18)


def test_shader_source_compiles_the_blocks_in():
    cameras, _ = three_camera_rig(48, 27)
    classes = np.ones((27, 48), dtype=np.int32)
    blocks = pinhole_blocks(classes, cameras, cameras[0].matrix_world, max_blocks=100)
    source = shader_source(blocks)
    assert "@" not in source
    assert f"int block_class[{7 * 12}] = {{{','.join(['1'] * 84)}}}" in source
    assert "float pinhole[54] = {" in source
    assert "int block_class[1] = {0}" in shader_source(None)


def test_shader_template_is_a_file_of_the_package():
    """The OSL source lives beside the module (packed with the extension) and every
    token of it is filled."""
    with open(OSL_PATH, encoding="utf-8") as template:
        tokens = set(re.findall(r"@[A-Z_]+@", template.read()))
    assert tokens == {
        "@UNUSABLE_LIMIT@",
        "@BLOCK@",
        "@BLOCKS_X@",
        "@BLOCKS_Y@",
        "@BLOCK_COUNT@",
        "@BLOCK_CLASS@",
        "@PINHOLE_COUNT@",
        "@PINHOLE@",
    }
    assert "shader multiscale_camera(" in shader_source(None)
