"""Small camera rigs for core tests (no Blender)."""

import numpy as np

from multiscale_camera.core.geometry import PinholeCamera, pixel_centres


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
        name=name,
        matrix_world=look_at(eye, target),
        lens=lens,
        sensor_width=36.0,
        sensor_height=24.0,
        sensor_fit=kw.pop("sensor_fit", "AUTO"),
        shift_x=kw.pop("shift_x", 0.0),
        shift_y=kw.pop("shift_y", 0.0),
        clip_start=clip_start,
        clip_end=kw.pop("clip_end", 100.0),
        width=width,
        height=height,
        **kw,
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


def orbit(target, distance, azimuth_deg, elevation_deg):
    """A point ``distance`` from ``target`` seen at an azimuth (about +Z, 0 = from -Y)
    and elevation, degrees."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    offset = np.array([np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), np.sin(el)])
    return np.asarray(target, dtype=float) + distance * offset


def zoom_rig(width=160, height=120, turn_deg=20.0, ratio=4.0):
    """The issue's two-camera rig: camera 2 ``ratio`` times closer to the subject and
    turned ``turn_deg`` about it; near planes far from the eyes (the paper's guideline 4:
    camera 1's at 0.4 of its distance, camera 2's half way to the subject)."""
    target = (0.0, 0.0, 0.5)
    far = 20.0
    c1 = camera(
        "C1", orbit(target, far, 0, 25), target, width, height, clip_start=0.4 * far, clip_end=200.0
    )
    c2 = camera(
        "C2",
        orbit(target, far / ratio, turn_deg, 25),
        target,
        width,
        height,
        clip_start=0.5 * far / ratio,
        clip_end=200.0,
    )
    return (c1, c2), disk_masks(width, height, 0.2 * width, 0.35 * width)


def three_camera_rig(width=192, height=108):
    """Three cameras, each about 2.5 times closer to the subject than the one before and
    turned 10 degrees further; near planes half way from each eye to the subject."""
    target = (0.0, 0.0, 0.5)
    c1 = camera(
        "C1", orbit(target, 24.0, 0, 25), target, width, height, clip_start=9.6, clip_end=200.0
    )
    c2 = camera(
        "C2", orbit(target, 10.0, 10, 25), target, width, height, clip_start=5.0, clip_end=200.0
    )
    c3 = camera(
        "C3", orbit(target, 4.0, 20, 25), target, width, height, clip_start=2.0, clip_end=200.0
    )
    px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    r = np.hypot(px - width / 2, py - height / 2) / width
    masks = np.stack([r > 0.42, (r > 0.2) & (r < 0.3), r < 0.12])
    return (c1, c2, c3), masks


def _chain(distances, clips, turns, width, height, target=(0.0, 0.0, 0.5), elevation=25):
    """Cameras looking at ``target`` from ``distances``, turned ``turns`` degrees about it,
    with near planes at ``clips``."""
    return tuple(
        camera(
            f"C{n + 1}",
            orbit(target, d, t, elevation),
            target,
            width,
            height,
            clip_start=c,
            clip_end=200.0,
        )
        for n, (d, c, t) in enumerate(zip(distances, clips, turns))
    )


def _rings(width, height):
    px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    r = np.hypot(px - width / 2, py - height / 2) / width
    return np.stack([r > 0.42, (r > 0.2) & (r < 0.3), r < 0.12])


def zoom25_rig(width=192, height=108):
    """Three cameras, each five times closer than the one before (25x from the first
    near plane to the last), turned 10 degrees further each."""
    d = 24.0
    cams = _chain(
        (d, d / 5, d / 25), (0.4 * d, 0.4 * d / 5, 0.4 * d / 25), (0, 10, 20), width, height
    )
    return cams, _rings(width, height)


def zoom1000_rig(width=192, height=108):
    """The galleon's scale: three cameras, each about 31.6 times closer than the one
    before, 1000x from the first near plane to the last."""
    d, k = 24.0, 1000.0**0.5
    cams = _chain(
        (d, d / k, d / k**2), (0.4 * d, 0.4 * d / k, 0.4 * d / k**2), (0, 10, 20), width, height
    )
    return cams, _rings(width, height)


def turn100_rig(width=192, height=108):
    """Two cameras, the second four times closer and turned 100 degrees about the subject
    (level with it, so their views turn by 100 degrees): past what the guides can bend
    (validation refuses it)."""
    cams = _chain((20.0, 5.0), (8.0, 2.5), (0, 100), width, height, elevation=0)
    return cams, disk_masks(width, height, 0.2 * width, 0.35 * width)


def contradictory_rig(width=192, height=108):
    """Two cameras at 4x whose masks overlap: the same pixels asked of both. As the scene
    adapter does, the smaller camera keeps the shared pixels, so the two preserved regions
    touch with no room for a transition."""
    from multiscale_camera.core.geometry import resolve_conflicts

    cams = _chain((20.0, 5.0), (8.0, 2.5), (0, 20), width, height)
    masks, _notices = resolve_conflicts(
        disk_masks(width, height, 0.3 * width, 0.25 * width), [c.name for c in cams]
    )
    return cams, masks
