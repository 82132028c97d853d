"""Volumes in a render: gathered once per frame, composited per tile over the surfaces.

``prepare_volumes`` reads the scene's volume sources and the cameras' transfer
functions; ``composite_volumes`` marches a tile's bent rays through every volume up to
the first surface hit and lays the result over the shaded surface (or the world), so
meshes and volumes meet by depth.
"""

import os
from dataclasses import dataclass, field

import numpy as np

from ..adapters.volumes import scene_volumes, transfer_tables
from ..core.volume import VolumeScene, composite_over, march_volume
from .fields import SERVICE

# Worker threads per tile: numpy releases the GIL in its loops, so two threads keep two
# cores busy; more only add contention.
THREADS = max(1, min(2, os.cpu_count() or 1))


@dataclass
class FrameVolumes:
    """The volumes of a frame, each ready to march (``core.volume.VolumeScene``).

    scenes : list of VolumeScene. samples, skipped : int, the samples the frame's tiles
        took and skipped in empty blocks so far (counters for the log).
    """

    scenes: list[VolumeScene] = field(default_factory=list)
    samples: int = 0
    skipped: int = 0

    def __bool__(self):
        return bool(self.scenes)


def prepare_volumes(depsgraph, grids=None):
    """Every volume of the evaluated scene with the cameras' transfer functions.

    Parameters
    ----------
    depsgraph : bpy.types.Depsgraph, evaluated.
    grids : adapters.volumes.VolumeGridCache, where decoded sources are looked up and
        kept (default: the field service's, shared by every frame of this process).

    Returns
    -------
    FrameVolumes (empty when the scene has none), notices : list of str.

    Raises
    ------
    VolumeError (a RigError) naming the object or camera and what to change.
    """
    grids = SERVICE.volume_grids if grids is None else grids
    found, notices = scene_volumes(depsgraph, grids)
    if not found:
        return FrameVolumes(), notices
    settings = depsgraph.scene.multiscale
    tables, said = transfer_tables(settings)
    notices += said
    scenes = [
        VolumeScene.build(
            vol,
            tables,
            step=float(settings.volume_step),
            shading=bool(settings.volume_shading),
            ranges=ranges,
            normals=normals,
        )
        for vol, ranges, normals in found
    ]
    return FrameVolumes(scenes), notices


def composite_volumes(volumes, bundle, distance, colour, alpha, depth, should_stop=None):
    """Lay the volumes along a tile's rays over what the rays hit.

    Parameters
    ----------
    volumes : FrameVolumes. bundle : RayBundle of R rays.
    distance : (R,) float, arc length from vertex 0 to the first surface (inf for none).
    colour : (R, 3) float32, premultiplied by ``alpha``. alpha : (R,) float32.
    depth : (R,) float, the Depth pass (camera-1 eye to the surface, or the miss value).

    Returns
    -------
    colour (R, 3) float32 premultiplied, alpha (R,) float32, depth (R,) float32: where
    a volume reaches half opacity before the surface, the depth of that point.
    """
    layers = []
    for scene in volumes.scenes:
        res = march_volume(
            scene,
            bundle.vertices,
            bundle.membership,
            bundle.reach,
            stop=distance,
            should_stop=should_stop,
            threads=THREADS,
        )
        volumes.samples += res.samples
        volumes.skipped += res.skipped
        layers.append(res)
    out_colour, out_alpha, vol_depth = composite_over(layers, colour, alpha)
    out_depth = np.where(
        np.isfinite(vol_depth), np.minimum(depth, bundle.start_depth + vol_depth), depth
    )
    return out_colour, out_alpha, out_depth.astype(np.float32)
