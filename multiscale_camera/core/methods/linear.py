"""LINEAR, one of the paper's two weaker ray-generation methods, kept to compare the field
method against (the other is ``vector_field``).

LINEAR (section 3, "Ray intersection"): a pixel in camera i's mask gets its curve R_i;
a transition pixel gets the linear interpolation, vertex by vertex, of the curves of the
nearest preserved pixels of the two nearest masks. Nothing keeps neighbouring rays
apart: where the nearest preserved pixel jumps (along the pixel steps of a mask's edge,
and between the sectors of its nearest-pixel map), neighbouring pixels follow curves
bent by different amounts, and they cross (fold).
"""

import time
from dataclasses import dataclass

import numpy as np

from ..diagnostics import diagnostics_of
from ..geometry import DEFAULT_SEGMENTS, build_guides, curved_rays
from ..quality import check_rig
from .base import RayField, guard_warnings, record_seconds

_FAR = np.iinfo(np.int32).max  # squared pixel distance standing for "no mask pixel yet"


def _shifted(a, dy, dx, fill):
    """``a`` read at (y + dy, x + dx); ``fill`` where that lies off the image."""
    h, w = a.shape[-2:]
    out = np.full_like(a, fill)
    if abs(dy) < h and abs(dx) < w:
        dst = (..., slice(max(-dy, 0), h - max(dy, 0)), slice(max(-dx, 0), w - max(dx, 0)))
        src = (..., slice(max(dy, 0), h - max(-dy, 0)), slice(max(dx, 0), w - max(-dx, 0)))
        out[dst] = a[src]
    return out


def nearest_mask_pixels(mask):
    """The nearest pixel of a mask to every pixel, by jump flooding (JFA+1).

    Each pass offers every pixel the nearest-pixel guesses of its 8 neighbours at a
    distance of k pixels, k halving from half the image size to 1, plus one more pass at
    k = 1 that mends most of jump flooding's rare misses.

    Parameters
    ----------
    mask : (H, W) bool.

    Returns
    -------
    near : (2, H, W) int32, (x, y) of the nearest mask pixel (-1 when the mask is empty).
    dist : (H, W) float64, distance to it between pixel centres, pixels (inf when empty).
    """
    h, w = mask.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.int32)
    near = np.where(mask, np.stack([xs, ys]), -1).astype(np.int32)
    best = np.where(mask, 0, _FAR).astype(np.int32)
    k = 1 << max(int(np.ceil(np.log2(max(h, w)))) - 1, 0)
    steps = []
    while k >= 1:
        steps.append(k)
        k //= 2
    for k in steps + [1]:
        for dy in (-k, 0, k):
            for dx in (-k, 0, k):
                if dy == 0 and dx == 0:
                    continue
                cand = _shifted(near, dy, dx, -1)
                d = (cand[0] - xs) ** 2 + (cand[1] - ys) ** 2
                better = (cand[0] >= 0) & (d < best)
                best = np.where(better, d, best)
                near = np.where(better, cand, near)
    dist = np.where(best < _FAR, np.sqrt(best.astype(np.float64)), np.inf)
    return near, dist


@dataclass
class LinearField(RayField):
    """Rays interpolated between two preserved curves per pixel.

    near : (2, 2, H, W) int32, for curve a and curve b the (x, y) pixel whose curve is
    taken. camera : (2, H, W) int8, the 0-based camera of curves a and b. lam : (H, W)
    float32, the weight of curve b (0 inside a mask, where a = b = the pixel's own R_i).
    """

    near: np.ndarray = None
    camera: np.ndarray = None
    lam: np.ndarray = None
    segments: int = DEFAULT_SEGMENTS

    def _curves(self, x, y, cam):
        """(P, K, 3) float64: curve R_cam of pixels (x, y)."""
        g = build_guides(self.rig.cameras, x + 0.5, y + 0.5, beta=self.rig.beta)
        return curved_rays(g, self.segments)[cam, np.arange(len(x))]

    def rays(self, ix, iy):
        ix, iy = np.asarray(ix), np.asarray(iy)
        (xa, ya), (xb, yb) = self.near[:, :, iy, ix]
        ca, cb = self.camera[:, iy, ix]
        lam = self.lam[iy, ix].astype(np.float64)
        verts = self._curves(xa, ya, ca)
        blend = np.flatnonzero(lam > 0)
        if len(blend):
            other = self._curves(xb[blend], yb[blend], cb[blend])
            verts[blend] += lam[blend, None, None] * (other - verts[blend])
        # the curves are other pixels': move each ray to start at its own pixel's point
        # on camera 1's near plane (no move inside a mask)
        cam = self.rig.cameras[0]
        start = cam.near_points(cam.directions(ix + 0.5, iy + 0.5))
        verts += (start - verts[:, 0])[:, None]
        m = (1.0 - lam) * (ca + 1) + lam * (cb + 1)
        return self._bundle(ix, iy, verts, np.repeat(m[:, None], verts.shape[1], axis=1))


def prepare_linear(rig, settings=None, diag=None):
    """LINEAR: a transition pixel p takes the curves R_a(q_a) and R_b(q_b) of q_a and q_b,
    its nearest preserved pixels in the two nearest masks (cameras a and b), blended
    vertex by vertex with weight lambda = d_a / (d_a + d_b) on R_b (d: distances to the
    masks, pixels), and moved to start at p's own point on camera 1's near plane: the
    paper's "ray direction interpolation". Where p lies on the segment q_a q_b (across a
    band or ring of transition) the blend starts there anyway, up to the rounding of q_a
    and q_b to pixels. Its membership is (1 - lambda) a + lambda b. Where only one mask is
    painted, transition pixels take the curve of its nearest pixel. No grid is built.
    ``diag`` (core.diagnostics.Diagnostics or None) steers the build.
    """
    diag = diagnostics_of(diag)
    start = time.perf_counter()
    fld = LinearField(rig=rig, method="LINEAR")
    fld.warnings += check_rig(rig)
    n = len(rig.cameras)
    near = np.empty((n, 2, *rig.masks.shape[1:]), dtype=np.int32)
    dist = np.empty(rig.masks.shape)
    for i, mask in enumerate(rig.masks):
        diag.check()
        near[i], dist[i] = nearest_mask_pixels(mask)
    order = np.argsort(dist, axis=0, kind="stable")[:2]
    if n == 1 or not np.isfinite(np.take_along_axis(dist, order[1:], axis=0)).any():
        order = np.concatenate([order[:1], order[:1]])  # one painted mask: b = a
    d_a, d_b = np.take_along_axis(dist, order, axis=0)
    with np.errstate(invalid="ignore"):
        lam = np.where((d_a > 0) & (order[1] != order[0]), d_a / (d_a + d_b), 0.0)
    fld.near = np.stack([np.take_along_axis(near, o[None, None], axis=0)[0] for o in order])
    fld.camera, fld.lam = order.astype(np.int8), lam.astype(np.float32)
    record_seconds(fld, {"fill": time.perf_counter() - start})
    fld.stats.update(conflicts=0, stalled=0)
    fld.warnings += guard_warnings(rig)
    return fld
