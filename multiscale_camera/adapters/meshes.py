"""Evaluated scene geometry -> one world-space triangle soup with per-triangle attributes
(material, UVs, corner normals), and the materials as plain numbers and textures."""

from dataclasses import dataclass, field

import bpy
import numpy as np

from ..core.geometry import cross3, dot3
from .textures import texture_from_node
from .visibility import HOLDOUT, camera_instances
from .volumes import is_volume_source

GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT"}
DEFAULT_COLOUR = (0.8, 0.8, 0.8)


@dataclass(frozen=True)
class Material:
    """What the solid shading reads of a material.

    base : (3,) float64 linear base colour (the value, used when there is no texture).
    texture : adapters.textures.Texture feeding the base colour, or None.
    emission : (3,) float64 linear emitted radiance (colour times strength).
    """

    base: np.ndarray
    texture: object = None
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class SceneGeometry:
    """All visible triangles of a scene in world space.

    Attributes
    ----------
    vertices : (V, 3) float64, world units.
    triangles : (T, 3) int64, vertex indices.
    colour : (T, 3) float32, linear base colour value of each triangle's material.
    pass_index : (T,) int32, the owning object's ``pass_index``.
    object_names : list of str, and ``object_of`` (T,) int32 indexing it.
    material : (T,) int32, index into ``materials``.
    materials : list of Material.
    uv : (T, 3, 2) float32, the active UV map at each corner (zeros without one).
    normals : (T, 3, 3) float32, world-space unit corner normals (smooth faces interpolate
        their vertices' normals; flat faces carry the face normal at every corner).
    notices : list of str, what the user should know (unreadable textures, ...).
    holdout : (T,) bool, triangles of holdout objects (they hide what lies behind them
        and show transparent).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    colour: np.ndarray
    pass_index: np.ndarray
    object_of: np.ndarray
    object_names: list
    material: np.ndarray = None
    materials: list = field(default_factory=list)
    uv: np.ndarray = None
    normals: np.ndarray = None
    notices: list = field(default_factory=list)
    holdout: np.ndarray = None

    def __len__(self):
        return len(self.triangles)


def uses_nodes(block):
    """Whether a material or world is shaded by its node tree (always, from Blender 5.0)."""
    if block.node_tree is None:
        return False
    return bpy.app.version >= (5, 0, 0) or block.use_nodes


def _principled(material):
    if material is None or not uses_nodes(material):
        return None
    for node in material.node_tree.nodes:
        if node.type == "BSDF_PRINCIPLED":
            return node
    return None


def material_colour(material, fallback):
    """Linear RGB base colour of a material: its Principled BSDF's Base Color value, else
    its viewport colour; ``fallback`` (the object's colour) when there is no material."""
    if material is None:
        return tuple(fallback[:3])
    node = _principled(material)
    if node is not None:
        return tuple(node.inputs["Base Color"].default_value[:3])
    return tuple(material.diffuse_color[:3])


def _linked_image_node(socket):
    """The Image Texture node feeding ``socket`` directly, or None."""
    for link in socket.links:
        node = link.from_node
        if node.type == "TEX_IMAGE" and getattr(node, "image", None) is not None:
            return node
    return None


def read_material(material, fallback, notices, cache):
    """A ``Material`` for a Blender material (None: the object's colour ``fallback``).
    ``cache`` (dict) keeps one Texture per image node across objects."""
    base = np.array(material_colour(material, fallback), dtype=np.float64)
    node = _principled(material)
    if node is None:
        return Material(base)
    texture = None
    tex_node = _linked_image_node(node.inputs["Base Color"])
    if tex_node is not None:
        key = tex_node.as_pointer()
        if key not in cache:
            cache[key] = texture_from_node(tex_node, notices)
        texture = cache[key]
    emission = np.zeros(3)
    if "Emission Color" in node.inputs and "Emission Strength" in node.inputs:
        emission = np.array(node.inputs["Emission Color"].default_value[:3], dtype=np.float64)
        emission = emission * float(node.inputs["Emission Strength"].default_value)
    return Material(base, texture, emission)


def _mesh_arrays(mesh, matrix):
    """World-space vertices, triangles, material slots, corner UVs and corner normals."""
    nv, nt, nl = len(mesh.vertices), len(mesh.loop_triangles), len(mesh.loops)
    co = np.empty(nv * 3, dtype=np.float64)
    mesh.vertices.foreach_get("co", co)
    # einsum, not ``@``: BLAS's threads, woken by a product of 30,000 rows or more, spin on
    # the cores the render's workers cast on (core/runtime)
    co = np.einsum("ij,vj->vi", matrix[:3, :3], co.reshape(nv, 3)) + matrix[:3, 3]
    tris = np.empty(nt * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("vertices", tris)
    loops = np.empty(nt * 3, dtype=np.int64)
    mesh.loop_triangles.foreach_get("loops", loops)
    mat = np.empty(nt, dtype=np.int64)
    mesh.loop_triangles.foreach_get("material_index", mat)
    uv = np.zeros((nt, 3, 2), dtype=np.float32)
    layer = mesh.uv_layers.active
    if layer is not None and nl:
        corner_uv = np.empty(nl * 2, dtype=np.float32)
        layer.data.foreach_get("uv", corner_uv)
        uv = corner_uv.reshape(nl, 2)[loops].reshape(nt, 3, 2)
    normals = np.empty(nl * 3, dtype=np.float32)
    corner = getattr(mesh, "corner_normals", None)
    if corner is not None and len(corner) == nl:
        corner.foreach_get("vector", normals)
    else:  # Blender before 4.1
        mesh.loops.foreach_get("normal", normals)
    normals = normals.reshape(nl, 3)[loops].reshape(nt, 3, 3).astype(np.float64)
    normals = np.einsum("ij,...j->...i", _inverse_transpose(matrix[:3, :3]), normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-30)
    return co, tris.reshape(nt, 3), mat, uv, normals.astype(np.float32)


def _inverse_transpose(m):
    """The inverse transpose of a 3x3 matrix ((3, 3) float64), which carries normals:
    its cofactors over its determinant (``np.linalg.inv`` wakes BLAS's threads, at any
    size: core/runtime). Rows of inv(M)^T are m1 x m2, m2 x m0, m0 x m1 over
    det M = m0 . (m1 x m2), m_i the rows of M."""
    m = np.asarray(m, dtype=np.float64)
    cof = cross3(m[[1, 2, 0]], m[[2, 0, 1]])
    return cof / float(dot3(m[0], cof[0]))


def scene_geometry(depsgraph):
    """Gather the geometry a render's camera rays see in an evaluated depsgraph
    (modifiers applied, instances and particles expanded) into one ``SceneGeometry``;
    of a viewport depsgraph (the rig check's), what a render would see: which objects
    count is decided in one place, ``visibility.camera_instances``."""
    verts, tris, colours, index, owner, names = [], [], [], [], [], []
    mats, uvs, normals, holdout = [], [], [], []
    materials, material_ids, notices, cache = [], {}, [], {}
    offset = 0
    for seen in camera_instances(depsgraph, GEOMETRY_TYPES):
        obj = seen.object
        if is_volume_source(obj):
            continue
        mesh = obj.to_mesh()
        if mesh is None:
            continue
        try:
            mesh.calc_loop_triangles()
            if len(mesh.loop_triangles) == 0:
                continue
            co, t, mat, uv, nor = _mesh_arrays(mesh, seen.matrix)
            slots = [s.material for s in obj.material_slots] or [None]
            ids = []
            for material in slots:
                # no material: the object's own colour, so one entry per object
                key = (material.name_full, None) if material else (None, obj.original.name)
                if key not in material_ids:
                    material_ids[key] = len(materials)
                    materials.append(read_material(material, obj.color, notices, cache))
                ids.append(material_ids[key])
            ids = np.array(ids, dtype=np.int32)
            tri_mat = ids[np.clip(mat, 0, len(ids) - 1)]
        finally:
            obj.to_mesh_clear()
        verts.append(co)
        tris.append(t + offset)
        offset += len(co)
        mats.append(tri_mat)
        colours.append(np.array([m.base for m in materials], np.float32)[tri_mat])
        uvs.append(uv)
        normals.append(nor)
        index.append(np.full(len(t), obj.original.pass_index, dtype=np.int32))
        owner.append(np.full(len(t), len(names), dtype=np.int32))
        names.append(obj.original.name)
        holdout.append(np.full(len(t), seen.kind == HOLDOUT))
    if not tris:
        return SceneGeometry(
            np.zeros((0, 3)),
            np.zeros((0, 3), np.int64),
            np.zeros((0, 3), np.float32),
            np.zeros(0, np.int32),
            np.zeros(0, np.int32),
            [],
            np.zeros(0, np.int32),
            materials,
            np.zeros((0, 3, 2), np.float32),
            np.zeros((0, 3, 3), np.float32),
            notices,
            np.zeros(0, bool),
        )
    return SceneGeometry(
        np.concatenate(verts),
        np.concatenate(tris),
        np.concatenate(colours),
        np.concatenate(index),
        np.concatenate(owner),
        names,
        np.concatenate(mats),
        materials,
        np.concatenate(uvs),
        np.concatenate(normals),
        notices,
        np.concatenate(holdout),
    )
