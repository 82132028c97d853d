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


def _first_hits(cam, tree, size, window=None):
    """Directions ((n, 3), rows from the top) of ``cam``'s straight rays through the
    centres of a ``size`` = (w, h) picture of its frame, or of its pixels in ``window``
    = (x0, y0, x1, y1) (ends excluded), and their first hits (``march``)."""
    w, h = size
    x0, y0, x1, y1 = window if window is not None else (0, 0, w, h)
    iy, ix = np.mgrid[y0:y1, x0:x1]
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


def pixel_window(cam, points, size, pad=1):
    """The pixels of a ``size`` = (w, h) picture of ``cam``'s frame that can see any
    of the triangles whose corners are ``points`` ((n, 3) world): (x0, y0, x1, y1), ends
    excluded, the box of their projections grown by ``pad`` pixels; the whole frame
    when a point lies behind the eye; None when the box misses the frame or there are
    no points."""
    w, h = size
    if len(points) == 0:
        return None
    pix, depth = cam.project(points)
    if (depth <= 0).any():
        return (0, 0, w, h)
    sx, sy = w / cam.width, h / cam.height  # camera pixels -> picture pixels
    lo = np.floor(pix.min(axis=0) * (sx, sy)).astype(int) - pad
    hi = np.ceil(pix.max(axis=0) * (sx, sy)).astype(int) + pad
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x0 >= x1 or y0 >= y1:
        return None
    return (int(x0), int(y0), int(x1), int(y1))


def silhouette(cam, geometry, tree, names, size):
    """Where camera ``cam`` sees one of the objects ``names`` first.

    Only the pixels in the box of the objects' projected corners (``pixel_window``) are
    cast: a small object costs a few of the picture's rays.

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
    out = np.zeros((h, w), dtype=bool)
    if tree is None:
        return out
    wanted = np.isin(np.asarray(geometry.object_names), list(names))
    tris = wanted[geometry.object_of]
    points = geometry.vertices[np.unique(geometry.triangles[tris])]
    window = pixel_window(cam, points, size)
    if window is None:
        return out
    x0, y0, x1, y1 = window
    _d, hits = _first_hits(cam, tree, size, window)
    seen = np.zeros(len(hits.hit), dtype=bool)
    seen[hits.hit] = wanted[geometry.object_of[hits.triangle[hits.hit]]]
    out[y0:y1, x0:x1] = seen.reshape(y1 - y0, x1 - x0)
    return out
