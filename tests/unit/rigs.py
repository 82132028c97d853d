"""Small camera rigs for core tests (no Blender)."""

import numpy as np

from multiscale_camera.core.camera import PinholeCamera, pixel_centres


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    """(4, 4) camera-to-world matrix of a camera at ``eye`` looking at ``target``."""
    f = np.subtract(target, eye, dtype=np.float64)
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u, -f, eye
    return m


def camera(name, eye, target, width=64, height=48, lens=50.0, clip_start=1.0, **kw):
    return PinholeCamera(
        name=name, matrix_world=look_at(eye, target), lens=lens, sensor_width=36.0,
        sensor_height=24.0, sensor_fit=kw.pop("sensor_fit", "AUTO"), shift_x=kw.pop("shift_x", 0.0),
        shift_y=kw.pop("shift_y", 0.0), clip_start=clip_start, clip_end=kw.pop("clip_end", 100.0),
        width=width, height=height, **kw,
    )


def disk_masks(width, height, inner, outer):
    """Camera 1 outside radius ``outer``, camera 2 inside ``inner``, about the centre."""
    px, py = pixel_centres(width, height)
    r = np.hypot(px - width / 2, py - height / 2)
    return np.stack([r > outer, r < inner])


def two_camera_rig(width=64, height=48):
    """Camera 2 four times closer to the subject, near planes in open air."""
    c1 = camera("C1", (0, -16, 8), (0, 0, 0), width, height, clip_start=4.0)
    c2 = camera("C2", (0.5, -4, 2), (0.2, 0, 0), width, height, clip_start=1.5)
    return (c1, c2), disk_masks(width, height, 0.2 * width, 0.35 * width)
