"""The Cycles hand-off's ray tables: the first-hit rays (``tables.ray_tables``) in the
render camera's space, in two-plane form, padded and written as float EXRs, and the
blocks of pixels that show a rig camera's own pinhole rays, which the custom camera
computes instead of reading them (render/cycles.py tells the whole hand-off;
docs/ray_tables.md the tables).
"""

import os
from dataclasses import dataclass

import numpy as np

from ..core.geometry import dot3
from ..io.exr import write_channels
from .tables import blocked_before

# Tables are extended this many pixels past every image edge (linear extrapolation),
# so raster positions Cycles' pixel filter puts outside the image still interpolate.
PAD = 2
# A texel of the two-plane table whose ray it cannot hold carries UNUSABLE in all four
# channels; the shader takes any interpolated channel beyond UNUSABLE_LIMIT as that mark
# (a bilinear weight is 0 or, in float32 texel coordinates, far above 1e-20).
UNUSABLE = 1e35
UNUSABLE_LIMIT = 1e15
# The two-plane table holds rays whose unit direction has at least this forward (z)
# component in the render camera's space (slopes up to 100).
MIN_FORWARD = 1e-2
# A ray moved back to the plane by less than this fraction of the scene's size (float32
# rounding of origins already on it) is not cast for what lies in between.
MOVED = 1e-6
# A pixel's ray counts as rig camera i's pinhole ray when they differ by at most this
# many of camera i's pixels (in direction, and in origin as seen from its eye): far
# below the ray simplification's 0.25 px, above the tables' own spread about camera 1's
# straight rays (up to 0.025 px in direction on the bench rig: float32 segments).
PINHOLE_TOLERANCE_PX = 0.05
# At most this many blocks in the shader's table of per-block ray sources (an int array
# compiled into the shader): 8160 blocks are 4x4 pixels at 480x270, 16x16 at 1920x1080.
MAX_BLOCKS = 8192


def camera_space(points, vectors, matrix_world):
    """World -> OSL camera space (+Z forward, +Y up, +X right).

    Cycles uses the camera object's matrix without its scale, with Z flipped (Blender
    cameras look down -Z).

    Parameters
    ----------
    points, vectors : (..., 3) float64 world positions and directions.
    matrix_world : (4, 4) float64, the camera object's world matrix.

    Returns
    -------
    (..., 3) float64 positions, (..., 3) float64 directions in camera space.
    """
    m = np.asarray(matrix_world, dtype=np.float64)
    rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    flip = np.array([1.0, 1.0, -1.0])
    p = (np.asarray(points) - m[:3, 3]) @ rot * flip
    v = np.asarray(vectors) @ rot * flip
    return p, v


def pad_edges(a, pad):
    """Extend (H, W, C) by ``pad`` pixels on every side by linear extrapolation from the
    two outermost rows and columns (one row or column: repeated).

    Returns
    -------
    (H + 2 pad, W + 2 pad, C) array of ``a``'s dtype.
    """
    out = a
    for axis in (0, 1):
        n = out.shape[axis]
        first = np.take(out, [0], axis=axis)
        last = np.take(out, [n - 1], axis=axis)
        if n > 1:
            step0 = first - np.take(out, [1], axis=axis)
            step1 = last - np.take(out, [n - 2], axis=axis)
        else:
            step0 = step1 = np.zeros_like(first)
        before = [first + step0 * (pad - i) for i in range(pad)]
        after = [last + step1 * (i + 1) for i in range(pad)]
        out = np.concatenate(before + [out] + after, axis=axis)
    return out


