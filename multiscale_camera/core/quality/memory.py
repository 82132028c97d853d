"""Peak memory of a field build and of a render, estimated from shapes before anything
large is allocated: the memory guard's arithmetic (docs/failures.md, "Memory").

``build_memory`` and ``render_memory`` take shapes (image size, cameras, voxels, traced
rays and their vertices, worker processes) and return bytes, part by part: the big
arrays the code allocates, each modelled from the code that makes it, with the bytes
per element it holds at its peak. The constants below were calibrated against peaks
measured on the bench rigs (bench/memory.py: the peak resident size of the process
plus each worker's); what they leave is stated there and in docs/performance.md.
``estimate_memory`` reads those shapes off a rig and its settings (the grids the build
would choose, the lattice, the step count) without building anything.
"""

from dataclasses import dataclass, field

import numpy as np

from ..field import (
    CELLS_ACROSS_NEAR_PER_PX,
    MIN_CELLS_ACROSS_NEAR,
    choose_grid,
    choose_levels,
    near_plane_width,
    solve_workers,
    step_cells,
)
from ..field.plane_step import MAX_GAIN, extra_steps
from .measure_memory import measure_memory

# Megabytes as Blender counts them (its memory statistics), and as the project says them
# everywhere (the Memory Budget, the cache limit, ``budget.size_text``): 2**20 bytes.
MB = 1 << 20

