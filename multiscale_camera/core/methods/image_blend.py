"""IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights."""

import time
from dataclasses import dataclass

import numpy as np

from ..field import mask_weights
from ..geometry import DEFAULT_SEGMENTS, build_guides, curved_rays
from ..quality import check_rig
from .base import RayField, guard_warnings, record_seconds


@dataclass
class CurveBlendField(RayField):
    """Rays that blend each pixel's own curves R_i by per-pixel camera weights.

    weights : (N, H, W) float32, summing to one per pixel.
    """

    weights: np.ndarray = None
    segments: int = DEFAULT_SEGMENTS

    def rays(self, ix, iy):
        ix, iy = np.asarray(ix), np.asarray(iy)
        cams = self.rig.cameras
        g = build_guides(cams, ix + 0.5, iy + 0.5, beta=self.rig.beta)
        curves = curved_rays(g, self.segments)
        w = self.weights[:, iy, ix].astype(np.float64)
        verts = np.einsum("np,npkc->pkc", w, curves)
        m = np.arange(1, len(cams) + 1, dtype=np.float64) @ w
        return self._bundle(ix, iy, verts, np.repeat(m[:, None], verts.shape[1], axis=1))


def prepare_image_blend(rig, settings=None, diag=None):
    """IMAGE_BLEND: each pixel's ray is its curves R_i blended by harmonic mask weights.

    Exact where it matters: a pixel inside camera i's mask gets R_i itself, so beyond
    camera i's near plane it is camera i's own pinhole ray. Neighbouring rays can cross
    in the transitions (folds), since nothing ties them together.
    """
    warnings = check_rig(rig)
    start = time.perf_counter()
    solve = mask_weights(rig.masks)
    fld = CurveBlendField(rig=rig, method="IMAGE_BLEND", weights=solve.x, warnings=warnings)
    record_seconds(fld, {"solve": time.perf_counter() - start})
    fld.solver.update(
        iterations=solve.iterations,
        residual=solve.residuals[-1] if solve.residuals else 0.0,
        converged=solve.converged,
    )
    fld.warnings += guard_warnings(rig)
    return fld