def plane_rays(origin, direction, min_forward=MIN_FORWARD):
    """Rays in two-plane form: where each crosses the plane z = depth, and its slopes.

    A ray is then four numbers that interpolate bilinearly between pixels, and exactly
    so across a pinhole camera's pixels (both are affine in the pixel position there).

    Parameters
    ----------
    origin, direction : (..., 3) float64, camera space (+Z forward), world units;
        direction unit (zero for a pixel without a ray).
    min_forward : float, the least z component of a direction the table holds.

    Returns
    -------
    depth : float, world units: the plane's z, the nearest origin of the rays it holds.
    table : (..., 4) float64: x and y (world units) where the ray crosses z = depth, and
        its slopes dx/dz, dy/dz; ``UNUSABLE`` in all four for a ray heading less than
        ``min_forward`` forward.
    back : (...) float64 >= 0, world units: how far before its origin each ray crosses
        the plane, along the ray (0 where the table does not hold it).
    """
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    dz = direction[..., 2]
    held = dz >= min_forward
    depth = float(origin[..., 2][held].min()) if held.any() else 0.0
    dz = np.where(held, dz, 1.0)
    back = np.where(held, (origin[..., 2] - depth) / dz, 0.0)
    table = np.empty((*origin.shape[:-1], 4))
    table[..., :2] = origin[..., :2] - back[..., None] * direction[..., :2]
    table[..., 2:] = direction[..., :2] / dz[..., None]
    table[~held] = UNUSABLE
    return depth, table, back


@dataclass(frozen=True)
class PinholeBlocks:
    """Which blocks of pixels show a rig camera's own pinhole rays, and those rays.

    size : int, pixels per block side; blocks run from the top-left corner.
    classes : (rows, cols) int32: 0 where the tables give the rays, c > 0 where every
        pixel of the block shows rig camera c's pinhole ray (camera numbers from 1).
    pinhole : (N, 18) float64, per rig camera, in the render camera's space (+Z forward,
        world units) as affine functions of Cycles' raster position (rx, ry) in [0, 1],
        (0, 0) the bottom left: origin (on the camera's near plane) at (0, 0), its
        derivatives along rx and ry, then the same for the direction (not unit: its
        component along that camera's view axis is 1).
    """

    size: int
    classes: np.ndarray
    pinhole: np.ndarray


def pinhole_rays(camera, px, py):
    """A rig camera's own rays through image points, in world space.

    Parameters
    ----------
    camera : core.geometry.PinholeCamera. px, py : arrays of one shape S, that camera's
        pixel coordinates (top-left origin, centres at + 0.5).

    Returns
    -------
    origin : (*S, 3) float64, world units, on the camera's near plane.
    direction : (*S, 3) float64, its component along the camera's view axis is 1.
    """
    unit = camera.directions(px, py)
    origin = camera.near_points(unit)
    return origin, unit / (unit @ camera.forward)[..., None]


def pinhole_affine(camera, matrix_world):
    """(18,) float64: ``camera``'s rays in the render camera's space as affine functions
    of the raster position (``PinholeBlocks.pinhole``'s layout)."""
    w, h = camera.width, camera.height
    # raster (0, 0), (1, 0), (0, 1) in pixels, top-left origin
    px = np.array([0.0, w, 0.0])
    py = np.array([h, h, 0.0])
    origin, direction = pinhole_rays(camera, px, py)
    o, d = camera_space(origin, direction, matrix_world)
    return np.concatenate([o[0], o[1] - o[0], o[2] - o[0], d[0], d[1] - d[0], d[2] - d[0]])


def pinhole_classes(tables, cameras, tolerance_px=PINHOLE_TOLERANCE_PX):
    """Per pixel, the rig camera whose own pinhole ray the pixel's first-hit ray is.

    A pixel's ray (``tables``' origin and direction) is camera i's pinhole ray through
    that pixel's centre when their directions differ by at most ``tolerance_px`` of
    camera i's pixels, the table's origin lies that close to the pinhole ray's line (as
    seen from camera i's eye), and not before its start on camera i's near plane (the
    march found nothing between the two). A ray cut at its far plane (``clipped``) is
    no camera's: the shader's pinhole ray would run on past it.

    Parameters
    ----------
    tables : tables.RayTables of an H x W image. cameras : sequence of PinholeCamera,
        the rig's, at that image size.
    tolerance_px : float, pixels of each camera.

    Returns
    -------
    (H, W) int32: 0 for none, i + 1 for the rig's camera i.
    """
    height, width = tables.hit.shape
    px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    classes = np.zeros((height, width), dtype=np.int32)
    length = np.sqrt(dot3(tables.direction, tables.direction))
    if getattr(tables, "clipped", None) is not None:
        length = np.where(tables.clipped, 0.0, length)
    for i, camera in enumerate(cameras):
        origin, direction = pinhole_rays(camera, px, py)
        direction /= np.sqrt(dot3(direction, direction))[..., None]
        # the camera's pixel, as an angle at unit distance (its narrowest, off axis)
        xmin, xmax, ymin, ymax = camera.view_plane()
        pixel = min((xmax - xmin) / width, (ymax - ymin) / height)
        pixel /= 1.0 + max(xmin * xmin, xmax * xmax) + max(ymin * ymin, ymax * ymax)
        limit = tolerance_px * pixel
        rel = tables.origin - origin
        along = dot3(rel, direction)
        rel -= along[..., None] * direction
        off = np.sqrt(dot3(rel, rel))
        eye = tables.origin - camera.eye
        seen_from = np.sqrt(dot3(eye, eye))
        bend = tables.direction - direction
        turn = np.sqrt(dot3(bend, bend))
        same = (
            (length > 0)
            & (turn <= limit)
            & (off <= limit * seen_from)
            & (along >= -limit * camera.clip_start)
            & (classes == 0)
        )
        classes[same] = i + 1
    return classes


