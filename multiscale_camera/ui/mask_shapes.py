"""What the mask tools write and the Image Editor's mask overlay shows, computed with
numpy alone (no bpy): soft shapes, a silhouette's margin, and the picture of every
camera's mask with the transition bands and the guidelines' warnings.

Arrays are (height, width), row 0 at the top, pixel (x, y) centred at (x + 0.5, y + 0.5).
"""

import numpy as np

from .preview_lines import PALETTE

SHAPES = ("CIRCLE", "ELLIPSE", "ROUNDED_RECT")

# Overlay colours (RGBA, straight alpha): the transition band, and the warnings.
BAND_COLOUR = (0.55, 0.55, 0.6, 1.0)
OVERLAP_COLOUR = (1.0, 0.1, 0.1, 1.0)
TOUCH_COLOUR = (1.0, 0.85, 0.0, 1.0)
WARNING_ALPHA = 0.9


def smoothstep(t):
    """3t^2 - 2t^3 of ``t`` clipped to [0, 1]."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def shape_distance(kind, width, height, centre, size, radius=0.0):
    """Signed distance in pixels from each pixel centre to a shape's edge (negative
    inside).

    Parameters
    ----------
    kind : "CIRCLE" (diameter ``min(size)``), "ELLIPSE" (axes ``size``) or
        "ROUNDED_RECT" (``size``, corners of ``radius``).
    width, height : int, the image. centre : (x, y) pixels from the top-left corner.
    size : (w, h) pixels, the shape's full extent. radius : float pixels.

    For the ellipse the distance is taken along the line from its centre (the point's
    distance to where that line meets the edge); circle and rounded rectangle are exact.

    Returns
    -------
    (height, width) float64.
    """
    if kind not in SHAPES:
        raise ValueError(f"Unknown shape '{kind}': one of {', '.join(SHAPES)}")
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5
    px, py = xs - centre[0], ys - centre[1]
    a, b = max(size[0], 1e-6) / 2.0, max(size[1], 1e-6) / 2.0
    if kind == "CIRCLE":
        return np.hypot(px, py) - min(a, b)
    if kind == "ELLIPSE":
        r = np.hypot(px, py)
        q = np.hypot(px / a, py / b)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(q > 0, r * (1.0 - 1.0 / q), -min(a, b))
        return d
    rad = float(np.clip(radius, 0.0, min(a, b)))
    qx, qy = np.abs(px) - (a - rad), np.abs(py) - (b - rad)
    outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
    return outside + np.minimum(np.maximum(qx, qy), 0.0) - rad


def soft_shape(kind, width, height, centre, size, radius=0.0, feather=0.0):
    """A shape's coverage in [0, 1]: 1 inside, 0 outside, a smoothstep across
    ``feather`` pixels centred on the edge (so the edge itself is 0.5, where a mask
    starts to claim a pixel). ``feather`` 0 gives a hard edge. Other parameters as
    ``shape_distance``.

    Returns
    -------
    (height, width) float32.
    """
    d = shape_distance(kind, width, height, centre, size, radius)
    if feather <= 0:
        return (d <= 0).astype(np.float32)
    return smoothstep(0.5 - d / feather).astype(np.float32)


def drag_box(start, end):
    """(centre, size) of the box dragged from ``start`` to ``end``, both (u, v) in the
    image's own coordinates (0 to 1 from its bottom-left corner)."""
    (u0, v0), (u1, v1) = start, end
    return ((u0 + u1) / 2.0, (v0 + v1) / 2.0), (abs(u1 - u0), abs(v1 - v0))


def outline(kind, start, end, count=64):
    """A closed outline, (count + 1, 2) float, of the shape filling the box from
    ``start`` to ``end`` (region pixels), to draw while dragging: the circle of the
    box's smaller side, the ellipse, or the box itself for the rounded rectangle."""
    (x0, y0), (x1, y1) = start, end
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    a, b = abs(x1 - x0) / 2.0, abs(y1 - y0) / 2.0
    if kind == "ROUNDED_RECT":
        return np.array(
            [
                (cx - a, cy - b),
                (cx + a, cy - b),
                (cx + a, cy + b),
                (cx - a, cy + b),
                (cx - a, cy - b),
            ]
        )
    if kind == "CIRCLE":
        a = b = min(a, b)
    t = np.linspace(0.0, 2.0 * np.pi, count + 1)
    return np.stack([cx + a * np.cos(t), cy + b * np.sin(t)], axis=1)


