"""The render's worker processes: background Blenders, which have mathutils for the BVH
casts, kept by the worker runtime (``core.runtime``) across renders.

A worker is ``blender -b --factory-startup`` running the runtime's bootstrap
(``bpy.app.binary_path``); where that path is empty (the bpy module outside Blender), a
Python that imports bpy, whose mathutils is the same. Either starts without copying
Blender's process, so workers are as safe to start from Blender's window as from
``blender -b``.

A frame goes to the workers as data (``portable``): its BVH tree, which cannot be
pickled, as the triangles it is built from (``TreeSource``). A worker builds the tree
once and keeps it while the triangles' digest is unchanged (``frame_here``); the tree
is the one ``pipeline.scene_tree`` builds, so the casts are the same.
"""

import hashlib
import os
import sys
from dataclasses import dataclass, replace

import bpy
import numpy as np
from mathutils.bvhtree import BVHTree

from ..core.diagnostics import Diagnostics
from ..core.runtime import Launcher

# Where a worker keeps its tree in ``Context.memo``.
TREE_MEMO = "multiscale tree"


def blender_launcher():
    """The runtime's Launcher of render workers (see the module's docstring)."""
    binary = bpy.app.binary_path
    if binary and os.path.isfile(binary):
        prefix = (binary, "-b", "--factory-startup", "-noaudio", "--python-expr")
        return Launcher("blender", prefix)
    return Launcher("blender", (sys.executable, "-I", "-c"), preamble="import bpy")


@dataclass(frozen=True)
class TreeSource:
    """What a BVH tree is built from: digest (str, of the two arrays), vertices (V, 3)
    float32 and triangles (T, 3) int32 (``SceneGeometry``'s), world units."""

    digest: str
    vertices: np.ndarray
    triangles: np.ndarray

    @classmethod
    def of(cls, geometry):
        vertices = np.ascontiguousarray(geometry.vertices)
        triangles = np.ascontiguousarray(geometry.triangles)
        digest = hashlib.blake2b(vertices.tobytes())
        digest.update(triangles.tobytes())
        return cls(digest.hexdigest(), vertices, triangles)

    def build(self):
        """The BVHTree of the triangles (as ``pipeline.scene_tree`` builds it)."""
        return BVHTree.FromPolygons(
            self.vertices.tolist(), self.triangles.tolist(), all_triangles=True
        )


def portable(frame):
    """A copy of ``frame`` for the workers: its tree as a TreeSource (None when it has
    none), a Diagnostics of its own (the frame's asks Blender whether to stop), counts
    at zero."""
    tree = None if frame.tree is None else TreeSource.of(frame.geometry)
    return replace(frame, tree=tree, diag=Diagnostics(), casts=0, shadow_casts=0, rays=0)


def frame_here(frame, context):
    """``frame`` with its tree, in the process that runs a task: a TreeSource is built
    into a tree once per digest and kept in ``context.memo`` (the last one only)."""
    source = frame.tree
    if not isinstance(source, TreeSource):
        return frame
    kept = context.memo.get(TREE_MEMO)
    if kept is None or kept[0] != source.digest:
        context.memo[TREE_MEMO] = kept = (source.digest, source.build())
    return replace(frame, tree=kept[1])
