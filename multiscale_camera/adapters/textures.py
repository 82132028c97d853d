"""Blender images -> numpy textures, read once per frame, sampled bilinearly in numpy."""

import math
from dataclasses import dataclass

import numpy as np

# What Blender shows for an image it cannot load (Cycles and EEVEE use the same pink).
MISSING_COLOUR = (1.0, 0.0, 1.0)


@dataclass(frozen=True)
class Texture:
    """An image's pixels as linear RGB.

    rgb : (H, W, 3) float32, row 0 at the BOTTOM (Blender's order, so v = 0 is row 0).
    repeat : bool, wrap (REPEAT) rather than clamp (EXTEND/CLIP) outside [0, 1].
    closest : bool, nearest-pixel lookup (interpolation 'Closest').
    """

    rgb: np.ndarray
    repeat: bool = True
    closest: bool = False

    def sample(self, uv):
        """(P, 3) float64 colours at texture coordinates ``uv`` (P, 2) (u right, v up)."""
        h, w = self.rgb.shape[:2]
        uv = np.asarray(uv, dtype=np.float64)
        x = uv[:, 0] * w - 0.5
        y = uv[:, 1] * h - 0.5
        if self.closest:
            xi, yi = (
                self._wrap(np.floor(x + 0.5).astype(np.int64), w),
                self._wrap(np.floor(y + 0.5).astype(np.int64), h),
            )
            return self.rgb[yi, xi].astype(np.float64)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        xa, xb = self._wrap(x0, w), self._wrap(x0 + 1, w)
        ya, yb = self._wrap(y0, h), self._wrap(y0 + 1, h)
        t = self.rgb
        return (
            t[ya, xa] * (1 - fx) * (1 - fy)
            + t[ya, xb] * fx * (1 - fy)
            + t[yb, xa] * (1 - fx) * fy
            + t[yb, xb] * fx * fy
        )

    def _wrap(self, i, n):
        return np.mod(i, n) if self.repeat else np.clip(i, 0, n - 1)

    def mean(self):
        """(3,) float64, the plain average colour."""
        return self.rgb.reshape(-1, 3).mean(axis=0).astype(np.float64)


def srgb_to_linear(c):
    """The sRGB transfer function, inverted (array in, array out)."""
    c = np.asarray(c, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_image(image):
    """(H, W, 3) float32 linear RGB of a Blender image (bottom row first), or None when it
    has no pixels (missing file, unsupported format)."""
    try:
        w, h = image.size
        has = image.has_data or (w > 0 and h > 0)
    except (ReferenceError, RuntimeError):
        return None
    if not has or w == 0 or h == 0:
        return None
    n = len(image.pixels)
    if n != w * h * image.channels or n == 0:
        return None
    px = np.empty(n, dtype=np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(h, w, image.channels)
    rgb = np.repeat(px[..., :1], 3, axis=2) if image.channels < 3 else px[..., :3]
    space = image.colorspace_settings.name
    if not image.is_float and space in ("sRGB", "sRGB EOTF"):
        rgb = srgb_to_linear(rgb)
    return np.ascontiguousarray(rgb, dtype=np.float32)


def texture_from_node(node, notices):
    """A ``Texture`` for an Image Texture / Environment Texture node, or None when the node
    has no image; an image that cannot be read gives a one-pixel pink texture and a
    notice in ``notices`` (list of str)."""
    image = getattr(node, "image", None)
    if image is None:
        return None
    rgb = read_image(image)
    if rgb is None:
        notices.append(
            f"Image '{image.name}' could not be read (file '{image.filepath}' missing or "
            "unreadable): it renders pink, as in Cycles"
        )
        rgb = np.array(MISSING_COLOUR, dtype=np.float32).reshape(1, 1, 3)
    extension = getattr(node, "extension", "REPEAT")
    return Texture(
        rgb=rgb,
        repeat=extension in ("REPEAT", "MIRROR"),
        closest=getattr(node, "interpolation", "Linear") == "Closest",
    )


def equirectangular_uv(directions):
    """(P, 2) float64 texture coordinates of world directions (P, 3) on an
    equirectangular environment, Blender's mapping (u = 0.5 looks down -X... +X at the
    centre, v up)."""
    d = np.asarray(directions, dtype=np.float64)
    u = -np.arctan2(d[:, 1], d[:, 0]) / (2 * math.pi) + 0.5
    v = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])) / math.pi + 0.5
    return np.stack([u, v], axis=1)


def environment_mean(texture):
    """(3,) float64: the environment's average radiance over the sphere (rows weighted by
    the cosine of their latitude), its ambient light for a diffuse surface."""
    h = texture.rgb.shape[0]
    lat = (np.arange(h) + 0.5) / h * math.pi - math.pi / 2
    w = np.cos(lat)
    rows = texture.rgb.mean(axis=1).astype(np.float64)
    return (rows * w[:, None]).sum(0) / w.sum()
