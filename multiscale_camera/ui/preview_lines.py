"""What the 3D viewport's ray preview draws, computed with numpy alone (no bpy): the
bent rays of a sparse pixel grid coloured by membership, the chained frusta of the
cameras and the folds among the drawn rays. ``preview`` draws them."""

import numpy as np

from ..core.quality import bending_active, quad_folds

# Camera colours, first to last (a ray's colour blends them by its membership).
PALETTE = np.array(
    [
        (0.25, 0.55, 1.0),
        (0.3, 0.85, 0.45),
        (1.0, 0.6, 0.15),
        (0.85, 0.35, 0.9),
        (0.95, 0.9, 0.3),
    ],
    dtype=np.float32,
)
FOLD_COLOUR = (1.0, 0.1, 0.1, 1.0)
FRUSTUM_ALPHA = 0.8
RAY_ALPHA = 0.9
# Drawn ray vertices per ray at most (every k-th vertex of long rays).
MAX_VERTICES = 96


def camera_colour(membership):
    """(..., 3) float32 colours for membership values (1-based camera numbers)."""
    m = np.clip(np.asarray(membership, dtype=np.float64) - 1.0, 0, len(PALETTE) - 1)
    lo = np.floor(m).astype(int)
    hi = np.minimum(lo + 1, len(PALETTE) - 1)
    t = (m - lo)[..., None]
    return ((1 - t) * PALETTE[lo] + t * PALETTE[hi]).astype(np.float32)


def frustum_lines(cameras):
    """Segments of the chained frusta.

    Returns
    -------
    pos : (S*2, 3) float32, world units, segment end points in pairs.
    colour : (S*2, 4) float32.
    """
    pos, col = [], []
    corners = []
    for i, cam in enumerate(cameras):
        w, h = cam.width, cam.height
        d = cam.directions(np.array([0.0, w, w, 0.0]), np.array([0.0, 0.0, h, h]))
        near = cam.near_points(d)
        corners.append(near)
        c = (*PALETTE[min(i, len(PALETTE) - 1)], FRUSTUM_ALPHA)
        for k in range(4):
            pos += [cam.eye, near[k], near[k], near[(k + 1) % 4]]
            col += [c] * 4
    for i in range(len(cameras) - 1):
        a, b = corners[i], corners[i + 1]
        ca = (*PALETTE[min(i, len(PALETTE) - 1)], 0.5 * FRUSTUM_ALPHA)
        cb = (*PALETTE[min(i + 1, len(PALETTE) - 1)], 0.5 * FRUSTUM_ALPHA)
        for k in range(4):
            pos += [a[k], b[k]]
            col += [ca, cb]
    return np.asarray(pos, dtype=np.float32).reshape(-1, 3), np.asarray(col, np.float32)


def preview_lines(fld, per_side=12):
    """Ray segments, their colours and fold marks for a sparse pixel grid of ``fld``.

    Parameters
    ----------
    fld : RayField. per_side : int, rays per image side.

    Returns
    -------
    dict with "rays" ((S*2, 3) float32 segment end points, world units), "ray_colours"
    ((S*2, 4) float32), "folds" ((F, 3) float32 points), "frusta" and
    "frustum_colours" (``frustum_lines``), "count" (rays drawn).
    """
    rig = fld.rig
    w, h = rig.size
    xs = np.unique(np.linspace(0, w - 1, per_side).round().astype(int))
    ys = np.unique(np.linspace(0, h - 1, max(2, round(per_side * h / w))).round().astype(int))
    iy, ix = np.meshgrid(ys, xs, indexing="ij")
    bundle = fld.rays(ix.ravel(), iy.ravel())
    verts, mem = bundle.vertices, bundle.membership
    r, k = verts.shape[:2]
    exit_index = fld.exit_index(ix.ravel(), iy.ravel())
    last = np.full(r, k - 1) if exit_index is None else np.clip(exit_index, 1, k - 1)
    step = max(1, int(np.ceil(k / MAX_VERTICES)))
    keep = np.arange(0, k, step)
    idx = np.arange(k - 1)
    seg = idx[None, :] < last[:, None]  # segments up to the exit vertex
    seg &= np.isin(idx, keep)[None, :] | (idx[None, :] == (last - 1)[:, None])
    rows, cols = np.nonzero(seg)
    nxt = np.minimum(cols + step, last[rows])
    a, b = verts[rows, cols], verts[rows, nxt]
    ca, cb = camera_colour(mem[rows, cols]), camera_colour(mem[rows, nxt])
    pos = np.stack([a, b], axis=1).reshape(-1, 3)
    col = np.concatenate(
        [np.stack([ca, cb], axis=1).reshape(-1, 3), np.full((len(pos), 1), RAY_ALPHA)], axis=1
    )
    grid_verts = verts.reshape(len(ys), len(xs), k, 3)
    counts = (last + 1).reshape(len(ys), len(xs))
    folds = np.zeros((0, 3), dtype=np.float32)
    if len(xs) > 1 and len(ys) > 1:
        folded = quad_folds(
            grid_verts, bending_active(grid_verts, rig.cameras[-1], counts, rig.cameras[:-1])
        )
        fy, fx = np.nonzero(folded)
        if len(fy):
            mid = (counts[fy, fx] // 2).clip(0, k - 1)
            folds = grid_verts[fy, fx, mid].astype(np.float32)
    frusta, frustum_colours = frustum_lines(rig.cameras)
    return {
        "rays": pos.astype(np.float32),
        "ray_colours": col.astype(np.float32),
        "folds": folds,
        "frusta": frusta,
        "frustum_colours": frustum_colours,
        "count": r,
    }
