"""Per-pixel ray tables: the straight segment of each bent ray that holds its first hit.

Beyond the segment that holds a pixel's first hit, what the pixel shows depends only on
that segment's line: a straight renderer (Cycles through a custom camera, another
renderer, a compositor) that starts a ray at the segment's start and follows its
direction meets the same surface first, because the march found nothing earlier on the
polyline. A ray that hits nothing is handed on as its last segment, whose direction is
the ray's last tangent. The tables come from the renderer's own rays and march: each
pixel centre's simplified polyline (``RaySampler.segments``), cast by ``raycast.march``
with the scene's box and occupancy culling, one tile of rows at a time.
"""

from dataclasses import dataclass
from functools import partial

import numpy as np

from ..core.geometry import RayBundle
from ..core.runtime import runtime
from ..core.sampling import Segments
from . import pipeline, workers
from .processes import blender_launcher, frame_here, portable
from .raycast import bundle_segments, clip_to_box, march

# A handed-on ray starts at least this fraction of the scene's size before its hit: far
# below anything visible, far above float32 rounding of the stored origins.
START_MARGIN = 1e-5


@dataclass(frozen=True)
class RayTables:
    """First-hit rays of an image of H x W pixels, row 0 at the top, world space.

    origin : (H, W, 3) float64, world units: start of the segment that holds the first
        hit (for a miss: start of the ray's last segment).
    direction : (H, W, 3) float64, unit: that segment's direction.
    distance : (H, W) float64, world units: from ``origin`` to the hit along
        ``direction`` (inf for a miss).
    depth : (H, W) float64, world units: arc length from camera 1's eye to the hit along
        the bent ray (the Depth pass; inf for a miss).
    hit : (H, W) bool.
    membership : (H, W) float32: the membership value where the ray leaves the bending
        stretch (the Membership pass).
    object_index : (H, W) float32: the hit object's ``pass_index`` (0 for a miss).
    casts : int, segment casts the march made.
    clipped : (H, W) bool: misses whose ray ended at its far plane (the cameras'
        ``clip_end``, ``core.sampling.clip_far``); their origin lies past the scene's
        box on the last segment's line, so a straight renderer sees only the world there.
    """

    origin: np.ndarray
    direction: np.ndarray
    distance: np.ndarray
    depth: np.ndarray
    hit: np.ndarray
    membership: np.ndarray
    object_index: np.ndarray
    casts: int
    clipped: np.ndarray = None


@dataclass(frozen=True)
class Polylines:
    """The polylines the renderer casts, in a ragged layout (see docs/ray_tables.md).

    points : (V, 3) float32, world units: each ray's vertices, ray after ray.
    offsets : (R + 1,) int64: ray r owns ``points[offsets[r]:offsets[r + 1]]``.
    membership : (V,) float32, the membership value at each vertex (nearest stored one).
    reach : (R,) float32, world units: how far the ray runs on past its last vertex.
    start_depth : (R,) float32, world units: camera 1's eye to vertex 0.
    pixels : (R, 2) int32, the (x, y) pixel of each ray, top-left origin.
    """

    points: np.ndarray
    offsets: np.ndarray
    membership: np.ndarray
    reach: np.ndarray
    start_depth: np.ndarray
    pixels: np.ndarray


