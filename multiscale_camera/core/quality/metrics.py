"""The report's measures of a ray bundle (docs/report.md).

- Preserved-ray error of camera i (i >= 2) at a pixel of its mask eroded by 2 pixels:
  where the ray the pixel renders beyond camera i's near plane meets that plane
  (``plane_crossing``), projected into camera i, minus the pixel centre, in camera i's
  pixels; and the angle between that ray and the pinhole direction v_i. For camera 1
  the ray's point and direction where it leaves the modelled volume (the end of its
  bending stretch) are used instead.
- Folds: a 2x2 quad of neighbouring rays folds when the signed area of its four points,
  projected on the plane normal to their mean direction, changes sign along the
  bending stretch (from camera 1's near plane to the last camera's near plane).
"""

from dataclasses import dataclass

import numpy as np

from ..geometry import dot3

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


def plane_crossing(vertices, cam):
    """The ray each polyline renders beyond a camera's near plane, met with that plane.

    The polyline's first segment that starts on or beyond the plane carries the ray on
    into camera i's preserved view; its line, extended back to the plane, gives the
    point, and the segment the direction. (The segment that straddles the plane is a
    chord across the guide's last bend and shows nothing beyond the plane.) A ray whose
    last vertex is the first beyond the plane uses the straddling segment instead.

    Parameters
    ----------
    vertices : (R, K, 3) float array. cam : PinholeCamera.

    Returns
    -------
    point : (R, 3) float64, world units (NaN where a ray never crosses).
    direction : (R, 3) float64, unit.
    """
    v = vertices.astype(np.float64)
    s = dot3(v - cam.eye, cam.forward) - cam.clip_start
    ahead = s >= 0
    k = np.argmax(ahead, axis=1)
    crosses = ahead.any(axis=1) & (k > 0)
    k = np.maximum(k, 1)
    r = np.arange(len(v))
    k1 = np.minimum(k + 1, v.shape[1] - 1)
    a = np.where((k1 > k)[:, None], v[r, k], v[r, k - 1])
    b = np.where((k1 > k)[:, None], v[r, k1], v[r, k])
    d = b - a
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-30)
    sa = dot3(a - cam.eye, cam.forward) - cam.clip_start
    with np.errstate(invalid="ignore", divide="ignore"):
        point = a - d * (sa / dot3(d, cam.forward))[:, None]
    point[~crosses] = np.nan
    return point, d


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


def preserved_error(cameras, i, bundle, exit_index=None):
    """Preserved-ray error of camera ``i`` (0-based) over the rays of ``bundle``.

    Parameters
    ----------
    cameras : sequence of PinholeCamera. i : int.
    bundle : RayBundle whose rays serve pixels of camera i's eroded mask.
    exit_index : (R,) int, for camera 1: the vertex where each ray leaves the modelled
        volume (default: the last vertex).

    Returns
    -------
    Preserved
    """
    cam = cameras[i]
    v = bundle.vertices
    px = bundle.pixels[:, 0] + 0.5
    py = bundle.pixels[:, 1] + 0.5
    if len(v) == 0:
        return Preserved(0, np.zeros(0), np.zeros(0))
    if i == 0:
        r = np.arange(len(v))
        k = (
            np.full(len(v), v.shape[1] - 1)
            if exit_index is None
            else np.clip(exit_index, 1, v.shape[1] - 1)
        )
        point = v[r, k].astype(np.float64)
        d = point - v[r, k - 1]
        d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-30)
    else:
        point, d = plane_crossing(v, cam)
    pix, _depth = cam.project(point)
    err = np.hypot(pix[:, 0] - px, pix[:, 1] - py)
    ref = cam.directions(px, py)
    cos = np.clip((d * ref).sum(-1), -1.0, 1.0)
    return Preserved(len(v), err, np.degrees(np.arccos(cos)))


def _chord_lengths(v):
    """(R, K) float64: arc length along each polyline of ``v`` (R, K, 3) at its vertices."""
    seg = np.sqrt(np.einsum("rkc,rkc->rk", np.diff(v, axis=1), np.diff(v, axis=1)))
    return np.concatenate([np.zeros((len(v), 1)), np.cumsum(seg, axis=1)], axis=1)


