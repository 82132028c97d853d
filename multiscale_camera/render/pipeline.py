"""Scene -> passes: the steps of a render, each a plain function, shared by the engine,
the operators and the tests. The field comes from the field service (``fields``)."""

import hashlib
from dataclasses import dataclass, field

import numpy as np
from mathutils.bvhtree import BVHTree

from ..adapters.lights import World, scene_lights, scene_world
from ..adapters.meshes import SceneGeometry, scene_geometry
from ..adapters.scene import processes_of
from ..core.diagnostics import Diagnostics, Level
from ..core.geometry import Rig
from ..core.quality import obstruction_messages
from ..core.runtime import gave_up, runtime, worker_count
from ..core.sampling import Occupancy, RaySampler, sample_offsets
from .checks import geometry_cast
from .fields import SERVICE, WORKERS_GIVEN_UP
from .memory import guard_memory
from .raycast import march
from .shade import shade
from .surface import surface_errors, surface_messages, with_surface
from .volume import FrameVolumes, composite_volumes, prepare_volumes

PASSES = (
    # name, channels, channel ids, Blender pass type
    ("Combined", 4, "RGBA", "COLOR"),
    ("Depth", 1, "Z", "VALUE"),
    ("Normal", 3, "XYZ", "VECTOR"),
    ("IndexOB", 1, "X", "VALUE"),
    ("Membership", 1, "X", "VALUE"),
)
# Not a Blender pass: each pixel centre's first hit, world units, and the index of its
# object in the frame's ``geometry.object_names`` plus one (all 0 where it misses), for
# the frame-to-frame jump of an animation (``render.sequence``); never written to a file.
HIT_PASS = ("First Hit", 4)
# Depth written where a ray hits nothing, as Blender's own engines do.
MISS_DEPTH = 1e10
NO_MESH = "The scene has no visible mesh: only the world is rendered"
NO_LIGHTS = "The scene has no lights: surfaces are lit by the world colour alone"
# Bounds padding, a fraction of the scene's size: float32 BVH boxes round outwards.
BOUNDS_PAD = 1e-4
# Seed of the sub-pixel jitter: renders are deterministic.
SAMPLE_SEED = 0


@dataclass
class Frame:
    """Everything a render needs, prepared once per frame.

    rig : core.geometry.Rig. field : core.methods.RayField (shared with the field
        cache: read only). geometry : adapters.meshes.SceneGeometry.
    tree : mathutils.bvhtree.BVHTree or None (no triangles).
    lights : list of adapters.lights.Light. world : adapters.lights.World.
    transparent : bool, film transparency (misses get alpha 0).
    scale : float, diagonal of the scene's bounds, world units.
    diag : core.diagnostics.Diagnostics, what the frame has to say (``notices``) and
        its seconds per stage (``seconds``), and the cancel check of the render.
    sampler : core.sampling.RaySampler. bounds : ((3,), (3,)) float64 padded scene box
        or None. samples : int, rays per pixel. filter_width : float, pixels.
    processes : int, worker processes for the tiles, the simplification and the ray
        tables (0: one per core; ``adapters.scene.processes_of``).
    occupancy : core.sampling.Occupancy of the triangles in ``bounds``, or None.
    volumes : render.volume.FrameVolumes.
    report : dict or None, the field's build report (docs/report.md), when asked for.
    rebuilt : dict, what the preparation built and reused (``frame_rebuilt``).
    casts, shadow_casts, rays : int, counted as the render goes.
    """

    rig: Rig
    field: object
    geometry: SceneGeometry
    tree: object
    lights: list
    world: World
    transparent: bool
    scale: float
    diag: Diagnostics = field(default_factory=Diagnostics)
    sampler: RaySampler | None = None
    bounds: tuple | None = None
    samples: int = 1
    filter_width: float = 1.5
    processes: int = 0
    casts: int = 0
    shadow_casts: int = 0
    rays: int = 0
    volumes: FrameVolumes = field(default_factory=FrameVolumes)
    occupancy: Occupancy | None = None
    report: dict | None = None
    rebuilt: dict = field(default_factory=dict)

    @property
    def size(self):
        return self.rig.size

    @property
    def notices(self) -> list[str]:
        """The warnings the frame has said so far, in order."""
        return self.diag.texts(Level.WARNING)

    @property
    def seconds(self) -> dict[str, float]:
        """Seconds per stage (field, geometry, simplify, render)."""
        return self.diag.seconds


def build_field(scene, diag=None):
    """The scene's ray field through the field service (``fields.SERVICE``: cached when
    the rig and settings are unchanged). ``scene`` should be an evaluated scene
    (``depsgraph.scene``), so that object matrices are current.

    Returns
    -------
    (RayField, built) : the field, and whether it was built now.
    """
    result = SERVICE.get(SERVICE.request(scene), diag)
    return result.field, result.built