def dilate(mask, margin):
    """``mask`` (bool (h, w)) grown by ``margin`` pixels: every pixel whose centre lies
    within ``margin`` of a pixel centre of the mask (a disk, not a square)."""
    r = int(np.floor(margin))
    if r <= 0 or not mask.any():
        return mask.copy()
    h, w = mask.shape
    padded = np.pad(mask, r)
    out = np.zeros_like(mask)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dx * dx + dy * dy <= margin * margin:
                out |= padded[r + dy : r + dy + h, r + dx : r + dx + w]
    return out


def mask_warnings(masks):
    """Where the masks break the guidelines.

    Parameters
    ----------
    masks : list of N bool (h, w), the cameras' masks first to last, one size.

    Returns
    -------
    overlap : bool (h, w), pixels two or more masks claim.
    touch : bool (h, w), pixels of consecutive cameras' masks with no gap between
        them (a pixel of mask i next to, 8-connected, a pixel of mask i+1).
    messages : list of str, one per kind of problem, naming the cameras (1-based).
    """
    h, w = masks[0].shape if masks else (0, 0)
    count = np.sum(masks, axis=0) if masks else np.zeros((h, w), int)
    overlap = count > 1
    touch = np.zeros((h, w), dtype=bool)
    messages = []
    pairs = []
    for i in range(len(masks) - 1):
        a, b = masks[i], masks[i + 1]
        near = (a & dilate(b, 1.5)) | (b & dilate(a, 1.5))
        near &= ~(a & b)
        if near.any() or (a & b).any():
            pairs.append(f"{i + 1}-{i + 2}")
        touch |= near
    if overlap.any():
        messages.append(f"Masks overlap on {int(overlap.sum())} pixels (shown red)")
    if pairs:
        messages.append(
            f"No gap between the masks of cameras {', '.join(pairs)}: leave a transition "
            "band between them (shown yellow)"
        )
    if masks and not masks[-1].any():
        messages.append(f"The last camera's mask (camera {len(masks)}) is empty")
    return overlap, touch, messages


def overlay_rgba(masks, shown, opacity=0.35):
    """The Image Editor's overlay over camera ``shown``'s mask.

    Parameters
    ----------
    masks : list of N bool (h, w), first camera to last. shown : int, index of the mask
        being painted (not drawn; the guide and the mask itself show it).
    opacity : float, alpha of the other masks and the bands.

    Returns
    -------
    rgba : (h, w, 4) float32 straight alpha, row 0 at the top: camera j's mask in
        ``PALETTE[j]``, the transition band (no mask claims it) grey, overlaps red and
        consecutive masks without a gap yellow (both at ``WARNING_ALPHA``), the last
        mask's absence as a red frame.
    messages : list of str (``mask_warnings``).
    """
    h, w = masks[0].shape
    rgba = np.zeros((h, w, 4), dtype=np.float32)
    claimed = np.zeros((h, w), dtype=bool)
    for j, m in enumerate(masks):
        claimed |= m
        if j == shown:
            continue
        rgba[m, :3] = PALETTE[j % len(PALETTE)]
        rgba[m, 3] = opacity
    band = ~claimed
    rgba[band] = (*BAND_COLOUR[:3], opacity)
    overlap, touch, messages = mask_warnings(masks)
    rgba[touch] = (*TOUCH_COLOUR[:3], WARNING_ALPHA)
    rgba[overlap] = (*OVERLAP_COLOUR[:3], WARNING_ALPHA)
    if not masks[-1].any():
        edge = max(1, min(h, w) // 60)
        frame = np.zeros((h, w), dtype=bool)
        frame[:edge], frame[-edge:], frame[:, :edge], frame[:, -edge:] = True, True, True, True
        rgba[frame] = (*OVERLAP_COLOUR[:3], WARNING_ALPHA)
    return rgba, messages
