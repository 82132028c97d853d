"""The hand-off's table helpers in plain numpy: camera space and edge padding."""

import numpy as np

from multiscale_camera.render.cycles import OSL_SOURCE, PAD, camera_space, pad_edges

from .rigs import look_at


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
    assert "float s = (raster[0] * width + pad) / (width + 2 * pad);" in OSL_SOURCE
    assert "float t = 1.0 - (raster[1] * height + pad) / (height + 2 * pad);" in OSL_SOURCE
    w, h = 40, 30
    x, y_top = np.arange(w), np.arange(h)
    s = ((x + 0.5) / w * w + PAD) / (w + 2 * PAD)
    raster_y = 1.0 - (y_top + 0.5) / h  # the raster position of top-first row y_top
    t = 1.0 - (raster_y * h + PAD) / (h + 2 * PAD)
    np.testing.assert_allclose(s * (w + 2 * PAD) - 0.5, x + PAD)
    np.testing.assert_allclose(t * (h + 2 * PAD) - 0.5, y_top + PAD)
