"""Bezier guides between consecutive cameras (paper eq. 1) and the curved rays R_i.

Every ray starts on camera 1's near plane. For a pixel, the guide B_j runs from camera
j's near-plane point p_j (leaving along v_j) to camera j+1's p_{j+1} (arriving along
v_{j+1}). The curved ray R_i follows B_1 .. B_{i-1} and then runs straight along v_i.

Vertex layout shared by every R_i, so curves can be blended vertex by vertex:
vertex 0 is p_1; stage j (j = 1 .. N-1) adds ``segments`` vertices ending at the stage's
far boundary; a last vertex continues along the final direction. A curve that no longer
bends in a stage (i <= j) runs straight along v_i there, as far as the guide's chord.
"""

from dataclasses import dataclass

import numpy as np

# Keep the handle into camera j+1 within this fraction of its near distance d_{j+1}:
# a handle reaching behind the eye (beta * L >= d_{j+1}) makes the guides of
# neighbouring pixels cross there. The clamp min(beta * L, GUARD_FRACTION * d_{j+1}) is
# continuous across pixels, so it adds no seam where it starts to act.
GUARD_FRACTION = 0.5

# Vertices per guide stage: a cubic with handles at most beta*L deviates from its
# 8-segment polyline by well under 1% of L.
DEFAULT_SEGMENTS = 8


@dataclass(frozen=True)
class Guides:
    """Near-plane points and directions of every camera for a set of pixels.

    Attributes
    ----------
    points : (N, P, 3) float64, world units: p_{i,x,y}.
    directions : (N, P, 3) float64, unit: v_{i,x,y}.
    handles_out, handles_in : (N-1, P) float64, world units
        Length of the handle leaving p_j and of the one arriving at p_{j+1}.
    shortened : (N-1,) int
        Pixels whose paper handle beta * L would reach behind camera j+1's eye
        (beta * L >= d_{j+1}), per stage: their guides are shortened by the guard.
    """

    points: np.ndarray
    directions: np.ndarray
    handles_out: np.ndarray
    handles_in: np.ndarray
    shortened: np.ndarray


def build_guides(cameras, px, py, beta=0.2):
    """Near-plane points, directions and handle lengths for pixels ``(px, py)``.

    Parameters
    ----------
    cameras : sequence of N PinholeCamera sharing one image size.
    px, py : (P,) float arrays, continuous pixel coordinates (centres at +0.5).
    beta : float, handle length over chord length (eq. 1).

    Returns
    -------
    Guides
    """
    dirs = np.stack([c.directions(px, py) for c in cameras])
    pts = np.stack([c.near_points(d) for c, d in zip(cameras, dirs)])
    chord = np.linalg.norm(pts[1:] - pts[:-1], axis=-1)
    out = beta * chord
    near = np.array([c.clip_start for c in cameras[1:]])[:, None]
    into = np.minimum(out, GUARD_FRACTION * near)
    return Guides(pts, dirs, out, into, (out >= near).sum(axis=1))


def bezier(q0, q1, q2, q3, t):
    """Cubic Bezier points.

    Parameters
    ----------
    q0, q1, q2, q3 : (P, 3) float arrays, control points.
    t : (K,) float array in [0, 1].

    Returns
    -------
    (P, K, 3) float64 array.
    """
    t = np.asarray(t, dtype=np.float64)[None, :, None]
    s = 1.0 - t
    return (
        (s**3) * q0[:, None]
        + (3 * s * s * t) * q1[:, None]
        + (3 * s * t * t) * q2[:, None]
        + (t**3) * q3[:, None]
    )


def curved_rays(guides, segments=DEFAULT_SEGMENTS, which=None):
    """The curved rays R_1..R_N of every pixel, in the shared vertex layout.

    Parameters
    ----------
    guides : Guides for N cameras and P pixels.
    segments : int, vertices per stage.
    which : sequence of int or None: the curves to make (0-based cameras; None: all N),
        each the bits it has among all N.

    Returns
    -------
    (len(which), P, K, 3) float64 array, K = 1 + (N - 1) * segments + 1, world units.
    The last segment of R_i points along v_i (its length is the last stage's chord, or
    one world unit for a single camera) and is meant to be extended.

    The curves are made as coordinate planes (len(which), 3, K, P), so that every
    operation runs along the pixels, and laid out once at the end. Each value is the
    same float64 operations on the same operands as ``bezier`` and ``start + v_i (chord
    t)`` written per pixel (elementwise, whatever the layout; products and sums of two
    operands commute bit for bit).
    """
    planes = curve_planes(guides, segments, which)
    rays = np.empty((planes.shape[0], planes.shape[-1], planes.shape[2], 3))
    rays[...] = planes.transpose(0, 3, 2, 1)
    return rays