def first_hit_segments(rays, hits, margin=0.0):
    """Origin of the segment holding each ray's first hit (last segment for a miss).

    Parameters
    ----------
    rays : core.sampling.Segments of R rays, or a RayBundle (its exact polylines,
        ``bundle_segments``). hits : Hits of the same rays (``raycast.march``).
    margin : float, world units: an origin closer than this to its hit is moved back
        along the segment's line to this distance.

    Returns
    -------
    origin : (R, 3) float64, world units. direction : (R, 3) float64 unit.
    distance : (R,) float64, world units, origin to hit (inf for a miss).
    """
    seg = bundle_segments(rays) if isinstance(rays, RayBundle) else rays
    r = len(seg)
    counts = np.diff(seg.offsets)
    # the segment holding arc length d of ray r is the last one starting before d (a hit
    # at a vertex belongs to the segment that ends there)
    target = np.where(hits.hit, hits.distance, np.inf)
    starts_before = seg.before < target[seg.ray]
    held = seg.offsets[:-1] + np.bincount(seg.ray, weights=starts_before, minlength=r).astype(
        np.int64
    )
    held = np.clip(held - 1, seg.offsets[:-1], seg.offsets[1:] - 1)
    held = np.where(counts > 0, held, 0)
    origin = seg.origin[held]
    direction = seg.direction[held]
    distance = np.where(hits.hit, hits.distance - seg.before[held], np.inf)
    # a ray handed on must not start on its surface (a renderer would skip the surface):
    # start at least ``margin`` before the hit, back along the segment's line
    short = hits.hit & (distance < margin)
    origin[short] -= direction[short] * (margin - distance[short])[:, None]
    distance[short] = margin
    return origin, direction, distance


def blocked_before(frame, origin, direction, length, should_stop=None):
    """Whether a surface lies on the stretch of each ray's line just before its origin.

    Parameters
    ----------
    frame : pipeline.Frame (its tree, bounds, triangles and occupancy grid).
    origin, direction : (N, 3) float64, world units; direction unit.
    length : (N,) float64 >= 0, world units: the stretch runs from ``origin - length *
        direction`` to ``origin``.
    should_stop : callable -> bool (raises ``Cancelled``).

    Returns
    -------
    (N,) bool, True where the stretch meets a triangle.
    """
    n = len(length)
    if n == 0:
        return np.zeros(0, dtype=bool)
    length = np.asarray(length, dtype=np.float64)
    start = origin - direction * length[:, None]
    rays = Segments(
        origin=start,
        direction=direction,
        length=length,
        ray=np.arange(n, dtype=np.int64),
        offsets=np.arange(n + 1, dtype=np.int64),
        before=np.zeros(n),
        start_depth=np.zeros(n),
        membership=np.zeros(n, dtype=np.float32),
    )
    hits = march(frame.tree, rays, should_stop, frame.bounds, frame.geometry, frame.occupancy)
    frame.casts += hits.casts
    return hits.hit


def ray_tables(frame, should_stop=None, progress=None, keep_polylines=False):
    """March every pixel of ``frame`` and tabulate its first-hit segment.

    Parameters
    ----------
    frame : pipeline.Frame; its tiles of rows are marched in render worker processes
        (``workers.worker_count(frame.processes)``, into shared tables; ``processes``)
        when the image has ``workers.MIN_RAYS`` pixels or more, else here.
    should_stop : callable -> bool (raises ``Cancelled``).
    progress : callable(fraction) or None, called after each tile of rows.
    keep_polylines : bool, also return the simplified polylines (``Polylines``); they
        are made here.

    Returns
    -------
    RayTables, or (RayTables, Polylines) with ``keep_polylines``.
    """
    width, height = frame.size
    shape = (height, width)
    step = pipeline.rows_per_tile(width)
    tiles = [(row0, min(row0 + step, height)) for row0 in range(0, height, step)]
    processes = 1 if keep_polylines else workers.worker_count(frame.processes)
    shared = processes > 1 and width * height >= workers.MIN_RAYS and len(tiles) > 1

    def table(extra, dtype, fill):
        out = None
        if shared:
            try:
                out = runtime().shared_array((*shape, *extra), dtype)
            except OSError:  # no shared memory to be had: one array here is as good
                pass
        out = np.empty((*shape, *extra), dtype) if out is None else out
        out[...] = fill
        return out

    out = (
        table((3,), np.float64, 0.0),  # origin
        table((3,), np.float64, 0.0),  # direction
        table((), np.float64, np.inf),  # distance
        table((), np.float64, np.inf),  # depth
        table((), bool, False),  # hit
        table((), np.float32, 0.0),  # membership
        table((), np.float32, 0.0),  # object index
        table((), bool, False),  # clipped
    )
    shared = shared and runtime().shared.handle(out[0]) is not None
    here = partial(_march_here, frame, out, keep_polylines)
    if shared:
        # in render workers (one per core by default) that write into the shared tables;
        # a tile whose worker was given up is marched here
        task = partial(_march_tile, portable(frame), out)
        run = runtime().run(
            task, tiles, processes, should_stop, launcher=blender_launcher(), local=here
        )
    else:
        run = ((index, here(tile, should_stop)) for index, tile in enumerate(tiles))
    counts, lines, rows = [0] * len(tiles), [None] * len(tiles), 0
    for index, (casts, polylines) in run:
        counts[index], lines[index] = casts, polylines
        rows += tiles[index][1] - tiles[index][0]
        if progress is not None:
            progress(rows / height)
    casts = int(sum(counts))
    frame.casts += casts
    tables = RayTables(*out[:7], casts, out[7])
    if not keep_polylines:
        return tables
    return tables, _concatenate(lines)


