"""The report's measures of a ray bundle (docs/report.md).

- Preserved-ray error of camera i at a pixel of its mask eroded by 2 pixels: the worst,
  over the ray the pixel renders from camera i's near plane out to its clip end, of the
  distance in camera i's pixels between the ray's points projected into camera i and
  the pixel centre (``along_ray``); and the worst angle between the ray and camera i's
  pinhole direction along the same stretch.
- Folds (``folds``): quads of neighbouring rays whose orientation flips in sections
  across the bundle.
"""

from dataclasses import dataclass

import numpy as np

from ..diagnostics import check_stop
from ..geometry import near_plane_entries_on_planes

# Erosion of the masks, pixels, before measuring preserved rays (docs/report.md).
ERODE_PX = 2
# At most this many pixels per camera are measured; a larger mask is subsampled evenly.
MAX_MEASURED = 20000


def erode(mask, pixels=ERODE_PX):
    """Binary erosion by a (2 * pixels + 1) square; outside the image counts as outside.

    Parameters
    ----------
    mask : (H, W) bool.

    Returns
    -------
    (H, W) bool.
    """
    out = mask.copy()
    for _ in range(pixels):
        m = out.copy()
        out[1:] &= m[:-1]
        out[:-1] &= m[1:]
        out[0] = False
        out[-1] = False
        m = out.copy()
        out[:, 1:] &= m[:, :-1]
        out[:, :-1] &= m[:, 1:]
        out[:, 0] = False
        out[:, -1] = False
    return out


def measured_pixels(mask, limit=MAX_MEASURED):
    """(ix, iy) int arrays of the eroded mask's pixels, evenly subsampled to ``limit``."""
    iy, ix = np.nonzero(erode(mask))
    if len(ix) > limit:
        keep = np.linspace(0, len(ix) - 1, limit).astype(np.int64)
        ix, iy = ix[keep], iy[keep]
    return ix, iy


# Far end of the measured stretch of a camera whose clip end is unbounded (infinite),
# in near distances (docs/report.md).
UNBOUNDED_NEAR_DISTANCES = 1000.0
# A segment whose part inside the measured stretch is shorter than this fraction of the
# camera's near distance lends it no angle: a float32 vertex a hair past the near plane
# would otherwise lend it the direction of the chord across the guide's last bend.
ANGLE_MIN_FRACTION = 1e-3
# Ray vertices measured together by ``along_ray`` (a dozen float64 temporaries of them).
ALONG_BLOCK_VERTICES = 1 << 19


def far_depth(cam):
    """Depth along ``cam``'s view axis where its measured stretch ends: its clip end, or
    ``UNBOUNDED_NEAR_DISTANCES`` near distances for an unbounded one (world units)."""
    end = float(cam.clip_end)
    return end if np.isfinite(end) else UNBOUNDED_NEAR_DISTANCES * float(cam.clip_start)


def along_ray(vertices, cam, px, py, earlier=(), should_stop=None):
    """Worst deviation of rendered rays from ``cam``'s pinhole rays beyond its near plane.

    Each polyline, with its last segment run on to the far depth (``far_depth``) as the
    renderer runs it on, is taken from where it enters ``cam``'s view (crossing its near
    plane from behind, after crossing the near planes of the ``earlier`` cameras in
    order: ``geometry.near_plane_entries``) and clipped to the slab between ``cam``'s
    near plane and its far depth (depth along the view axis). Projected into ``cam``, a
    straight piece in front of the eye is a straight piece of the image, whose distance
    to a fixed point is largest at one of its ends: the worst over the ends of the
    clipped pieces is the worst over the whole stretch, exactly. What comes before the
    entry is the ray's way there (the guides), even where it lies beyond the near plane
    to one side of the camera's frustum, as it does on rigs turned 40 degrees or more.

    Parameters
    ----------
    vertices : (R, K, 3) float array, K >= 2, world units. cam : PinholeCamera.
    px, py : (R,) float, the pixel centres the rays serve, in ``cam``'s pixels.
    earlier : sequence of PinholeCamera, the rig's cameras before ``cam``, in order.
    should_stop : callable () -> bool or None, asked before each block of
        ``ALONG_BLOCK_VERTICES`` vertices (raises ``Cancelled``).

    Returns
    -------
    error_px : (R,) float64, the largest distance, in ``cam``'s pixels, between the
        projection of a point of the stretch and (px, py); inf where a ray never reaches
        the stretch.
    angle_deg : (R,) float64, the largest angle between a piece of the stretch (at
        least ``ANGLE_MIN_FRACTION`` near distances long, on a segment that starts on or
        beyond the near plane where there is one: the segment straddling the plane is a
        chord across the guide's last bend) and the pinhole direction through (px, py),
        degrees; inf where none is.
    """
    r, k = vertices.shape[:2]

    def block(sl):
        return np.moveaxis(vertices[sl], -1, 0).astype(np.float64, order="C")

    return _along_in_blocks(block, r, k, cam, px, py, earlier, should_stop)