def blended_planes(guides, weights, segments=DEFAULT_SEGMENTS):
    """The blend of every pixel's curves R_1..R_N by its weights, sum_i w_i R_i, as
    coordinate planes.

    Parameters
    ----------
    guides : Guides for N cameras and P pixels.
    weights : (N, P) float64, each pixel's camera weights.
    segments : int, vertices per stage.

    Returns
    -------
    (3, K, P) float64 array, world units: the bits of
    ``np.einsum("np,npkc->pkc", weights, curved_rays(guides, segments))`` moved to
    planes (an accumulator from +0.0 that adds w_i R_i in camera order, signed zeros
    included), made on the curves' planes (``curve_planes``), so that no pixel's N
    curves are laid out as rows.
    """
    planes = curve_planes(guides, segments, None)
    blend = np.zeros(planes.shape[1:])
    term = np.empty_like(blend)
    for i in range(len(planes)):
        np.multiply(weights[i], planes[i], out=term)
        blend += term
    return blend


def curve_planes(guides, segments=DEFAULT_SEGMENTS, which=None):
    """``curved_rays``' curves as coordinate planes (len(which), 3, K, P), float64: the
    same bits, laid out along the pixels."""
    pts, dirs = guides.points, guides.directions
    n, p = pts.shape[:2]
    which = list(range(n)) if which is None else [int(i) for i in which]
    t = np.arange(1, segments + 1) / segments
    k = 1 + (n - 1) * segments + 1
    planes = np.empty((len(which), 3, k, p))
    planes[:, :, 0] = pts[0].T
    dir_planes = np.ascontiguousarray(dirs.transpose(0, 2, 1))[:, :, None]  # (N, 3, 1, P)
    for j in range(n - 1):
        chord = np.linalg.norm(pts[j + 1] - pts[j], axis=-1)
        sl = slice(1 + j * segments, 1 + (j + 1) * segments)
        # the curves still bending follow guide B_j (they stand at p_j here): one
        # evaluation serves them all
        guide = None
        if max(which) > j:
            guide = _bezier_planes(
                pts[j],
                pts[j] + dirs[j] * guides.handles_out[j][:, None],
                pts[j + 1] - dirs[j + 1] * guides.handles_in[j][:, None],
                pts[j + 1],
                t,
            )
        along = None
        for r, i in enumerate(which):
            if i > j:
                planes[r, :, sl] = guide
                continue
            if along is None:
                along = t[:, None] * chord[None, :]  # (segments, P): chord t
            here = planes[r, :, sl]
            np.multiply(dir_planes[i], along, out=here)
            here += planes[r, :, j * segments][:, None]
    tail = np.linalg.norm(pts[-1] - pts[-2], axis=-1) if n > 1 else np.ones(p)
    planes[:, :, -1] = planes[:, :, -2] + dir_planes[which][:, :, 0] * tail
    return planes


def _bezier_planes(q0, q1, q2, q3, t):
    """``bezier(q0, q1, q2, q3, t)`` as coordinate planes (3, K, P): the same products
    and sums, in the same order, of the same operands (each control point's (P, 3) rows
    copied to planes first: the products then read contiguous memory)."""
    t = np.asarray(t, dtype=np.float64)[None, :, None]
    s = 1.0 - t
    weights = [(s**3), (3 * s * s * t), (3 * s * t * t), (t**3)]  # (1, K, 1), as bezier's
    out = np.multiply(weights[0][0], np.ascontiguousarray(q0.T)[:, None])
    term = np.empty_like(out)
    for w, q in zip(weights[1:], (q1, q2, q3)):
        np.multiply(w[0], np.ascontiguousarray(q.T)[:, None], out=term)
        out += term
    return out
