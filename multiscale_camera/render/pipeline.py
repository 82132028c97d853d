"""Scene -> passes: the steps of a render, each a plain function, shared by the engine,
the operators and the tests."""

import time
from dataclasses import dataclass, field

import numpy as np

from ..adapters.lights import scene_lights, world_colour
from ..adapters.meshes import scene_geometry
from ..adapters.scene import rig_from_scene
from ..core.fingerprint import field_key
from ..core.methods import prepare, settings_for
from ..core.validate import crossing_messages, empty_mask_messages
from ..io import cache
from .raycast import march
from .shade import shade

PASSES = (
    # name, channels, channel ids, Blender pass type
    ("Combined", 4, "RGBA", "COLOR"),
    ("Depth", 1, "Z", "VALUE"),
    ("Normal", 3, "XYZ", "VECTOR"),
    ("IndexOB", 1, "X", "VALUE"),
    ("Membership", 1, "X", "VALUE"),
)
# Depth written where a ray hits nothing, as Blender's own engines do.
MISS_DEPTH = 1e10
NO_MESH = "The scene has no visible mesh: only the world is rendered"


@dataclass
class Frame:
    """Everything a render needs, prepared once per frame.

    rig : Rig. field : RayField. geometry : SceneGeometry. tree : BVHTree or None.
    lights : list of Light. world : (3,) float32 linear colour.
    transparent : bool, film transparency (misses get alpha 0).
    scale : float, diagonal of the scene's bounds, world units.
    notices : list of str, for the user. seconds : dict, stage timings.
    """

    rig: object
    field: object
    geometry: object
    tree: object
    lights: list
    world: np.ndarray
    transparent: bool
    scale: float
    notices: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)
    casts: int = 0

    @property
    def size(self):
        return self.rig.size


def build_field(scene, should_stop=None):
    """The scene's ray field, from the field cache (``io.cache``: memory, then disk) when
    the rig and settings are unchanged.

    ``scene`` should be an evaluated scene (``depsgraph.scene``), so that object
    matrices are current.

    Returns
    -------
    (RayField, built) : the field, and whether it was built now.
    """
    settings_group = scene.multiscale
    rig = rig_from_scene(scene)
    settings = settings_for(settings_group.quality, settings_group.accuracy_px)
    key = field_key(rig, settings_group.method, settings)
    cache.CACHE.limit_mb = float(getattr(settings_group, "cache_limit_mb", cache.DEFAULT_LIMIT_MB))
    # checks before each build that the methods do not make themselves
    notices = list(rig.notices) + empty_mask_messages(rig) + crossing_messages(rig)
    fld = cache.CACHE.get(key, rig)
    if fld is not None:
        fld.notices = notices
        return fld, False
    fld = prepare(rig, settings_group.method, settings, should_stop)
    fld.notices = notices
    failed = cache.CACHE.put(key, fld)
    if failed:
        fld.notices.append(failed)
    return fld, True


def clear_fields():
    """Forget every cached field (memory and disk)."""
    cache.CACHE.clear()


def prepare_frame(depsgraph, should_stop=None):
    """Build (or reuse) the ray field and the scene's BVH.

    Raises
    ------
    RigError, SolverDidNotConverge: the rig cannot be rendered (the message says why).
    Cancelled: ``should_stop`` said so.
    """
    from mathutils.bvhtree import BVHTree

    scene = depsgraph.scene
    t0 = time.perf_counter()
    ray_field, built = build_field(scene, should_stop)
    rig = ray_field.rig
    t1 = time.perf_counter()
    t2 = t1
    geometry = scene_geometry(depsgraph)
    notices = list(ray_field.notices) + list(ray_field.warnings)
    if len(geometry):
        tree = BVHTree.FromPolygons(
            geometry.vertices.tolist(), geometry.triangles.tolist(), all_triangles=True
        )
        scale = float(np.linalg.norm(geometry.vertices.max(0) - geometry.vertices.min(0)))
    else:
        tree, scale = None, 1.0
        notices.append(NO_MESH)
    if built:  # geometry in the bending stretch hides a camera's view: say so once
        from ..core.validate import obstruction_messages
        from .checks import geometry_cast

        notices += obstruction_messages(rig, geometry_cast(geometry, tree))
    t3 = time.perf_counter()
    return Frame(
        rig=rig,
        field=ray_field,
        geometry=geometry,
        tree=tree,
        lights=scene_lights(depsgraph),
        world=world_colour(scene),
        transparent=bool(scene.render.film_transparent),
        scale=max(scale, 1e-6),
        notices=notices,
        seconds={"field" if built else "field (cached)": t1 - t0, "geometry": t3 - t2},
    )


def render_rows(frame, row0, row1, should_stop=None):
    """Render image rows ``row0 .. row1 - 1`` (row 0 at the top).

    Returns
    -------
    dict pass name -> (row1 - row0, W, C) float32 array, row 0 at the top.

    Raises
    ------
    raycast.Cancelled when ``should_stop`` says so.
    """
    width = frame.size[0]
    iy, ix = np.mgrid[row0:row1, 0:width]
    bundle = frame.field.rays(ix.ravel(), iy.ravel())
    hits = march(frame.tree, bundle, should_stop)
    frame.casts += hits.casts
    colour, normal = shade(frame.geometry, hits, frame.lights, frame.world, frame.tree, frame.scale)
    shape = (row1 - row0, width)
    alpha = np.where(hits.hit | (not frame.transparent), 1.0, 0.0).astype(np.float32)
    if frame.transparent:
        colour = colour * alpha[:, None]
    # Membership: where the ray leaves the bending stretch (DESIGN.md), not at the hit
    leave = frame.field.exit_index(ix.ravel(), iy.ravel())
    if leave is None:
        leave = np.full(len(bundle), bundle.vertices.shape[1] - 1)
    leave = np.clip(leave, 0, bundle.vertices.shape[1] - 1)
    membership = bundle.membership[np.arange(len(bundle)), leave]
    index = np.zeros(len(hits.hit), dtype=np.float32)
    index[hits.hit] = frame.geometry.pass_index[hits.triangle[hits.hit]]
    depth = np.where(hits.hit, bundle.start_depth + hits.distance, MISS_DEPTH)
    return {
        "Combined": np.concatenate([colour, alpha[:, None]], axis=1).reshape(*shape, 4),
        "Depth": depth.astype(np.float32).reshape(*shape, 1),
        "Normal": normal.reshape(*shape, 3),
        "IndexOB": index.reshape(*shape, 1),
        "Membership": membership.astype(np.float32).reshape(*shape, 1),
    }


def rows_per_tile(width, rays=16384):
    """Rows in a tile of about ``rays`` rays: small enough to show progress and to stop
    within a fraction of a second, large enough that numpy overhead stays negligible."""
    return max(1, rays // max(width, 1))
