"""Blender camera objects -> ``PinholeCamera``."""

import numpy as np

from ..core.errors import RigError
from ..core.geometry import PinholeCamera

_TYPE_NAMES = {"ORTHO": "orthographic", "PANO": "panoramic", "CUSTOM": "a custom (OSL) camera"}


def render_size(scene):
    """(width, height) in pixels of the final render, percentage applied."""
    r = scene.render
    return (
        max(1, int(r.resolution_x * r.resolution_percentage / 100)),
        max(1, int(r.resolution_y * r.resolution_percentage / 100)),
    )


def pinhole_from_object(obj, scene):
    """A ``PinholeCamera`` for a Blender camera object at the scene's render size.

    Raises
    ------
    RigError if the camera is not perspective.
    """
    cam = obj.data
    if cam.type != "PERSP":
        kind = _TYPE_NAMES.get(cam.type, cam.type.lower())
        raise RigError(
            f"Camera '{obj.name}' is {kind}; multiscale rays need perspective cameras "
            "(Camera Properties > Lens > Type: Perspective)"
        )
    width, height = render_size(scene)
    r = scene.render
    return PinholeCamera(
        name=obj.name,
        matrix_world=np.array(obj.matrix_world, dtype=np.float64),
        lens=float(cam.lens),
        sensor_width=float(cam.sensor_width),
        sensor_height=float(cam.sensor_height),
        sensor_fit=cam.sensor_fit,
        shift_x=float(cam.shift_x),
        shift_y=float(cam.shift_y),
        clip_start=float(cam.clip_start),
        clip_end=float(cam.clip_end),
        width=width,
        height=height,
        pixel_aspect_x=float(r.pixel_aspect_x),
        pixel_aspect_y=float(r.pixel_aspect_y),
    )
