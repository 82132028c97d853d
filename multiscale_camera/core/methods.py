"""Ray-generation methods. Each method prepares a ``RayField`` from a rig once; the
field then hands out ray bundles for any set of pixels, so the renderer can work tile
by tile with bounded memory."""

import time
from dataclasses import dataclass, field

import numpy as np

from .bundle import RayBundle
from .errors import RigError
from .guides import DEFAULT_SEGMENTS, build_guides, curved_rays
from .harmonic import mask_weights


@dataclass
class RayField:
    """A prepared ray generator.

    Attributes
    ----------
    rig : Rig
    method : str, the method's enum name.
    weights : (N, H, W) float32, per-pixel camera weights (IMAGE_BLEND).
    seconds : dict of stage name -> float seconds spent preparing.
    solver : dict with "iterations", "residual", "converged".
    warnings : list of str, for the report and the user.
    """

    rig: object
    method: str
    weights: np.ndarray
    seconds: dict = field(default_factory=dict)
    solver: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    segments: int = DEFAULT_SEGMENTS

    def rays(self, ix, iy):
        """Rays for pixels ``(ix, iy)``.

        Parameters
        ----------
        ix, iy : (P,) int arrays, pixel column and row (row 0 at the top).

        Returns
        -------
        RayBundle of P rays.
        """
        return _image_blend_rays(self, np.asarray(ix), np.asarray(iy))

    def membership_image(self):
        """(H, W) float32: the weight-averaged camera number (1-based) of every pixel."""
        n = self.weights.shape[0]
        return np.tensordot(np.arange(1, n + 1, dtype=np.float32), self.weights, axes=1)


def _image_blend_rays(fld, ix, iy):
    cams = fld.rig.cameras
    g = build_guides(cams, ix + 0.5, iy + 0.5, beta=fld.rig.beta)
    curves = curved_rays(g, fld.segments)
    w = fld.weights[:, iy, ix].astype(np.float64)
    verts = np.einsum("np,npkc->pkc", w, curves)
    m = np.arange(1, len(cams) + 1, dtype=np.float64) @ w
    eye = cams[0].eye
    return RayBundle(
        vertices=verts.astype(np.float32),
        membership=np.repeat(m[:, None], verts.shape[1], axis=1).astype(np.float32),
        pixels=np.stack([ix, iy], axis=1).astype(np.int32),
        start_depth=np.linalg.norm(g.points[0] - eye, axis=-1).astype(np.float32),
        reach=np.full(len(ix), max(c.clip_end for c in cams), dtype=np.float32),
    )


def prepare_image_blend(rig):
    """IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights.

    Exact where it matters: a pixel inside camera i's mask gets R_i itself, so beyond
    camera i's near plane it is camera i's own pinhole ray.

    Parameters
    ----------
    rig : Rig

    Returns
    -------
    RayField
    """
    t0 = time.perf_counter()
    solve = mask_weights(rig.masks)
    fld = RayField(rig=rig, method="IMAGE_BLEND", weights=solve.x)
    fld.seconds["solve"] = time.perf_counter() - t0
    fld.solver.update(
        iterations=solve.iterations,
        residual=solve.residuals[-1] if solve.residuals else 0.0,
        converged=solve.converged,
    )
    w, h = rig.size
    cx, cy = np.meshgrid(np.linspace(0.5, w - 0.5, 9), np.linspace(0.5, h - 0.5, 9))
    shortened = build_guides(rig.cameras, cx.ravel(), cy.ravel(), rig.beta).shortened
    for j, count in enumerate(shortened):
        if count:
            a, b = rig.cameras[j], rig.cameras[j + 1]
            fld.warnings.append(
                f"Guides from '{a.name}' into '{b.name}' were shortened to keep them in front of "
                f"'{b.name}' (beta x distance between near planes exceeds its near distance "
                f"{b.clip_start:g}); move its near plane (Clip Start) farther from its eye"
            )
    return fld


METHODS = {"IMAGE_BLEND": prepare_image_blend}
# AUTO picks the cheapest method that meets the accuracy target; with one method, that one.
AUTO_CHOICE = "IMAGE_BLEND"


def prepare(rig, method):
    """Prepare the ray field of ``method`` (an enum name of DESIGN.md) for ``rig``."""
    try:
        builder = METHODS[AUTO_CHOICE if method == "AUTO" else method]
    except KeyError:
        raise RigError(
            f"Method '{method}' is not available in this version; use one of: " + ", ".join(METHODS)
        ) from None
    return builder(rig)