def clear_fields():
    """Forget every cached field (memory and disk)."""
    SERVICE.clear()


def prepare_frame(depsgraph, diag=None, report=False, step_frames=True, render=True):
    """Build (or reuse) the ray field and the scene's BVH.

    ``diag`` (core.diagnostics.Diagnostics or None) steers the work (Esc) and becomes
    the frame's: what the frame has to say and its seconds per stage. With ``report``
    the field is measured (once per field) and the frame carries its build report.
    ``step_frames`` False (the viewport's picture, drawn) takes a rig in motion's shot
    layout only when it is known (``FieldService.request``).
    ``render``: the frame will be rendered at the scene's full size, so the memory guard
    weighs that render too (False for the viewport's small picture and for Export Rays,
    which renders nothing).

    Raises
    ------
    RigError, SolverDidNotConverge: the rig cannot be rendered (the message says why);
    ``memory.MemoryBudgetError`` (a RigError) before the build when the build or the
    render would need more memory than the scene's budget.
    Cancelled: ``diag`` said so.
    """
    diag = diag if diag is not None else Diagnostics()
    scene = depsgraph.scene
    # volumes first: a missing or unusable volume file stops the render before the build
    volumes, volume_notices = prepare_volumes(depsgraph)
    with diag.stage("field"), runtime().journal() as runs:  # what the field's workers did
        request = SERVICE.request(scene, depsgraph=depsgraph, step_frames=step_frames)
        guard_off = guard_memory(scene, request, render=render)  # before large allocations
        if guard_off:
            diag.warn(guard_off)
        result = SERVICE.get(request, diag, measure=report)
    if not result.built:  # said as "field (cached)" in the timings
        diag.seconds["field (cached)"] = diag.seconds.pop("field")
    ray_field = result.field
    rig = ray_field.rig
    with diag.stage("geometry"):
        geometry = scene_geometry(depsgraph)
        bounds = occupancy = None
        tree_built = False
        if len(geometry):
            (tree, bounds, occupancy, scale), tree_built = scene_tree_built(geometry)
        else:
            tree, scale = None, 1.0
        diag.extend(volume_notices)
        if not len(geometry) and not volumes:
            diag.warn(NO_MESH)
        diag.extend(geometry.notices)
        lights = scene_lights(depsgraph)
        if not lights and len(geometry):
            diag.warn(NO_LIGHTS)
        said = []
        world = scene_world(scene, said)
        diag.extend(said)
        published = result.report
        if result.built:  # geometry in the bending stretch hides a camera's view: say so once
            diag.extend(obstruction_messages(rig, geometry_cast(geometry, tree)))
            # and preserved pixels that show the surface away from their camera's view,
            # measured once: for the warning and for the report this build publishes
            errors = surface_errors(ray_field, tree, diag.should_stop)
            target = request.settings.accuracy_px
            diag.extend(surface_messages(rig.cameras, errors, target))
            if published is not None:
                published = with_surface(published, errors)
    settings = scene.multiscale
    tol = settings.simplify_px
    processes = processes_of(scene)
    with diag.stage("simplify"), runtime().journal() as simplified:
        sampler = sampler_for(ray_field, tol, bounds, diag.should_stop, occupancy, processes)
    if gave_up(runs + simplified):  # the field's trace or the simplification
        diag.warn(WORKERS_GIVEN_UP)
    rebuilt = frame_rebuilt(scene.frame_current, result, tree_built, diag.seconds)
    if published is not None:
        published = dict(published, frame=rebuilt)
    return Frame(
        rig=rig,
        field=ray_field,
        geometry=geometry,
        tree=tree,
        lights=lights,
        world=world,
        transparent=bool(scene.render.film_transparent),
        scale=max(scale, 1e-6),
        diag=diag,
        sampler=sampler,
        bounds=bounds,
        samples=max(1, int(settings.samples)),
        filter_width=float(getattr(scene.render, "filter_size", 1.5)),
        processes=processes,
        volumes=volumes,
        occupancy=occupancy,
        report=published,
        rebuilt=rebuilt,
    )