def _march_tile(frame, out, tile, context):
    """In a render worker: ``_march_here`` with the frame's tree built there."""
    return _march_here(frame_here(frame, context), out, False, tile, context)


def _march_here(frame, out, keep_polylines, tile, stop=None):
    """March rows tile[0] .. tile[1] - 1 of ``frame`` into the tables ``out`` (origin,
    direction, distance, depth, hit, membership, object index, clipped). Returns
    (segment casts, Polylines of the tile or None)."""
    origin, direction, distance, depth, hit, membership, index, clipped = out
    width = frame.size[0]
    row0, row1 = tile
    iy, ix = (a.ravel() for a in np.mgrid[row0:row1, 0:width])
    seg = frame.sampler.segments(ix + 0.5, iy + 0.5, ix, iy)
    hits = march(frame.tree, seg, stop, frame.bounds, frame.geometry, frame.occupancy)
    o, d, t = first_hit_segments(seg, hits, START_MARGIN * frame.scale)
    cut = clipped_before_geometry(seg, hits, frame.bounds)
    if cut.any():
        o[cut] = past_box(o[cut], d[cut], *frame.bounds, frame.scale)
    clipped[slice(row0, row1)] = cut.reshape(row1 - row0, width)
    rows = slice(row0, row1)
    origin[rows] = o.reshape(row1 - row0, width, 3)
    direction[rows] = d.reshape(row1 - row0, width, 3)
    distance[rows] = t.reshape(row1 - row0, width)
    depth[rows] = np.where(hits.hit, seg.start_depth + hits.distance, np.inf).reshape(
        row1 - row0, width
    )
    hit[rows] = hits.hit.reshape(row1 - row0, width)
    membership[rows] = seg.membership.reshape(row1 - row0, width)
    tile_index = np.zeros(len(seg), dtype=np.float32)
    tile_index[hits.hit] = frame.geometry.pass_index[hits.triangle[hits.hit]]
    index[rows] = tile_index.reshape(row1 - row0, width)
    lines = None
    if keep_polylines:
        whole = frame.sampler.segments(ix + 0.5, iy + 0.5, ix, iy, clip=False)
        lines = _polylines(frame.field.rays(ix, iy), whole, frame.sampler.reach)
    return hits.casts, lines


def clipped_before_geometry(seg, hits, bounds):
    """(R,) bool: misses that ended at their far plane where their line, run on, would
    still meet the scene's box ``bounds`` (None: no geometry, so none); a straight
    renderer handed such a ray from its last segment could show what the far plane
    hides."""
    if seg.clipped is None or bounds is None:
        return np.zeros(len(seg), dtype=bool)
    rays = np.flatnonzero(seg.clipped & ~hits.hit)
    # each ray ends on its last segment of non-zero length (a ray clipped before its
    # last vertex has empty segments after it)
    last = np.zeros(len(seg), dtype=np.int64)
    np.maximum.at(last, seg.ray, np.where(seg.length > 0, np.arange(len(seg.ray)), 0))
    last = last[rays]
    end = seg.origin[last] + seg.direction[last] * seg.length[last][:, None]
    direction = seg.direction[last]
    meets, _t0, _t1 = clip_to_box(end, direction, np.full(len(rays), np.inf), *bounds)
    out = np.zeros(len(seg), dtype=bool)
    out[rays[meets]] = True
    return out