def pinhole_blocks(classes, cameras, matrix_world, max_blocks=MAX_BLOCKS):
    """Square blocks of pixels that all show one rig camera's pinhole rays.

    Parameters
    ----------
    classes : (H, W) int32, ``pinhole_classes``. cameras : the rig's PinholeCameras.
    matrix_world : (4, 4) float64, the render camera's world matrix.
    max_blocks : int, the most blocks the image may be cut into.

    Returns
    -------
    PinholeBlocks, with the smallest block size that gives at most ``max_blocks``.
    """
    height, width = classes.shape
    size = max(1, int(np.ceil(np.sqrt(width * height / max_blocks))))
    while -(-width // size) * -(-height // size) > max_blocks:
        size += 1
    rows, cols = -(-height // size), -(-width // size)
    padded = np.pad(classes, ((0, rows * size - height), (0, cols * size - width)), mode="edge")
    cells = padded.reshape(rows, size, cols, size)
    low, high = cells.min(axis=(1, 3)), cells.max(axis=(1, 3))
    blocks = np.where(low == high, low, 0).astype(np.int32)
    pinhole = np.stack([pinhole_affine(cam, matrix_world) for cam in cameras])
    return PinholeBlocks(size, blocks, pinhole)


def write_tables(folder, tables, matrix_world, frame, should_stop=None):
    """Write the hand-off's tables (camera space, padded) as uncompressed float EXRs.

    The two-plane table (RGBA: ``plane_rays``) holds every ray that heads forward and
    whose line meets no surface between the plane and the ray's origin (cast on
    ``frame``'s tree); the others are marked there, and only then are the origin and
    direction tables (RGB) written too.

    Parameters
    ----------
    folder : str, where the EXRs go. tables : tables.RayTables of the image.
    matrix_world : (4, 4) float64, the render camera's world matrix.
    frame : pipeline.Frame (``tables.blocked_before``). should_stop : callable -> bool.

    Returns
    -------
    dict of the shader's parameters: "ray_table", "origin_table", "direction_table"
    (str paths, "" when not written), "plane" (float, world units); and "back" (float,
    world units), the longest stretch a ray was moved back to the plane.
    """
    origin, direction = camera_space(tables.origin, tables.direction, matrix_world)
    depth, table, back = plane_rays(origin, direction)
    moved = back > MOVED * frame.scale
    blocked = blocked_before(
        frame, tables.origin[moved], tables.direction[moved], back[moved], should_stop
    )
    held = np.ones(back.shape, dtype=bool)
    held[moved] = ~blocked
    held &= table[..., 0] != UNUSABLE
    table[~held] = UNUSABLE
    params = {"plane": depth, "origin_table": "", "direction_table": "", "back": 0.0}
    if held.any():
        params["back"] = float(back[held].max())
    padded = pad_edges(table, PAD)
    path = os.path.join(folder, "rays.exr")
    write_channels(path, {c: padded[..., i] for i, c in enumerate("RGBA")}, compress=False)
    params["ray_table"] = path
    if not held.all():
        for name, values in (("origin", origin), ("direction", direction)):
            padded = pad_edges(values, PAD)
            path = os.path.join(folder, f"{name}.exr")
            write_channels(path, {c: padded[..., i] for i, c in enumerate("RGB")}, compress=False)
            params[f"{name}_table"] = path
    return params