def along_ray_on_planes(planes, cam, px, py, earlier=(), should_stop=None):
    """``along_ray`` of R polylines held as coordinate planes: ``planes`` (3, R, K)
    float64, K >= 2, world units (``RayField.vertex_planes``); the same figures."""
    r, k = planes.shape[1:]
    return _along_in_blocks(lambda sl: planes[:, sl], r, k, cam, px, py, earlier, should_stop)


def _along_in_blocks(block, r, k, cam, px, py, earlier, should_stop):
    """``along_ray`` of R rays of K vertices, ``ALONG_BLOCK_VERTICES`` at a time:
    ``block(slice)`` gives a slice of the rays as coordinate planes (3, n, K) float64."""
    px, py = np.asarray(px, dtype=np.float64), np.asarray(py, dtype=np.float64)
    error = np.empty(r)
    angle = np.empty(r)
    step = max(1, ALONG_BLOCK_VERTICES // (k + 1))
    for s in range(0, r, step):
        check_stop(should_stop)
        sl = slice(s, s + step)
        error[sl], angle[sl] = _along_block(block(sl), cam, px[sl], py[sl], tuple(earlier))
    return error, angle


def _camera_planes(comp, cam, out):
    """Write the points ``comp`` (3, R, K) float64, world units, into ``out`` (3, R, K)
    as ``cam``'s own coordinates (x right, y up, z backwards: depth is -z)."""
    eye, rot = np.asarray(cam.eye, dtype=np.float64), cam.rotation
    rel = [np.subtract(comp[i], eye[i]) for i in range(3)]
    term = np.empty(comp.shape[1:])
    for c in range(3):
        np.multiply(rel[0], rot[0, c], out=out[c])
        for i in (1, 2):
            np.multiply(rel[i], rot[i, c], out=term)
            out[c] += term


def _along_block(comp, cam, px, py, earlier):
    """``along_ray`` of the polylines ``comp`` (3, R, K) float64, in ``cam``'s own
    coordinates: each vertex turned into them once; a point along a segment, an affine
    mix of its ends, is the same mix of theirs (the world's figures to rounding)."""
    _, r, k = comp.shape
    near, far = float(cam.clip_start), far_depth(cam)
    ax, bx, ay, by = cam.image_affine
    world = np.empty((3, r, k + 1))
    world[:, :, :k] = comp
    loc = np.empty((3, r, k + 1))
    _camera_planes(comp, cam, loc[:, :, :k])
    # the last segment run on to the far depth, as the renderer runs it on
    s_last = -loc[2, :, k - 1]
    rate = s_last + loc[2, :, k - 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        run = np.where(rate > 0, np.maximum((far - s_last) / rate, 0.0), 0.0)
    for x in (world, loc):
        x[:, :, k] = x[:, :, k - 1] + (x[:, :, k - 1] - x[:, :, k - 2]) * run
    # from where the ray enters the camera's view on (inf: never)
    entry = near_plane_entries_on_planes(world, earlier + (cam,))[-1][:, None]
    del world
    # segments wholly before every ray's entry cannot count (their piece starts past
    # their end): they are left out, one kept before (an entry on a vertex)
    first = entry[np.isfinite(entry)]
    j0 = min(max(int(np.floor(first.min())) - 1, 0), k - 1) if len(first) else 0
    a = loc[:, :, j0:-1]
    seg = loc[:, :, j0 + 1 :] - a
    sa, ds = -a[2], -seg[2]  # depths along the view axis
    inside = (sa >= near) & (sa <= far)
    lo = np.where(inside, 0.0, 1.0)
    hi = np.where(inside, 1.0, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tn, tf = (near - sa) / ds, (far - sa) / ds
    up, down = ds > 0, ds < 0
    lo = np.where(up, np.maximum(tn, 0.0), np.where(down, np.maximum(tf, 0.0), lo))
    hi = np.where(up, np.minimum(tf, 1.0), np.where(down, np.minimum(tn, 1.0), hi))
    seg_index = np.arange(j0, k)[None, :]
    with np.errstate(invalid="ignore"):
        lo = np.maximum(lo, entry - seg_index)
    valid = lo <= hi
    worst = np.full(r, -np.inf)
    for t in (lo, hi):
        t = np.clip(t, 0.0, 1.0)
        z = a[2] + seg[2] * t
        with np.errstate(divide="ignore", invalid="ignore"):
            x = ((a[0] + seg[0] * t) / -z - bx) / ax - px[:, None]
            y = ((a[1] + seg[1] * t) / -z - by) / ay - py[:, None]
        err = np.sqrt(x * x + y * y)
        worst = np.maximum(worst, np.where(valid, err, -np.inf).max(axis=1))
    length = np.sqrt(seg[0] * seg[0] + seg[1] * seg[1] + seg[2] * seg[2])
    # the pinhole direction through (px, py), in the camera's coordinates
    lx, ly = px * ax + bx, py * ay + by
    inv = 1.0 / np.sqrt(lx * lx + ly * ly + 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = (
            seg[0] * (lx * inv)[:, None] + seg[1] * (ly * inv)[:, None] - seg[2] * inv[:, None]
        ) / length
    with np.errstate(invalid="ignore"):  # inf - inf on rays that never enter the view
        long = valid & (length * (hi - lo) >= ANGLE_MIN_FRACTION * near)
    # the segment that straddles the near plane is a chord across the guide's last bend:
    # its point counts above, its direction belongs to the bend (unless nothing else does)
    beyond = long & (sa >= near) & (seg_index >= entry)
    long = np.where(beyond.any(axis=1)[:, None], beyond, long)
    ang = np.degrees(np.arccos(np.clip(np.where(long, cos, 1.0), -1.0, 1.0)))
    ang = np.where(long.any(axis=1), np.where(long, ang, -np.inf).max(axis=1), np.inf)
    worst = np.where(np.isfinite(worst), worst, np.inf)
    return worst, ang


@dataclass(frozen=True)
class Preserved:
    """Preserved-ray errors of one camera.

    pixels : int, pixels measured. error_px : (P,) float64 pixel error.
    angle_deg : (P,) float64, angle to the pinhole direction, degrees.
    """

    pixels: int
    error_px: np.ndarray
    angle_deg: np.ndarray

    def summary(self):
        """{"p50", "p95", "max"} of the error and of the angle. A ray without a finite
        figure (one that never crosses the near plane) counts as infinitely wrong; a
        percentile that lands on such rays, or one of no rays, is None (strict JSON has
        no NaN or Infinity: ``unmeasured`` says why)."""

        def stats(a):
            a = np.where(np.isfinite(a), a, np.inf)
            out = {}
            for k, q in (("p50", 50), ("p95", 95), ("max", 100)):
                with np.errstate(invalid="ignore"):  # inf - inf between two infinite rays
                    v = float(np.percentile(a, q)) if len(a) else np.inf
                out[k] = v if np.isfinite(v) else None
            return out

        return stats(self.error_px), stats(self.angle_deg)

    def unmeasured(self):
        """Rays of the measure without a finite error: int."""
        return int(np.count_nonzero(~np.isfinite(self.error_px)))


def preserved_error(cameras, i, bundle, should_stop=None):
    """Preserved-ray error of camera ``i`` (0-based) over the rays of ``bundle``: the
    worst deviation along each ray from camera i's near plane out to its clip end
    (``along_ray``).

    Parameters
    ----------
    cameras : sequence of PinholeCamera. i : int.
    bundle : RayBundle whose rays serve pixels of camera i's eroded mask.
    should_stop : callable () -> bool or None, ``along_ray``'s cancel check.

    Returns
    -------
    Preserved
    """
    v = bundle.vertices
    if len(v) == 0:
        return Preserved(0, np.zeros(0), np.zeros(0))
    px, py = bundle.pixels[:, 0] + 0.5, bundle.pixels[:, 1] + 0.5
    err, angle = along_ray(v, cameras[i], px, py, tuple(cameras[:i]), should_stop)
    return Preserved(len(v), err, angle)


def preserved_error_on_planes(cameras, i, planes, ix, iy, should_stop=None):
    """``preserved_error`` of the rays of pixels ``ix``, ``iy`` ((P,) int, camera i's)
    held as coordinate planes ``planes`` (3, P, K) float64 (``RayField.vertex_planes``)."""
    if planes.shape[1] == 0:
        return Preserved(0, np.zeros(0), np.zeros(0))
    px, py = np.asarray(ix) + 0.5, np.asarray(iy) + 0.5
    err, angle = along_ray_on_planes(planes, cameras[i], px, py, tuple(cameras[:i]), should_stop)
    return Preserved(planes.shape[1], err, angle)


def bending_active(vertices, last_cam, counts=None, earlier=()):
    """(…, K) bool: vertices before the ray enters the last camera's view (crossing its
    near plane from behind after the ``earlier`` cameras' planes, in order:
    ``geometry.near_plane_entries``; every vertex of a ray that never does) and, with
    ``counts``, among the traced ones: the stretch where folds are counted."""
    shape = vertices.shape
    flat = np.asarray(vertices).reshape(-1, shape[-2], 3)
    planes = np.moveaxis(flat, -1, 0).astype(np.float64)
    flat_counts = None if counts is None else np.reshape(counts, -1)
    return bending_active_on_planes(planes, last_cam, flat_counts, earlier).reshape(shape[:-1])


def bending_active_on_planes(planes, last_cam, counts=None, earlier=()):
    """``bending_active`` of R rays held as coordinate planes ``planes`` (3, R, K)
    float64 (``counts``: (R,) int or None): (R, K) bool."""
    k = planes.shape[-1]
    cams = tuple(earlier) + (last_cam,)
    entry = near_plane_entries_on_planes(planes, cams)[-1]
    before = np.arange(k) < entry[:, None]
    if counts is not None:
        before &= np.arange(k) < np.asarray(counts)[:, None]
    return before
