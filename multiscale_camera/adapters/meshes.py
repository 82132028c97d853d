"""Evaluated scene geometry -> one world-space triangle soup with per-triangle attributes."""

from dataclasses import dataclass

import numpy as np

from .volumes import is_volume_source

GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT"}
DEFAULT_COLOUR = (0.8, 0.8, 0.8)


@dataclass(frozen=True)
class SceneGeometry:
    """All visible triangles of a scene in world space.

    Attributes
    ----------
    vertices : (V, 3) float64, world units.
    triangles : (T, 3) int64, vertex indices.
    colour : (T, 3) float32, linear base colour of each triangle's material.
    pass_index : (T,) int32, the owning object's ``pass_index``.
    object_names : list of str, and ``object_of`` (T,) int32 indexing it.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    colour: np.ndarray
    pass_index: np.ndarray
    object_of: np.ndarray
    object_names: list

    def __len__(self):
        return len(self.triangles)


def uses_nodes(block):
    """Whether a material or world is shaded by its node tree (always, from Blender 5.0)."""
    import bpy

    if block.node_tree is None:
        return False
    return bpy.app.version >= (5, 0, 0) or block.use_nodes


def material_colour(material, fallback):
    """Linear RGB base colour of a material: its Principled BSDF's Base Color value, else
    its viewport colour; ``fallback`` (the object's colour) when there is no material."""
    if material is None:
        return tuple(fallback[:3])
    if uses_nodes(material):
        for node in material.node_tree.nodes:
            if node.type == "BSDF_PRINCIPLED":
                return tuple(node.inputs["Base Color"].default_value[:3])
    return tuple(material.diffuse_color[:3])


def _mesh_arrays(mesh, matrix):
    nv, nt = len(mesh.vertices), len(mesh.loop_triangles)
    co = np.empty(nv * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(nv, 3) @ matrix[:3, :3].T + matrix[:3, 3]
    tris = np.empty(nt * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", tris)
    mat = np.empty(nt, dtype=np.int64)
    mesh.loop_triangles.foreach_get("material_index", mat)
    return co, tris.reshape(nt, 3), mat


def scene_geometry(depsgraph):
    """Gather the render-visible geometry of an evaluated depsgraph (modifiers applied,
    instances expanded) into one ``SceneGeometry``."""
    verts, tris, colours, index, owner, names = [], [], [], [], [], []
    offset = 0
    for inst in depsgraph.object_instances:
        obj = inst.object
        if obj.type not in GEOMETRY_TYPES or is_volume_source(obj):
            continue
        mesh = obj.to_mesh()
        if mesh is None:
            continue
        try:
            mesh.calc_loop_triangles()
            if len(mesh.loop_triangles) == 0:
                continue
            co, t, mat = _mesh_arrays(mesh, np.array(inst.matrix_world, dtype=np.float64))
            slots = [material_colour(s.material, obj.color) for s in obj.material_slots]
            palette = np.array(slots or [tuple(obj.color[:3])], dtype=np.float32)
            colours.append(palette[np.clip(mat, 0, len(palette) - 1)])
        finally:
            obj.to_mesh_clear()
        verts.append(co)
        tris.append(t + offset)
        offset += len(co)
        index.append(np.full(len(t), obj.original.pass_index, dtype=np.int32))
        owner.append(np.full(len(t), len(names), dtype=np.int32))
        names.append(obj.original.name)
    if not tris:
        return SceneGeometry(
            np.zeros((0, 3)),
            np.zeros((0, 3), np.int64),
            np.zeros((0, 3), np.float32),
            np.zeros(0, np.int32),
            np.zeros(0, np.int32),
            [],
        )
    return SceneGeometry(
        np.concatenate(verts),
        np.concatenate(tris),
        np.concatenate(colours),
        np.concatenate(index),
        np.concatenate(owner),
        names,
    )