def frame_rebuilt(number, result, tree_built, seconds):
    """What frame ``number``'s preparation built and what it took as it was, for the
    log and the report's ``frame`` (docs/report.md): ``built`` and ``reused`` list the
    parts ("field", "camera claims ...", "membership solve (warm start)", "mask
    weights", "curves", "BVH"),
    ``seconds`` the stages' seconds so far. ``result`` is the field service's
    FieldResult, ``tree_built`` whether the BVH was built."""
    built, reused = [], []
    if not result.built:
        reused.append("field")
    else:
        took = result.field.stats.get("reuse")
        if took is None:
            built.append("field")
        elif "weights" in took:  # IMAGE_BLEND: its weights, and this frame's curves
            (reused if took["weights"] == "reused" else built).append("mask weights")
            built.append("curves")
        else:
            names = ", ".join(f"'{n}'" for n in took["claims_reused"])
            if names:
                reused.append(f"claims of {names}")
            rest = ", ".join(f"'{n}'" for n in took["claims_built"])
            built.append(f"claims of {rest}" if rest else "no claims")
            built.append(took["solve_said"])
            built.append("trace")
    (built if tree_built else reused).append("BVH")
    return {
        "number": int(number),
        "built": built,
        "reused": reused,
        "seconds": {k: round(float(v), 3) for k, v in seconds.items()},
    }


def rebuilt_line(rebuilt):
    """The log's line for a frame's ``rebuilt`` record (``frame_rebuilt``)."""
    seconds = rebuilt["seconds"]
    field_s = seconds.get("field", seconds.get("field (cached)", 0.0))
    return (
        f"Multiscale: frame {rebuilt['number']}: built {', '.join(rebuilt['built']) or 'nothing'}; "
        f"reused {', '.join(rebuilt['reused']) or 'nothing'}; field {field_s:.2f} s, "
        f"geometry {seconds.get('geometry', 0.0):.2f} s"
    )


def scene_tree(geometry):
    """The BVH tree, padded bounds, occupancy grid and size of ``geometry``'s triangles,
    reused from the last call when the triangles are the same (building them takes most
    of a frame's preparation: 0.14 of 0.25 s for 100k triangles); the field service
    keeps the last one (``SERVICE.trees``).

    Returns
    -------
    tree : BVHTree. bounds : ((3,), (3,)) float64, world units. occupancy : Occupancy.
    scale : float, the diagonal of the triangles' bounding box, world units.
    """
    return scene_tree_built(geometry)[0]


def scene_tree_built(geometry):
    """(``scene_tree``'s tuple, whether it was built now rather than reused)."""
    digest = hashlib.blake2b(np.ascontiguousarray(geometry.vertices).tobytes())
    digest.update(np.ascontiguousarray(geometry.triangles).tobytes())
    key = digest.hexdigest()
    trees = SERVICE.trees
    built = key not in trees
    if built:
        tree = BVHTree.FromPolygons(
            geometry.vertices.tolist(), geometry.triangles.tolist(), all_triangles=True
        )
        lo, hi = geometry.vertices.min(0), geometry.vertices.max(0)
        scale = float(np.linalg.norm(hi - lo))
        pad = BOUNDS_PAD * max(scale, 1e-6) + 1e-6
        bounds = (lo - pad, hi + pad)
        occupancy = Occupancy(geometry.vertices, geometry.triangles, *bounds, pad=pad)
        trees.clear()
        trees[key] = tree, bounds, occupancy, scale
    return trees[key], built


def sampler_for(
    ray_field, tol_px, bounds, should_stop=None, occupancy=None, processes=1, pixel_rays=False
):
    """The field's RaySampler at ``tol_px`` pixels for geometry inside ``bounds`` (and in
    the occupied cells of ``occupancy``, when given), built once per field, tolerance and
    geometry layout; its simplification in ``processes`` worker processes (0: one per
    core). ``pixel_rays``: a field without a traced lattice has every pixel's ray taken
    and simplified once (``core.sampling.PixelRays``), for pictures sampled between its
    pixels."""
    cache = ray_field.__dict__.setdefault("_samplers", {})
    box = None if bounds is None else tuple(np.round(np.concatenate(bounds), 9).tolist())
    cells = None if occupancy is None else occupancy.digest()
    key = (round(float(tol_px), 6), box, cells, bool(pixel_rays))
    if key not in cache:
        cache.clear()
        clearance = None if occupancy is None else occupancy.clearance
        occupied = None if occupancy is None else occupancy.any_between
        cache[key] = RaySampler(
            ray_field,
            key[0],
            bounds,
            should_stop,
            clearance,
            occupied,
            worker_count(processes),
            pixel_rays=key[3],
        )
    return cache[key]


def _cast_and_shade(frame, seg, should_stop):
    """(hits, shaded) for ``Segments``; counts the casts on ``frame``."""
    hits = march(frame.tree, seg, should_stop, frame.bounds, frame.geometry, frame.occupancy)
    shaded = shade(
        frame.geometry, hits, frame.lights, frame.world, frame.tree, frame.scale, should_stop
    )
    frame.casts += hits.casts
    frame.shadow_casts += shaded.casts
    frame.rays += len(seg)
    return hits, shaded