# A worker process of the field's runtime at work, before its share of rays: a fresh
# interpreter with numpy and the core (about 36 MB), the modules and buffers of a task.
WORKER_BASE_BYTES = 44 * MB
# The fill (eq. 4): every voxel centre (float64 xyz and its meshgrid) and the values,
# the claims of each camera (per camera below), and the fixed-size chunks the cameras'
# guides are splatted and the centres projected in.
FILL_BYTES_PER_VOXEL = 22
FILL_BYTES_PER_CAMERA_VOXEL = 17
FILL_CHUNK_BYTES = 75 * MB
# The solve (eq. 5), per voxel (or per pixel of the image plane for IMAGE_BLEND's
# weights): the conjugate gradients' float64 vectors and scratch, the multigrid's
# levels and the fill it reads.
SOLVE_BYTES_PER_CELL = 104
# What stays per voxel through the trace in the main process (the solved membership,
# its sampler's rows, the fill's values and claims).
KEPT_BYTES_PER_VOXEL = 11
# ... in each worker: the membership the tracer samples (float32, shared memory).
WORKER_BYTES_PER_VOXEL = 4
# Per pixel, in the main process, of a traced field: the lattice's index and leaf of
# every pixel (int32 each) and the preserved labels (int8), and per camera its
# summed-area table (int64, ``traced._CellLabels``).
LATTICE_BYTES_PER_PIXEL = 9
CELL_TABLE_BYTES_PER_PIXEL = 8
# Per vertex of a traced ray kept in the main process (float32 xyz and membership). Once
# the rounds (and their error estimates) are done, the lattice's parts are merged: the
# result beside the part being copied (a worker's share, or the largest round traced
# here; the rounds' peak and the merge's come one after the other).
RAY_BYTES_PER_VERTEX = 16
# The lattice's error estimate weighs ``methods.traced.DEVIATION_BLOCK_VERTICES``
# vertices at a time (the same value, tests/unit/test_memory_guard.py), a dozen float32
# and float64 temporaries each: per vertex of a round's rays, up to one block.
DEVIATION_BLOCK_VERTICES = 1 << 20
DEVIATION_BYTES_PER_VERTEX = 110
# A share of rays in a worker (or of the trace in the main process), measured stage by
# stage with ``tracemalloc`` on one share of the largest lattice round, replayed in a
# fresh process (bench/worker_memory.py; docs/performance.md, "Peak memory"). The stages
# come one after the other, so a share's peak is the largest of them, not their sum:
# 1. each camera's preserved pixels' rays (``FieldTracer.preserved_rays``), one camera
#    after the other: held as float32 xyz and membership on every step to the step limit
#    (16 B a vertex), laid out and sampled ``BLOCK_VERTICES`` vertices at a time (the
#    float64 temporaries of a block: 48 B a vertex for camera 1's pinhole rays, 130 for a
#    later camera's, whose guides are looked up by arc length; on nested grids 225, the
#    nested sampler's temporaries as the block is sampled), then trimmed to their length;
# 2. the other rays (transitions) as streamlines to the longest ray's length: 52 B a
#    vertex (the vertex buffer grown by doubling, 24; its trimmed and assembled copies,
#    24; the membership, 4), and a block of them completed at a time (float64 copies and
#    the sampler's temporaries: 46 B a vertex of the block, 130 on nested grids);
# 3. the share merged and pickled for the trip back: 50 B a vertex of the longest ray.
WORKER_BLOCK_VERTICES = 1 << 18  # ``field.tracer.BLOCK_VERTICES`` (the same value, tested)
HELD_BYTES_PER_VERTEX = 16
PINHOLE_LAYOUT_BYTES_PER_VERTEX = 48
CURVED_LAYOUT_BYTES_PER_VERTEX = 130
NESTED_BLOCK_BYTES_PER_VERTEX = 225
STREAMLINE_BYTES_PER_VERTEX = 52
COMPLETION_BYTES_PER_VERTEX = 46
NESTED_COMPLETION_BYTES_PER_VERTEX = 130
RETURN_BYTES_PER_VERTEX = 50
RECEIVE_BYTES_PER_VERTEX = 2 * RAY_BYTES_PER_VERTEX
# The lattice traces in rounds (the base lattice, then the midpoints of the cells it
# splits); the largest round holds about this fraction of every traced ray, and is
# what the workers share at once.
LARGEST_ROUND = 0.45
# ``field.tracer.MAX_RAYS_PER_SHARE``, ``MIN_RAYS_PER_PROCESS`` (tests check the values)
MAX_RAYS_PER_SHARE = 16384
MIN_RAYS_PER_PROCESS = 256
# ``methods.traced.MAX_STRIDE``, the lattice's widest stride in pixels (the same value,
# and the stride and step limit ``estimate_memory`` reads off a rig are those of
# ``traced.lattice_stride`` and ``traced.trace_field``: tests/unit/test_memory_guard.py).
MAX_STRIDE = 16
# IMAGE_BLEND's weights: float64 per camera and pixel while each camera is solved; the
# field keeps them eased, float32 (what AUTO holds while it measures the field).
WEIGHT_BYTES_PER_CAMERA_PIXEL = 8
# Easing the weights (float32, a float64 copy, temporaries): 38 B a camera-pixel measured.
EASE_BYTES_PER_CAMERA_PIXEL = 36
BLEND_BYTES_PER_CAMERA_PIXEL = 4
# Traced rays over the image's pixels, beyond the base lattice: the lattice splits
# cells down to single pixels along every preserved region's edge (a band of about
# this many pixels for each edge pixel), and refines elsewhere as the accuracy target
# and the transitions ask: a fraction of the pixels, TRACED_FRACTION at 0.5 px on a
# 480-pixel-wide image of a rig whose scales differ tenfold, growing as the target
# tightens and as (1 + log10 of the scale ratio) to the power TRACED_RATIO_EXPONENT
# (deeper zooms bend faster), falling as the image widens (the exponents below).
# Fitted on the calibration rows of bench/memory.py since a cell of one camera's
# preserved pixels is checked where the picture shows it (``methods.traced``), which
# traces about half the rays it did on the nested rigs' preserved regions.
EDGE_BAND_PIXELS = 3.0
TRACED_FRACTION = 0.124
TRACED_ACCURACY_EXPONENT = 1.15
TRACED_RATIO_EXPONENT = 1.7
TRACED_WIDTH_EXPONENT = 0.6
# ... on one uniform grid. There the scale ratio does not show (bench/memory.json):
# the fraction is this at 0.5 px on a 480-pixel-wide image, with its own accuracy
# exponent (fitted on the same rows but the contradictory rig's, whose lattice and
# edges alone exceed what it traces; the same width exponent).
TRACED_FRACTION_UNIFORM = 0.048
TRACED_ACCURACY_EXPONENT_UNIFORM = 1.75
# The longest traced ray over the trace's step limit: on one grid the limit allows two
# of its diagonals and the longest ray crosses about 0.7 of one (measured 0.33 to 0.35
# on the bench rows); on nested grids the limit adds every level's diagonals while a
# ray crosses only part of each finer level (measured 0.23 to 0.28 on the four nested
# rows of bench/memory.json: the longest ray of 39 to 147 vertices).
VERTICES_OF_LIMIT = 0.35
VERTICES_OF_LIMIT_NESTED = 0.25
# A render, measured (bench/render_memory.py: the two-camera scene, IMAGE_BLEND, at
# 480x270, 960x540 and 1920x1080, in-process and with two workers; the peak resident
# size a render adds to Blender's process and each worker's). Per pixel in Blender's
# process: what the Render Result takes (measured: the in-process slope, 34 B/px, less
# the engine's arrays; less than its 10 float32 channels, 40 B/px), the engine's
# IndexOB and First Hit arrays of the whole image (float32, 1 + 3 channels,
# ``engine._render``), and with workers the shared passes they write (``PASSES`` and
# the First Hit pass: 13 float32 channels, ``workers.shared_passes``).
RESULT_BYTES_PER_PIXEL = 20
ENGINE_BYTES_PER_PIXEL = (1 + 3) * 4
SHARED_PASS_BYTES_PER_PIXEL = 13 * 4
# A tile (``pipeline.rows_per_tile``: 16384 rays) rendered in Blender's process, with
# its scene (BVH, lights), per ray (measured: the in-process intercept, about 30 MB).
TILE_RAYS = 16384
TILE_BYTES_PER_RAY = 2048
# A render worker at work: a fresh interpreter, the frame it is sent (``portable``) and
# its tiles (measured: 294 MB at any size on the two-camera scene; what of it is the
# frame's and what the tile's is not separated, so a larger scene may need more), and
# per pixel its share of the shared passes and the frame's per-pixel arrays (34 B/px
# with two workers).
RENDER_WORKER_BYTES = 294 * MB
RENDER_WORKER_BYTES_PER_PIXEL = 34
# ``render.workers.MIN_RAYS``: under this many rays a frame renders in-process.
RENDER_MIN_RAYS = 200_000
# Per traced vertex of the field a frame renders: its rays (float32 xyz and membership)
# and the sampler's leaf schedules and ray measures (shared memory).
FIELD_BYTES_PER_VERTEX = 16 + 24


