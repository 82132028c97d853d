import numpy as np
import pytest

from fixtures.rigs import camera
from multiscale_camera.core.geometry import pixel_centres


def reference_direction(cam, x, y):
    """Slow reference: Blender's view plane written out for one pixel, by the rule
    'the longer side (after pixel aspect) spans the sensor width under AUTO'."""
    w, h = cam.width, cam.height
    ax, ay = cam.pixel_aspect_x, cam.pixel_aspect_y
    fit = cam.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if ax * w >= ay * h else "VERTICAL"
    sensor = cam.sensor_height if cam.sensor_fit == "VERTICAL" else cam.sensor_width
    if fit == "HORIZONTAL":
        plane_w = sensor / cam.lens
        plane_h = plane_w * (h * ay) / (w * ax)
        along = plane_w
    else:
        plane_h = sensor / cam.lens
        plane_w = plane_h * (w * ax) / (h * ay)
        along = plane_h
    u = (x / w - 0.5) * plane_w + cam.shift_x * along
    v = (0.5 - y / h) * plane_h + cam.shift_y * along
    d = cam.rotation @ np.array([u, v, -1.0])
    return d / np.linalg.norm(d)


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"width": 48, "height": 64},
        {"sensor_fit": "VERTICAL"},
        {"sensor_fit": "HORIZONTAL", "width": 30, "height": 60},
        {"shift_x": 0.1, "shift_y": -0.2},
        {"pixel_aspect_x": 2.0, "pixel_aspect_y": 1.0},
    ],
)
def test_directions_match_reference(kw):
    cam = camera("C", (1, -5, 2), (0, 0, 0), **kw)
    for x, y in [(0.5, 0.5), (10.5, 3.5), (cam.width - 0.5, cam.height - 0.5)]:
        got = cam.directions(np.array(x), np.array(y))
        np.testing.assert_allclose(got, reference_direction(cam, x, y), atol=1e-12)


def test_project_inverts_directions_and_near_points_lie_on_near_plane():
    cam = camera("C", (1, -5, 2), (0, 0, 0), clip_start=0.7, shift_x=0.05)
    px, py = pixel_centres(cam.width, cam.height)
    p = cam.near_points(cam.directions(px, py))
    np.testing.assert_allclose((p - cam.eye) @ cam.forward, 0.7, atol=1e-12)
    pix, depth = cam.project(p + 3.0 * cam.directions(px, py))
    np.testing.assert_allclose(pix[..., 0], px, atol=1e-9)
    np.testing.assert_allclose(pix[..., 1], py, atol=1e-9)
    assert (depth > 0).all()


def test_centre_pixel_looks_along_view_axis():
    cam = camera("C", (3, -4, 5), (0, 1, 0), width=65, height=49)
    d = cam.directions(np.array(32.5), np.array(24.5))
    np.testing.assert_allclose(d, cam.forward, atol=1e-12)
