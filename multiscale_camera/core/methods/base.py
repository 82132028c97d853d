"""What every ray-generation method shares: the settings a build is asked for and the
quality presets, and ``RayField``, the base of every method's prepared field, which
hands out ray bundles for any set of pixels so the renderer works tile by tile with
bounded memory.
"""

import abc
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..geometry import RayBundle
from ..quality import guard_messages


@dataclass(frozen=True)
class Settings:
    """What a build is asked for.

    accuracy_px : float, target preserved error in pixels.
    max_voxels : int, the grid's voxel budget.
    cubic : bool, monotone cubic blending weights (SCALAR_FIELD).
    nested : bool or None, SCALAR_FIELD on nested grids that refine toward the smaller
        cameras (``nested``); False: one uniform grid, as the paper; None (default):
        nested only where one uniform grid within the budget cannot have the cells the
        accuracy target asks for (scale ratios beyond about 10x).
    processes : int, worker processes that share the trace and the nested levels'
        fills (0: one per core; 1: in Blender's process). Not part of the field's
        identity: every count traces the same rays (to about float32 rounding).
    steady : bool, grids on a world-fixed lattice (``field.layout``) so that a rig in
        motion keeps its layout from frame to frame (an animated rig's fields).
    layout : field.ShotLayout or None, the grids chosen once for a whole shot
        (``scalar_field.plan_shot``): SCALAR_FIELD builds on them wherever they hold
        the frame's rig (its own steady layout elsewhere). Part of the field's identity.
    shot : shot.ShotChoice or None, AUTO's method for a whole shot of a rig in motion
        (``shot.choose_shot_method``); None: SCALAR_FIELD. Part of the field's identity.
    """

    accuracy_px: float = 0.5
    max_voxels: int = 160**3
    cubic: bool = False
    nested: bool = None
    processes: int = field(default=0, repr=False, compare=False)
    steady: bool = False
    layout: object = None
    shot: object = None


# Quality presets: accuracy target in pixels and voxel budget (about 0.1, 0.4 and
# 1.3 GB of build memory), the `quality` enum of `scene.multiscale`.
QUALITY = {
    "PREVIEW": Settings(2.0, 96**3),
    "STANDARD": Settings(0.5, 160**3),
    "HIGH": Settings(0.25, 256**3),
}


def settings_for(quality, accuracy_px=0.5):
    """The Settings of a quality preset; CUSTOM uses ``accuracy_px`` and a budget that
    grows as the target tightens (the STANDARD budget at 0.5 px)."""
    if quality in QUALITY:
        return QUALITY[quality]
    budget = int(np.clip(160**3 * (0.5 / accuracy_px) ** 1.5, 64**3, 320**3))
    return Settings(float(accuracy_px), budget)


# The build stages a field's ``seconds`` (and the report's) hold.
STAGES = ("fill", "solve", "tangents", "trace")


def record_seconds(fld, seconds):
    """Set ``fld.seconds`` to a build's seconds per stage (dict of str to float; the
    stages of ``STAGES`` a method has not run count 0)."""
    fld.seconds.update({k: float(seconds.get(k, 0.0)) for k in STAGES})


@dataclass
class RayField(abc.ABC):
    """A prepared ray generator (base of every method's field). Built once by its
    method; after that the field cache shares it among callers, so it is read only.

    Attributes
    ----------
    rig : Rig. method : str, the method's enum name.
    seconds : dict stage -> float seconds ("fill", "solve", "tangents", "trace").
    solver : dict with "iterations", "residual", "converged".
    warnings : list of str, for the report and the user.
    grids : list of [nx, ny, nz].
    stats : dict of counts ("conflicts", "stalled", ...).
    """

    rig: object
    method: str
    seconds: dict = field(default_factory=dict)
    solver: dict = field(
        default_factory=lambda: {"iterations": 0, "residual": 0.0, "converged": True}
    )
    warnings: list = field(default_factory=list)
    grids: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    # Whether the ray of a pixel kept by camera i (inside its mask) is camera i's curve
    # R_i itself, vertex for vertex (``geometry.curved_rays``): then from R_i's vertex
    # ``near_vertex(i)`` on it lies on camera i's pinhole ray, and the fold count skips
    # what cannot fold there (``quality.report.fold_map``). A field that sets it True
    # has ``near_vertex(i)`` -> int (0-based camera i), as ``CurveBlendField`` does.
    exact_kept: ClassVar[bool] = False

    @abc.abstractmethod
    def rays(self, ix, iy):
        """Rays for pixels ``(ix, iy)`` ((P,) int arrays, row 0 at the top): a RayBundle."""

    def vertex_planes(self, ix, iy):
        """``rays(ix, iy)``' vertices as float64 coordinate planes, (3, P, K): each
        coordinate's rays one after the other (the fold count's layout)."""
        return np.moveaxis(self.rays(ix, iy).vertices, -1, 0).astype(np.float64, order="C")

    def exit_index(self, ix, iy):
        """(P,) int: the vertex where each pixel's ray leaves the modelled volume (the
        end of its bending stretch); the last vertex unless a method knows better."""
        return None

    def ray_vertices(self):
        """The most vertices a ray of ``rays`` has (int), where a method knows it before
        it lays rays out (the report measures its rays in blocks of so many vertices);
        None: few enough to measure a camera's pixels at once."""
        return None

    def _bundle(self, ix, iy, verts, membership):
        cams = self.rig.cameras
        p1 = cams[0].near_points(cams[0].directions(ix + 0.5, iy + 0.5))
        return RayBundle(
            vertices=verts.astype(np.float32, copy=False),
            membership=membership.astype(np.float32, copy=False),
            pixels=np.stack([ix, iy], axis=1).astype(np.int32),
            start_depth=np.linalg.norm(p1 - cams[0].eye, axis=-1).astype(np.float32),
            reach=np.full(len(ix), max(c.clip_end for c in cams), dtype=np.float32),
        )


def guard_warnings(rig):
    """Warnings for camera pairs whose guides the guard shortened (see ``guides``)."""
    return guard_messages(rig)
