"""The preserved error at the visible surface (docs/report.md): where each measured
pixel's rendered ray first hits the scene, projected into the pixel's camera. What the
picture shows there is what the pinhole camera shows only if the hit lands on the
pixel."""

import numpy as np

from ..core.quality import far_depth, measured_pixels
from .checks import scene_tree
from .raycast import march


def surface_errors(fld, tree, should_stop=None):
    """Per camera, the first hits of its measured pixels' rays.

    Parameters
    ----------
    fld : RayField. tree : mathutils BVHTree of the scene in world space, or None.

    Returns
    -------
    list of dict, one per camera: "surface_pixels" (int, measured pixels whose ray hits
    the scene between the camera's near plane and its clip end) and "surface_px"
    ({"p50", "p95", "max"}, camera pixels between the hit projected into the camera and
    the pixel centre; None each when no ray hits there).
    """
    out = []
    rig = fld.rig
    for i, cam in enumerate(rig.cameras):
        ix, iy = measured_pixels(rig.masks[i])
        err = np.zeros(0)
        if len(ix) and tree is not None:
            hits = march(tree, fld.rays(ix, iy), should_stop)
            pix, depth = cam.project(hits.location)
            seen = hits.hit & (depth >= cam.clip_start) & (depth <= far_depth(cam))
            err = np.hypot(pix[:, 0] - (ix + 0.5), pix[:, 1] - (iy + 0.5))[seen]
        stats = {
            k: (float(np.percentile(err, q)) if len(err) else None)
            for k, q in (("p50", 50), ("p95", 95), ("max", 100))
        }
        out.append({"surface_pixels": int(len(err)), "surface_px": stats})
    return out


def with_surface(report, errors):
    """A copy of the build ``report`` whose camera entries also hold the preserved error
    at the visible surface (``errors``, from ``surface_errors``)."""
    cameras = [dict(entry, **extra) for entry, extra in zip(report["cameras"], errors)]
    return dict(report, cameras=cameras)


def scene_surface_errors(fld, depsgraph, should_stop=None):
    """``surface_errors`` of ``fld`` against the evaluated scene of ``depsgraph``."""
    _geometry, tree = scene_tree(depsgraph)
    return surface_errors(fld, tree, should_stop)


def surface_messages(cameras, errors, target_px):
    """Warnings for the cameras whose preserved pixels show the scene's surface farther
    than ``target_px`` (their p95 in ``errors``, from ``surface_errors``) from where the
    camera itself shows it: what a render says once per built field.

    Returns
    -------
    list of str, one per such camera.
    """
    out = []
    for cam, got in zip(cameras, errors):
        p95 = got["surface_px"]["p95"]
        if p95 is not None and p95 > target_px:
            out.append(
                f"Camera '{cam.name}': its preserved pixels show the surface {p95:.3g} px "
                f"(p95; at worst {got['surface_px']['max']:.3g} px) from where '{cam.name}' "
                f"itself shows it, over the {target_px:g} px target of the quality; "
                "IMAGE_BLEND lays preserved rays out exactly"
            )
    return out