def _rgba(frame, hits, shaded):
    """(R, 4) float32 Combined (premultiplied by alpha under film transparency). A hit
    on a holdout shows transparent black, whatever the film (as Cycles' holdouts)."""
    alpha = np.where(hits.hit | (not frame.transparent), 1.0, 0.0).astype(np.float32)
    colour = shaded.colour * alpha[:, None] if frame.transparent else shaded.colour
    holdout = frame.geometry.holdout
    if holdout is not None and holdout.any():
        held = hits.hit.copy()
        held[held] = holdout[hits.triangle[held]]
        alpha[held] = 0.0
        colour = np.where(held[:, None], 0.0, colour)
    return np.concatenate([colour, alpha[:, None]], axis=1)


def render_rows(frame, row0, row1, should_stop=None):
    """Render image rows ``row0 .. row1 - 1`` (row 0 at the top).

    Combined averages ``frame.samples`` rays per pixel (sub-pixel rays jittered under
    the pixel filter, see ``core.sampling.sample_offsets``); one sample is the pixel's
    own ray. Depth, Normal, IndexOB and Membership come from the pixel's own ray (its
    centre), unfiltered, as data passes are.

    Returns
    -------
    dict pass name -> (row1 - row0, W, C) float32 array, row 0 at the top: the passes
    of ``PASSES`` and ``HIT_PASS``.

    Raises
    ------
    Cancelled when ``should_stop`` says so.
    """
    width = frame.size[0]
    iy, ix = np.mgrid[row0:row1, 0:width]
    ix, iy = ix.ravel(), iy.ravel()
    centre = frame.sampler.segments(ix + 0.5, iy + 0.5, ix, iy)
    hits, shaded = _cast_and_shade(frame, centre, should_stop)
    combined = _rgba(frame, hits, shaded)
    if frame.samples > 1:
        off = sample_offsets(ix, iy, frame.samples, frame.filter_width, SAMPLE_SEED)
        sx = ((ix + 0.5)[:, None] + off[..., 0]).ravel()
        sy = ((iy + 0.5)[:, None] + off[..., 1]).ravel()
        seg = frame.sampler.segments(sx, sy)
        s_hits, s_shaded = _cast_and_shade(frame, seg, should_stop)
        combined = _rgba(frame, s_hits, s_shaded).reshape(len(ix), frame.samples, 4).mean(1)
    shape = (row1 - row0, width)
    index = np.zeros(len(hits.hit), dtype=np.float32)
    index[hits.hit] = frame.geometry.pass_index[hits.triangle[hits.hit]]
    if frame.geometry.holdout is not None:  # Cycles writes no object index on a holdout
        index[hits.hit] *= ~frame.geometry.holdout[hits.triangle[hits.hit]]
    depth = np.where(hits.hit, centre.start_depth + hits.distance, MISS_DEPTH)
    if frame.volumes:
        # volumes are marched along the pixel's own bent ray (its centre), membership and all
        bundle = frame.field.rays(ix, iy)
        colour, alpha, depth = composite_volumes(
            frame.volumes,
            bundle,
            hits.distance,
            combined[:, :3],
            combined[:, 3],
            depth,
            should_stop,
        )
        combined = np.concatenate([colour, alpha[:, None]], axis=1)
    return {
        "Combined": combined.astype(np.float32).reshape(*shape, 4),
        "Depth": depth.astype(np.float32).reshape(*shape, 1),
        "Normal": shaded.normal.reshape(*shape, 3),
        "IndexOB": index.reshape(*shape, 1),
        "Membership": centre.membership.astype(np.float32).reshape(*shape, 1),
        HIT_PASS[0]: first_hits(frame, hits).reshape(*shape, 4),
    }


def first_hits(frame, hits):
    """(N, 4) float32: each hit's world point and its object's index in
    ``frame.geometry.object_names`` plus one; zeros where a ray missed (``HIT_PASS``)."""
    out = np.zeros((len(hits.hit), 4), dtype=np.float32)
    out[hits.hit, :3] = hits.location[hits.hit]
    out[hits.hit, 3] = frame.geometry.object_of[hits.triangle[hits.hit]] + 1
    return out


def tiles(frame):
    """[(row0, row1), ...] covering the image, ``rows_per_tile`` rows each."""
    width, height = frame.size
    step = rows_per_tile(width, samples=frame.samples)
    return [(r, min(r + step, height)) for r in range(0, height, step)]


def rows_per_tile(width, rays=16384, samples=1):
    """Rows in a tile of about ``rays`` rays (``samples`` per pixel, plus the pixel's own
    ray): small enough to show progress and to stop within a fraction of a second,
    large enough that numpy overhead stays negligible."""
    per_pixel = 1 + (samples if samples > 1 else 0)
    return max(1, rays // max(width * per_pixel, 1))
