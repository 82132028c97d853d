"""Validation of a scene's rig, with the checks that need its geometry: what the
``multiscale.validate`` operator and every build run first (``core.quality`` holds
the geometry-free checks)."""

import bpy  # noqa: F401 (outside Blender, the bpy module provides mathutils once imported)
import numpy as np
from mathutils.bvhtree import BVHTree

from ..adapters.meshes import scene_geometry
from ..adapters.scene import rig_from_scene
from ..core.geometry import RayBundle
from ..core.quality import obstruction_messages, preflight
from .fields import SERVICE
from .raycast import march


def geometry_cast(geometry, tree):
    """The ``cast`` callable of ``core.quality.obstruction_messages`` for a scene's
    geometry and its world-space BVH (None: nothing is ever hit)."""

    def cast(vertices):
        p, k = vertices.shape[:2]
        if tree is None or p == 0:
            return np.zeros(p, dtype=bool), []
        bundle = RayBundle(
            vertices=vertices.astype(np.float32),
            membership=np.zeros((p, k), dtype=np.float32),
            pixels=np.zeros((p, 2), dtype=np.int32),
            start_depth=np.zeros(p, dtype=np.float32),
            reach=np.zeros(p, dtype=np.float32),
        )
        hits = march(tree, bundle)
        owners = geometry.object_of[hits.triangle[hits.hit]]
        return hits.hit, [geometry.object_names[o] for o in np.unique(owners)]

    return cast


def scene_tree(depsgraph):
    """(SceneGeometry, BVHTree or None) of the evaluated scene."""
    geometry = scene_geometry(depsgraph)
    if not len(geometry):
        return geometry, None
    tree = BVHTree.FromPolygons(
        geometry.vertices.tolist(), geometry.triangles.tolist(), all_triangles=True
    )
    return geometry, tree


def validate_scene(depsgraph):
    """Every check of the scene's rig.

    Returns
    -------
    rig : Rig. messages : list of str, warnings and notes, each naming the camera and
        what to change (the rig's own notices first).

    Raises
    ------
    RigError for a rig that cannot render (the message says what to change).
    """
    scene = depsgraph.scene
    rig = rig_from_scene(scene, depsgraph, frames=SERVICE.mask_frames)
    messages = list(rig.notices) + preflight(rig)
    geometry, tree = scene_tree(depsgraph)
    messages += obstruction_messages(rig, geometry_cast(geometry, tree))
    return rig, messages
