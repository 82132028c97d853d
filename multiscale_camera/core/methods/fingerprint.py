"""A digest of everything a ray field depends on, to know when a built field can be reused."""

import hashlib

import numpy as np

# The methods' revision: a change that alters the rays of an unchanged rig (IMAGE_BLEND's
# eased weights: 2; SCALAR_FIELD's step shortened at the near planes: 3; AUTO keeping
# IMAGE_BLEND where kept views must cross, not SCALAR_FIELD: 4) bumps it, so fields
# cached on disk before it are built again.
REVISION = 4


def field_key(rig, method, settings):
    """Hex digest of the rig (cameras, masks, beta), the method and its settings.

    Lights, materials and geometry are not part of it: changing them needs no new field.
    """
    h = hashlib.sha1()
    h.update(repr((REVISION, method, settings, rig.beta, rig.size)).encode())
    hash_cameras(h, rig.cameras)
    h.update(np.packbits(np.ascontiguousarray(rig.masks)).tobytes())
    return h.hexdigest()


def hash_cameras(h, cameras):
    """Feed the hasher ``h`` (hashlib) everything of ``cameras`` that shapes their rays:
    placement, lens, sensor, shift, clipping and pixel aspect, camera after camera."""
    for cam in cameras:
        h.update(np.ascontiguousarray(cam.matrix_world, dtype=np.float64).tobytes())
        h.update(
            repr(
                (
                    cam.lens,
                    cam.sensor_width,
                    cam.sensor_height,
                    cam.sensor_fit,
                    cam.shift_x,
                    cam.shift_y,
                    cam.clip_start,
                    cam.clip_end,
                    cam.pixel_aspect_x,
                    cam.pixel_aspect_y,
                )
            ).encode()
        )