@dataclass(frozen=True)
class MemoryEstimate:
    """Peak memory of a build or a render, before it runs.

    main : int, bytes the main process adds at its peak (beyond what it holds now).
    worker : int, bytes of one worker process at its peak, its interpreter included.
    workers : int, worker processes that run at once (0: the work stays in the main
        process). parts : dict str -> int, what ``main`` and ``worker`` are made of
        (bytes, "worker: ..." for a worker's), the largest first. shapes : dict, the
        shapes the estimate was made from (pixels, voxels, traced rays, vertices).
    """

    main: int
    worker: int
    workers: int
    parts: dict = field(default_factory=dict)
    shapes: dict = field(default_factory=dict)

    @property
    def total(self):
        """int, bytes: the main process's peak addition plus every worker's peak."""
        return self.main + self.workers * self.worker

    def largest(self):
        """str, the name of the part that takes the most bytes."""
        return max(self.parts, key=self.parts.get) if self.parts else ""


def _estimate(main_parts, worker_parts, workers, shapes):
    main = int(sum(main_parts.values()))
    worker = int(sum(worker_parts.values())) if workers else 0
    parts = dict(main_parts)
    if workers:
        parts.update({f"workers: {k}": v * workers for k, v in worker_parts.items()})
    parts = dict(sorted(((k, int(v)) for k, v in parts.items() if v), key=lambda kv: -kv[1]))
    return MemoryEstimate(main, worker, workers if worker else 0, parts, dict(shapes))


def image_solves(pixels, cameras, workers):
    """(main parts, a worker's parts, workers) of the weight solves (``harmonic.
    mask_weights``, one a camera but the last): in workers as ``field.solve_workers``
    shares them, each holding one and the masks; else here, one at a time. The
    main process then eases the weights (``image_blend.eased``), the larger if so."""
    weights = {"mask weights": pixels * cameras * WEIGHT_BYTES_PER_CAMERA_PIXEL}
    solve = {"image solve": pixels * SOLVE_BYTES_PER_CELL}
    easing = {"weights eased": pixels * cameras * EASE_BYTES_PER_CAMERA_PIXEL}
    n = solve_workers(pixels, int(cameras) - 1, workers)
    if not n:
        return max({**weights, **solve}, easing, key=_total), {}, 0
    return max(weights, easing, key=_total), {**solve, "masks": pixels * int(cameras)}, n