def _at_lengths(v, cum, targets):
    """Points of polylines ``v`` (R, K, 3) at arc lengths ``targets`` (R, M), clamped
    to each polyline's ends: (R, M, 3) float64, and (R, M) int, the vertex before each."""
    r, k = cum.shape
    span = max(float(cum[:, -1].max()), float(np.max(targets, initial=0.0))) + 1.0
    offset = span * np.arange(r)[:, None]
    flat = (cum + offset).ravel()
    want = np.clip(targets, 0.0, cum[:, -1:]) + offset
    hi = np.searchsorted(flat, want.ravel(), side="right").reshape(targets.shape)
    hi = np.clip(hi - np.arange(r)[:, None] * k, 1, k - 1)
    rows = np.arange(r)[:, None]
    c0, c1 = cum[rows, hi - 1], cum[rows, hi]
    w = ((want - offset - c0) / np.maximum(c1 - c0, 1e-300))[..., None]
    return v[rows, hi - 1] * (1 - w) + v[rows, hi] * w, hi - 1


def quad_folds(vertices, active):
    """Quads of neighbouring rays that fold along the bending stretch.

    The quad of pixels (y, x), (y, x+1), (y+1, x+1), (y+1, x) is compared at equal arc
    lengths from camera 1's near plane: at each vertex of ray (y, x), the points of the
    other three rays as far along their own polylines. (Vertex k of neighbouring rays
    need not lie at the same arc length: with nested grids the step follows the local
    cell, and a ray that heads for a smaller camera takes shorter steps.)

    Parameters
    ----------
    vertices : (Hy, Wx, K, 3) float array: rays on a pixel lattice.
    active : (Hy, Wx, K) bool: whether vertex k is inside the bending stretch.

    Returns
    -------
    (Hy - 1, Wx - 1) bool: True where the quad's orientation ever differs from its
    orientation on camera 1's near plane.
    """
    hy, wx, k = vertices.shape[:3]
    v = vertices.astype(np.float64)
    cum = _chord_lengths(v.reshape(-1, k, 3)).reshape(hy, wx, k)

    def at(sl_y, sl_x):
        """The rays of one corner of every quad, at the arc lengths of corner a."""
        rays = v[sl_y, sl_x].reshape(-1, k, 3)
        pts, idx = _at_lengths(rays, cum[sl_y, sl_x].reshape(-1, k), ref)
        on = np.take_along_axis(active[sl_y, sl_x].reshape(-1, k), idx, axis=1)
        return pts.reshape(hy - 1, wx - 1, k, 3), on.reshape(hy - 1, wx - 1, k)

    a = v[:-1, :-1]
    ref = cum[:-1, :-1].reshape(-1, k)
    (b, on_b), (c, on_c), (d, on_d) = (
        at(slice(None, -1), slice(1, None)),
        at(slice(1, None), slice(1, None)),
        at(slice(1, None), slice(None, -1)),
    )
    live = active[:-1, :-1] & on_b & on_c & on_d
    tangent = np.zeros_like(a)
    for p in (a, b, c, d):
        step = np.diff(p, axis=2, append=p[:, :, -1:] + (p[:, :, -1:] - p[:, :, -2:-1]))
        tangent += step / np.maximum(np.linalg.norm(step, axis=-1, keepdims=True), 1e-30)
    area = (np.cross(c - a, d - b) * tangent).sum(-1)
    sign0 = np.sign(area[:, :, :1])
    flipped = (np.sign(area) != sign0) & (area != 0) & live
    return flipped.any(axis=-1)


def bending_active(vertices, last_cam, counts=None):
    """(…, K) bool: vertices before the last camera's near plane (and, with ``counts``,
    among the traced ones): the stretch where folds are counted."""
    s = dot3(vertices.astype(np.float64) - last_cam.eye, last_cam.forward) - last_cam.clip_start
    before = np.logical_and.accumulate(s < 0, axis=-1)
    if counts is not None:
        before &= np.arange(vertices.shape[-2]) < counts[..., None]
    return before
