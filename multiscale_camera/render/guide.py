"""A quick picture of one camera's own (straight, pinhole) view, the guide shown under a
mask while it is painted (our solid raycast, for when no GPU context can run Workbench),
and the silhouette of some objects as that camera sees them, for masks made from the
scene."""

import numpy as np

from ..core.geometry import RayBundle
from .raycast import march
from .shade import face_normals

# The guide is cast at most this many pixels wide (then shown stretched to the mask):
# enough to paint by, a second or two of BVH casts.
GUIDE_MAX_WIDTH = 480
# Light from the camera: ambient plus head-on Lambert, so shapes read without scene lights.
AMBIENT = 0.35


def guide_size(width, height, max_width=GUIDE_MAX_WIDTH):
    """(w, h) of the guide for a render of ``width`` x ``height``: the render size,
    scaled down to ``max_width`` keeping the aspect."""
    if width <= max_width:
        return width, height
    return max_width, max(1, round(height * max_width / width))


def solid_view(cam, geometry, tree, world, size):
    """Camera ``cam``'s straight view, shaded flat-and-head-on.

    Parameters
    ----------
    cam : PinholeCamera (at the render size). geometry : SceneGeometry.
    tree : BVHTree or None. world : (3,) float linear colour of misses.
    size : (w, h) of the picture, pixels (the render's frame, resampled).

    Returns
    -------
    (h, w, 4) float32 RGBA, row 0 at the top, linear.
    """
    w, h = size
    d, hits = _first_hits(cam, tree, size)
    n = len(d)
    rgb = np.broadcast_to(np.asarray(world, dtype=np.float32), (n, 3)).copy()
    if hits.hit.any():
        tri = hits.triangle[hits.hit]
        normal = face_normals(geometry, tri)
        lit = AMBIENT + (1 - AMBIENT) * np.abs((normal * d[hits.hit]).sum(-1))
        rgb[hits.hit] = geometry.colour[tri] * lit[:, None]
    rgba = np.concatenate([rgb, np.ones((n, 1), dtype=np.float32)], axis=1)
    return rgba.reshape(h, w, 4).astype(np.float32)


def _first_hits(cam, tree, size):
    """Directions ((w*h, 3), rows from the top) of ``cam``'s straight rays through the
    centres of a ``size`` = (w, h) picture of its frame, and their first hits (``march``)."""
    w, h = size
    iy, ix = np.mgrid[0:h, 0:w]
    px = (ix.ravel() + 0.5) * (cam.width / w)
    py = (iy.ravel() + 0.5) * (cam.height / h)
    d = cam.directions(px, py)
    start = cam.near_points(d)
    verts = np.stack([start, start + d], axis=1).astype(np.float32)
    n = len(d)
    bundle = RayBundle(
        vertices=verts,
        membership=np.zeros((n, 2), dtype=np.float32),
        pixels=np.stack([ix.ravel(), iy.ravel()], axis=1).astype(np.int32),
        start_depth=np.zeros(n, dtype=np.float32),
        reach=np.full(n, cam.clip_end, dtype=np.float32),
    )
    return d, march(tree, bundle)


def silhouette(cam, geometry, tree, names, size):
    """Where camera ``cam`` sees one of the objects ``names`` first.

    Parameters
    ----------
    cam : PinholeCamera. geometry : SceneGeometry. tree : BVHTree or None.
    names : iterable of str, object names. size : (w, h) of the mask, pixels.

    Returns
    -------
    (h, w) bool, row 0 at the top: the pixel's centre ray (from the near plane to
    clip end) hits one of ``names`` before anything else.
    """
    w, h = size
    if tree is None:
        return np.zeros((h, w), dtype=bool)
    _d, hits = _first_hits(cam, tree, size)
    wanted = np.isin(np.asarray(geometry.object_names), list(names))
    out = np.zeros(w * h, dtype=bool)
    out[hits.hit] = wanted[geometry.object_of[hits.triangle[hits.hit]]]
    return out.reshape(h, w)