def _total(parts):
    return sum(parts.values())


def traced_workers(rays, workers):
    """int, worker processes that share a trace of ``rays`` rays (0: traced in the main
    process), as ``FieldTracer._workers`` decides."""
    n = min(int(workers), int(rays) // MIN_RAYS_PER_PROCESS)
    return n if n >= 2 else 0


def share_memory(rays, max_vertices, vertices, preserved, nested=False, pickled=True):
    """Bytes a share of ``rays`` traced rays holds at its peak, in a worker or in the
    main process: the largest of its stages (see ``WORKER_BLOCK_VERTICES``): each
    camera's preserved rays held to the step limit and laid out a block at a time, the
    rest traced as streamlines, the whole share merged and pickled.

    Parameters
    ----------
    rays : int. max_vertices : int, the step limit plus one (preserved rays' layout).
    vertices : int, the longest ray's (what a share keeps of every ray).
    preserved : sequence of float in [0, 1], each camera's share of the rays (its
        mask's share of the image), in the rig's order. nested : bool, nested grids.
    pickled : bool, a worker's share, merged and pickled for the trip back; False, the
        trace in the main process: merged alone (its parts and the result, float32).

    Returns
    -------
    dict str -> float: "preserved rays laid out", "streamlines", "share returned".
    """
    held = laid = 0.0
    for i, fraction in enumerate(preserved):
        count = float(fraction) * rays * max_vertices
        if nested:
            block = NESTED_BLOCK_BYTES_PER_VERTEX
        else:
            block = CURVED_LAYOUT_BYTES_PER_VERTEX if i else PINHOLE_LAYOUT_BYTES_PER_VERTEX
        laid = max(
            laid,
            held + count * HELD_BYTES_PER_VERTEX + min(count, WORKER_BLOCK_VERTICES) * block,
        )
        held += float(fraction) * rays * vertices * HELD_BYTES_PER_VERTEX
    rest = max(0.0, 1.0 - float(sum(preserved))) * rays * vertices
    completion = NESTED_COMPLETION_BYTES_PER_VERTEX if nested else COMPLETION_BYTES_PER_VERTEX
    return {
        "preserved rays laid out": laid,
        "streamlines": held
        + rest * STREAMLINE_BYTES_PER_VERTEX
        + min(rest, WORKER_BLOCK_VERTICES) * completion,
        "share returned": rays
        * vertices
        * (RETURN_BYTES_PER_VERTEX if pickled else 2 * HELD_BYTES_PER_VERTEX),
    }


def build_memory(
    method,
    width,
    height,
    cameras,
    voxels=0,
    traced_rays=0,
    vertices=0,
    max_vertices=0,
    workers=1,
    level_voxels=0,
    preserved=(0.0, 1.0),
):
    """Peak memory of building a field, from shapes.

    The main process's peak is that of its largest stage: the fill (eq. 4), the solve
    (eq. 5), or the trace on the lattice (the kept grid and the lattice's arrays, with
    the rays traced so far, the error estimate's block and a share received from a
    worker while the rounds run, then the traced rays and the part being merged); each
    worker's, its interpreter, the grid it samples and its share of rays (the largest
    of the share's stages, ``share_memory``). On nested
    grids (``level_voxels``) the levels are filled in the workers and solved one at a
    time: the fill is a worker's stage, the solve the largest level's.

    Parameters
    ----------
    method : str, "IMAGE_BLEND", "LINEAR", "VECTOR_FIELD", "SCALAR_FIELD" or "AUTO":
        its first candidate, IMAGE_BLEND, built and measured as AUTO measures it (the
        along-ray measure, the fold count's bands: ``measure_memory``); AUTO asks the
        guard again before it goes on to SCALAR_FIELD (``Diagnostics.guard``).
    width, height : int, pixels. cameras : int.
    voxels : int, the grid's voxels (every nested level's). traced_rays : int, rays the
        lattice traces. vertices : int, vertices of the longest traced ray (what every
        kept ray holds). max_vertices : int, the trace's step limit plus one (what a
        worker lays preserved rays out on); ``vertices`` when 0.
    workers : int, worker processes available (1: none).
    level_voxels : int, the largest nested level's voxels (0: one uniform grid).
    preserved : sequence of float in [0, 1], each camera's share of the traced rays
        (its preserved pixels': laid out to the step limit; the rest are traced to
        ``vertices``), in the rig's order (``share_memory``). Default: every ray a later
        camera's, the most a share holds.

    Returns
    -------
    MemoryEstimate whose ``parts`` are those of the main process's largest stage and
    the workers'.
    """
    pixels = int(width) * int(height)
    voxels = int(voxels)
    shapes = dict(
        pixels=pixels,
        cameras=cameras,
        voxels=voxels,
        traced_rays=int(traced_rays),
        vertices=int(vertices),
    )
    image, solving, n_solve = image_solves(pixels, cameras, workers)
    along, fold, n_fold = measure_memory(width, height, cameras, workers)
    if method in ("IMAGE_BLEND", "LINEAR"):  # with one solve, the fold workers start
        n = n_solve or (n_fold if method == "IMAGE_BLEND" else 0)
        return _estimate(image, {"interpreter": WORKER_BASE_BYTES, **solving}, n, shapes)
    if method == "AUTO":  # its first candidate, IMAGE_BLEND, built then measured
        measured = {"blend weights": pixels * cameras * BLEND_BYTES_PER_CAMERA_PIXEL, **along}
        main = max(image, measured, key=_total)
        worker = max(solving, fold if n_fold else {}, key=_total)  # solves, then counts folds
        n = max(n_fold, n_solve)
        return _estimate(main, {"interpreter": WORKER_BASE_BYTES, **worker} if n else {}, n, shapes)
    grid_factor = 3 if method == "VECTOR_FIELD" else 1  # three channels of tangents
    max_vertices = max(int(max_vertices), int(vertices))
    rays = int(traced_rays)
    kept = rays * int(vertices)
    n = traced_workers(rays, workers)
    largest = int(np.ceil(LARGEST_ROUND * rays))
    share = min(MAX_RAYS_PER_SHARE, -(-largest // n)) if n else largest
    preserved = [float(np.clip(f, 0.0, 1.0)) for f in preserved]
    share_bytes = max(
        share_memory(
            share, max_vertices, int(vertices), preserved, bool(level_voxels), pickled=bool(n)
        ).values()
    )
    level = int(level_voxels) or voxels
    per_voxel = (FILL_BYTES_PER_VOXEL + cameras * FILL_BYTES_PER_CAMERA_VOXEL) * grid_factor
    fill = {"grid fill": FILL_CHUNK_BYTES + level * per_voxel}
    fills_in_workers = bool(level_voxels) and workers > 1
    held = {  # through the trace
        "grid": voxels * KEPT_BYTES_PER_VOXEL * grid_factor,
        "lattice": pixels * (LATTICE_BYTES_PER_PIXEL + cameras * CELL_TABLE_BYTES_PER_PIXEL),
    }
    stages = [
        {} if fills_in_workers else fill,
        {"grid solve": level * SOLVE_BYTES_PER_CELL * grid_factor},
        # the lattice's rounds: the rays traced so far (once, in parts), the error
        # estimate's block, a share coming in; then, the rounds done, their merge
        {
            **held,
            "traced rays": kept * RAY_BYTES_PER_VERTEX,
            "error estimate": min(largest * int(vertices), DEVIATION_BLOCK_VERTICES)
            * DEVIATION_BYTES_PER_VERTEX,
            "shares received" if n else "share of rays": (
                share * int(vertices) * RECEIVE_BYTES_PER_VERTEX if n else share_bytes
            ),
        },
        {
            **held,
            "traced rays": kept * RAY_BYTES_PER_VERTEX,
            "part merged": share * int(vertices) * RAY_BYTES_PER_VERTEX,
        },
    ]
    main = max(stages, key=lambda parts: sum(parts.values()))
    worker = {}
    if n or fills_in_workers:
        work = {"share of rays": share_bytes} if n else {}
        if fills_in_workers and sum(fill.values()) > sum(work.values()):
            work = fill
        worker = {
            "interpreter": WORKER_BASE_BYTES,
            "grid": voxels * WORKER_BYTES_PER_VOXEL * grid_factor,
            **work,
        }
        n = n or max(2, int(workers))
    return _estimate(main, worker, n, shapes)


def render_memory(width, height, samples=1, traced_rays=0, vertices=0, workers=1):
    """Peak memory of rendering a frame whose field is built, from shapes: the Render
    Result, the engine's per-pixel arrays, the field's traced rays and the sampler's
    schedules of them, and a tile in the main process or, with workers (at least
    ``RENDER_MIN_RAYS`` rays), the shared passes and each worker. Not modelled: the
    Cycles hand-off (its tables and Cycles' own memory, docs/performance.md).

    Parameters
    ----------
    width, height : int, pixels. samples : int, rays per pixel. traced_rays, vertices :
    int, the field's traced rays and their vertices (0 for methods without a lattice).
    workers : int, render worker processes (1: none).

    Returns
    -------
    MemoryEstimate
    """
    pixels = int(width) * int(height)
    n = int(workers) if workers > 1 and pixels * samples >= RENDER_MIN_RAYS else 0
    main = {
        "render result": pixels * RESULT_BYTES_PER_PIXEL,
        "engine arrays": pixels * ENGINE_BYTES_PER_PIXEL,
        "field rays": int(traced_rays) * int(vertices) * FIELD_BYTES_PER_VERTEX,
    }
    tile = min(pixels * (1 + (samples if samples > 1 else 0)), TILE_RAYS)
    worker = {}
    if n:
        main["shared passes"] = pixels * SHARED_PASS_BYTES_PER_PIXEL
        worker = {
            "render worker": RENDER_WORKER_BYTES,
            "share of pixels": pixels * RENDER_WORKER_BYTES_PER_PIXEL,
        }
    else:
        main["tile"] = tile * TILE_BYTES_PER_RAY
    shapes = dict(pixels=pixels, traced_rays=int(traced_rays), vertices=int(vertices))
    return _estimate(main, worker, n, shapes)


# Pixels above which ``edge_pixels`` counts on every s-th row and column (and scales
# the count by s): an edge's length in pixels grows with the resolution.
EDGE_COUNT_PIXELS = 1 << 22


def edge_pixels(masks):
    """int, pixels whose preserved label (camera or none) differs from a 4-neighbour's:
    where the lattice splits cells down to single pixels. masks : (N, H, W) bool.
    Counted exactly up to ``EDGE_COUNT_PIXELS`` pixels; above, on every s-th row and
    column, times s."""
    masks = np.asarray(masks, dtype=bool)
    s = max(1, int(np.ceil(np.sqrt(masks[0].size / EDGE_COUNT_PIXELS))))
    masks = masks[:, ::s, ::s]
    label = np.zeros(masks.shape[1:], dtype=np.int8)
    for i, mask in enumerate(masks):
        label[mask] = i + 1
    edge = np.zeros(label.shape, dtype=bool)
    dy = label[1:] != label[:-1]
    dx = label[:, 1:] != label[:, :-1]
    edge[1:] |= dy
    edge[:-1] |= dy
    edge[:, 1:] |= dx
    edge[:, :-1] |= dx
    return int(edge.sum()) * s


def preserved_fractions(masks):
    """list of float, each camera's share of the image's pixels: of the traced rays,
    those it lays out to the step limit. masks : (N, H, W) bool. Counted on every s-th
    row and column above ``EDGE_COUNT_PIXELS`` pixels, as ``edge_pixels``."""
    masks = np.asarray(masks, dtype=bool)
    s = max(1, int(np.ceil(np.sqrt(masks[0].size / EDGE_COUNT_PIXELS))))
    return [float(m[::s, ::s].mean()) for m in masks]


def traced_rays_of(width, height, stride, edges, accuracy_px, ratio=10.0, nested=True):
    """int, an estimate of the rays the adaptive lattice traces: the base lattice at
    ``stride``, a band around the ``edges`` pixels of preserved regions' edges, and the
    fraction of every pixel the accuracy target and, on ``nested`` grids, the rig's
    scale ``ratio`` (the first camera's near-plane width over the smallest one's)
    refine to (``TRACED_FRACTION``; ``TRACED_FRACTION_UNIFORM`` on one uniform grid);
    at most every pixel."""
    lattice = (-(-width // stride) + 1) * (-(-height // stride) + 1)
    if nested:
        depth = (1.0 + np.log10(max(ratio, 1.0))) / 2.0  # 1 at a tenfold ratio
        fraction = (
            TRACED_FRACTION
            * (0.5 / accuracy_px) ** TRACED_ACCURACY_EXPONENT
            * depth**TRACED_RATIO_EXPONENT
        )
    else:
        fraction = TRACED_FRACTION_UNIFORM * (0.5 / accuracy_px) ** TRACED_ACCURACY_EXPONENT_UNIFORM
    fraction *= (480 / max(width, 1)) ** TRACED_WIDTH_EXPONENT
    extra = EDGE_BAND_PIXELS * edges + min(fraction, 1.0) * width * height
    return int(min(width * height, lattice + extra))


def estimate_memory(rig, method, settings, workers=1):
    """Peak memory of building ``rig``'s field with ``method`` and ``settings`` (the
    core's ``methods.Settings``: accuracy_px, max_voxels, nested), from
    the shapes the build would have: the grids it would choose (``choose_grid``, or
    ``choose_levels`` on nested grids), the lattice's stride and an estimate of its
    traced rays (``traced_rays_of``), the trace's step count. Nothing large is
    allocated: the masks are read once, the grids chosen from a 17x17 pixel lattice.

    Returns
    -------
    MemoryEstimate (``build_memory``); for a traced method its ``shapes`` add the
    lattice's ``stride`` (pixels) and the trace's ``step_limit`` (steps).
    """
    w, h = rig.size
    n = len(rig.cameras)
    if method == "AUTO" and settings.steady:  # a shot's one method, built unmeasured
        shot = getattr(settings.shot, "method", None)
        method = "IMAGE_BLEND" if shot == "IMAGE_BLEND" else "SCALAR_FIELD"
    if method in ("IMAGE_BLEND", "LINEAR", "AUTO") or n < 2:
        return build_memory(method, w, h, n, workers=workers)
    choice = choose_grid(rig, settings.accuracy_px, settings.max_voxels)
    grids = [choice.grid]
    nested = settings.nested if settings.nested is not None else choice.capped
    if method in ("SCALAR_FIELD", "AUTO") and nested:
        outer = choose_grid(rig, settings.accuracy_px, 1 << 62).grid
        across = max(MIN_CELLS_ACROSS_NEAR, CELLS_ACROSS_NEAR_PER_PX / settings.accuracy_px)
        grids = list(
            choose_levels(
                rig, settings.accuracy_px, settings.max_voxels, across, outer.bounds
            ).grids
        )
    voxels = sum(g.size for g in grids)
    level = max(g.size for g in grids) if len(grids) > 1 else 0
    # the lattice's stride (``traced.lattice_stride``) and the step limit (``trace_field``)
    px = min(near_plane_width(c) / w for c in rig.cameras)
    stride = int(np.clip(grids[-1].cell / px / 2, 1, MAX_STRIDE))
    cells = step_cells(settings.accuracy_px, w)
    steps = int(sum(np.ceil(np.linalg.norm(np.array(g.shape)) / cells * 2) for g in grids)) + 8
    # at most what the step's bands at the near planes add (``field.NearPlaneStep``): the
    # trace picks their gains from its families, up to MAX_GAIN where a camera has pixels
    planes = int(np.asarray(rig.masks)[1:].reshape(n - 1, -1).any(axis=1).sum())
    steps += extra_steps([MAX_GAIN] * planes) if planes else 0
    widths = [near_plane_width(c) for c in rig.cameras]
    ratio = widths[0] / max(min(widths), 1e-30)
    edges = edge_pixels(rig.masks)
    rays = traced_rays_of(w, h, stride, edges, settings.accuracy_px, ratio, len(grids) > 1)
    of_limit = VERTICES_OF_LIMIT_NESTED if len(grids) > 1 else VERTICES_OF_LIMIT
    estimate = build_memory(
        method,
        w,
        h,
        n,
        voxels=voxels,
        traced_rays=rays,
        vertices=int(np.ceil(of_limit * (steps + 1))),
        max_vertices=steps + 1,
        workers=workers,
        level_voxels=level,
        preserved=preserved_fractions(rig.masks),
    )
    estimate.shapes.update(stride=stride, step_limit=steps)
    return estimate