def past_box(origin, direction, lo, hi, scale):
    """Points on the lines ``origin + t direction`` (t >= 0) beyond the box (lo, hi),
    by ``scale`` more: a ray started there meets nothing of the scene.

    origin, direction : (N, 3) float64 (direction unit); lo, hi : (3,) float64;
    scale : float, world units. Returns (N, 3) float64.
    """
    inv = 1.0 / np.where(direction == 0.0, 1e-300, direction)
    with np.errstate(over="ignore", invalid="ignore"):
        far = np.maximum((lo - origin) * inv, (hi - origin) * inv)
    exit_ = np.clip(np.nan_to_num(far.min(axis=1), posinf=0.0, neginf=0.0), 0.0, None)
    return origin + direction * (exit_ + scale)[:, None]


def _polylines(bundle, seg, reach):
    """The polylines ``seg`` (Segments of the rays of ``bundle``, whose last segments run
    ``reach`` world units past the last vertex) as ``Polylines``, with the bundle's
    membership at each kept vertex."""
    counts = np.diff(seg.offsets)
    last = seg.offsets[1:] - 1
    end = seg.origin[last] + seg.direction[last] * (seg.length[last] - reach)[:, None]
    # each ray: its segment starts, then the end of its last segment
    order = np.concatenate([np.arange(len(seg.ray)), len(seg.ray) + np.arange(len(bundle))])
    owner = np.concatenate([seg.ray, np.arange(len(bundle))])
    key = np.lexsort((order, owner))
    points = np.concatenate([seg.origin, end])[key].astype(np.float32)
    offsets = np.concatenate([[0], np.cumsum(counts + 1)])
    # membership at the bundle vertex nearest in arc length (every kept point is one)
    verts = bundle.vertices.astype(np.float64)
    r, k = verts.shape[:2]
    arc = np.concatenate(
        [np.zeros((r, 1)), np.cumsum(np.linalg.norm(np.diff(verts, axis=1), axis=-1), axis=1)],
        axis=1,
    )
    total = seg.before[last] + seg.length[last] - reach
    point_arc = np.concatenate([seg.before, total])[key]
    ray_of_point = owner[key]
    span = float(arc[:, -1].max()) + 1.0
    flat = (arc + span * np.arange(r)[:, None]).ravel()
    pos = np.searchsorted(flat, point_arc + span * ray_of_point)
    pos = np.clip(pos, 1, r * k - 1)
    nearer_left = np.abs(flat[pos - 1] - (point_arc + span * ray_of_point)) < np.abs(
        flat[pos] - (point_arc + span * ray_of_point)
    )
    pos = np.where(nearer_left, pos - 1, pos)
    pos = np.clip(pos, ray_of_point * k, ray_of_point * k + k - 1)
    membership = bundle.membership.reshape(-1)[pos].astype(np.float32)
    return Polylines(
        points=points,
        offsets=offsets.astype(np.int64),
        membership=membership,
        reach=np.asarray(bundle.reach, dtype=np.float32),
        start_depth=np.asarray(bundle.start_depth, dtype=np.float32),
        pixels=np.asarray(bundle.pixels, dtype=np.int32),
    )


def _concatenate(parts):
    starts = np.cumsum([0] + [len(p.points) for p in parts[:-1]])
    offsets = np.concatenate(
        [[0]] + [p.offsets[1:] + s for p, s in zip(parts, starts, strict=True)]
    ).astype(np.int64)
    return Polylines(
        points=np.concatenate([p.points for p in parts]),
        offsets=offsets,
        membership=np.concatenate([p.membership for p in parts]),
        reach=np.concatenate([p.reach for p in parts]),
        start_depth=np.concatenate([p.start_depth for p in parts]),
        pixels=np.concatenate([p.pixels for p in parts]),
    )
