"""Cycles hand-off (Blender 4.5+): Cycles shades the bent rays with the scene's own
materials, lights, world and sample count.

Our march finds, for every pixel, the straight segment that holds the first hit
(``tables.ray_tables``). Those rays, in the render camera's space, go to a float EXR
table in a temporary folder in two-plane form (``plane_rays``: where each ray crosses
one plane in front of the camera, and its slopes), so that an OSL custom camera gets a
ray from one bilinear four-channel texture lookup at the raster position Cycles asks
for; Cycles' own sub-pixel jitter then gives interpolated rays (anti-aliasing) and
Cycles renders into this engine's Render Result. A ray the two-plane table cannot hold
(one that does not head forward, or whose line meets a surface between the plane and
its origin) is marked there, and the shader reads it from origin and direction tables.

A texture lookup costs far more per camera sample than the rest of the custom camera
(about 0.4 us against nearly nothing, measured on the bpy 5.0.1 wheel: OpenImageIO's
texture system, whatever the file's layout). Where a whole block of pixels shows one
rig camera's own pinhole rays (its preserved region, the march's segments on that
camera's straight rays), the shader computes the ray from that camera's parameters
instead (``pinhole_classes``): origin and direction are affine in the raster position,
so the rays at Cycles' jittered sub-pixel positions are exact there too.

Nothing the user made is touched: the custom camera is set on the render depsgraph's
evaluated copy of the scene camera (and Cycles' device and denoiser on the evaluated
copy of the scene); Blender throws those copies away after the render, whatever
happens. The temporary folder is removed at the end, also on failure or cancel.
"""

import hashlib
import os
import shutil
import tempfile
import time
from dataclasses import dataclass

import numpy as np

from ..core import parallel
from ..core.errors import Cancelled
from ..core.geometry import dot3
from ..io.exr import ExrError, write_channels
from .pipeline import WORKERS_GIVEN_UP
from .tables import blocked_before, ray_tables

# The custom camera (camera.type = 'CUSTOM') came with Blender 4.5.
MIN_VERSION = (4, 5, 0)
# Tables are extended this many pixels past every image edge (linear extrapolation),
# so raster positions Cycles' pixel filter puts outside the image still interpolate.
PAD = 2
# Depth written where a ray hits nothing, as in the other passes (pipeline.MISS_DEPTH).
MISS_DEPTH = 1e10
# A texel of the two-plane table whose ray it cannot hold carries UNUSABLE in all four
# channels; the shader takes any interpolated channel beyond UNUSABLE_LIMIT as that mark
# (a bilinear weight is 0 or, in float32 texel coordinates, far above 1e-20).
UNUSABLE = 1e35
UNUSABLE_LIMIT = 1e15
# The two-plane table holds rays whose unit direction has at least this forward (z)
# component in the render camera's space (slopes up to 100).
MIN_FORWARD = 1e-2
# A ray moved back to the plane by less than this fraction of the scene's size (float32
# rounding of origins already on it) is not cast for what lies in between.
MOVED = 1e-6
# A pixel's ray counts as rig camera i's pinhole ray when they differ by at most this
# many of camera i's pixels (in direction, and in origin as seen from its eye): far
# below the ray simplification's 0.25 px, above the tables' own spread about camera 1's
# straight rays (up to 0.025 px in direction on the bench rig: float32 segments).
PINHOLE_TOLERANCE_PX = 0.05
# At most this many blocks in the shader's table of per-block ray sources (an int array
# compiled into the shader): 8160 blocks are 4x4 pixels at 480x270, 16x16 at 1920x1080.
MAX_BLOCKS = 8192

OSL_SOURCE = """\
// Multiscale Camera: per-pixel rays, in camera space (+Z forward).
// A block of block x block pixels whose block_class is c > 0 shows rig camera c's own
// pinhole rays: origin and direction (not unit) are affine in the raster position,
// pinhole[18 (c - 1) ...] = origin, its x and y derivatives, then the direction's.
// Elsewhere, ray_table: where each ray crosses the plane z = plane (R, G) and its
// slopes dx/dz, dy/dz (B, A). Texels marked with huge values hold no ray: there the
// origin and direction tables give it.
shader multiscale_camera(
    string ray_table = "",
    string origin_table = "",
    string direction_table = "",
    float plane = 0.0,
    int width = 1,
    int height = 1,
    int pad = 0,
    int block = @BLOCK@,
    int blocks_x = @BLOCKS_X@,
    int blocks_y = @BLOCKS_Y@,
    int block_class[@BLOCK_COUNT@] = {@BLOCK_CLASS@},
    float pinhole[@PINHOLE_COUNT@] = {@PINHOLE@},
    output point position = 0.0,
    output vector direction = 0.0,
    output color throughput = 1.0)
{
    point raster = camera_shader_raster_position();  // (0, 0) is the bottom left
    int bx = clamp((int)floor(raster[0] * width / block), 0, blocks_x - 1);
    int by = clamp((int)floor((1.0 - raster[1]) * height / block), 0, blocks_y - 1);
    int c = block_class[by * blocks_x + bx];
    if (c > 0) {
        int k = 18 * (c - 1);
        position = point(pinhole[k] + raster[0] * pinhole[k + 3] + raster[1] * pinhole[k + 6],
                         pinhole[k + 1] + raster[0] * pinhole[k + 4] + raster[1] * pinhole[k + 7],
                         pinhole[k + 2] + raster[0] * pinhole[k + 5] + raster[1] * pinhole[k + 8]);
        direction = normalize(vector(
            pinhole[k + 9] + raster[0] * pinhole[k + 12] + raster[1] * pinhole[k + 15],
            pinhole[k + 10] + raster[0] * pinhole[k + 13] + raster[1] * pinhole[k + 16],
            pinhole[k + 11] + raster[0] * pinhole[k + 14] + raster[1] * pinhole[k + 17]));
        return;
    }
    float s = (raster[0] * width + pad) / (width + 2 * pad);
    float t = 1.0 - (raster[1] * height + pad) / (height + 2 * pad);  // t = 0 is the top row
    float slope_y = 0.0;
    color r = texture(ray_table, s, t, "interp", "linear", "wrap", "clamp", "width", 0.0,
                      "alpha", slope_y);
    if (max(max(abs(r[0]), abs(r[1])), max(abs(r[2]), abs(slope_y))) < UNUSABLE_LIMIT) {
        position = point(r[0], r[1], plane);
        direction = normalize(vector(r[2], slope_y, 1.0));
        return;
    }
    color o = texture(origin_table, s, t, "interp", "linear", "wrap", "clamp", "width", 0.0);
    color d = texture(direction_table, s, t, "interp", "linear", "wrap", "clamp", "width", 0.0);
    vector dir = vector(d[0], d[1], d[2]);
    if (length(dir) == 0.0) {
        throughput = color(0.0);
        return;
    }
    position = point(o[0], o[1], o[2]);
    direction = normalize(dir);
}
""".replace("UNUSABLE_LIMIT", repr(UNUSABLE_LIMIT))


# Stage timings of the last hand-off (seconds): "march", "tables", "cycles", "passes".
LAST_SECONDS = {}
# The last hand-off's pinhole blocks: "block" (pixels per side), "share" (of the image).
LAST_BLOCKS = {}


def _cycles_module():
    try:
        import _cycles
    except ImportError:
        return None
    return _cycles


def unsupported_reason(version=None):
    """Why the hand-off cannot run in this Blender, or None when it can.

    Parameters
    ----------
    version : tuple of int, optional; ``bpy.app.version`` by default.
    """
    import bpy

    version = tuple(version or bpy.app.version)
    if version < MIN_VERSION:
        return (
            "Cycles shading needs Blender 4.5 or later (OSL custom cameras); "
            f"this is Blender {'.'.join(map(str, version))}"
        )
    cyc = _cycles_module()
    if cyc is None:
        return "Cycles shading needs Cycles, which this Blender lacks"
    if not getattr(cyc, "with_osl", True):
        return "Cycles shading needs Cycles built with OSL, which this Blender lacks"
    if "cycles" not in bpy.types.Scene.bl_rna.properties:
        return "Cycles shading needs the Cycles add-on: enable it in Preferences > Add-ons"
    return None


def shader_source(blocks):
    """``OSL_SOURCE`` with the per-block ray sources of ``blocks`` compiled in.

    Parameters
    ----------
    blocks : PinholeBlocks, or None for a shader that reads every ray from the tables.

    Returns
    -------
    str, OSL source.
    """
    if blocks is None:
        blocks = PinholeBlocks(1, np.zeros((1, 1), dtype=np.int32), np.zeros((1, 18)))
    rows, cols = blocks.classes.shape
    # float32 literals with 9 significant digits read back to the same float32
    pinhole = ", ".join(f"{v:.9g}" for v in blocks.pinhole.astype(np.float32).ravel())
    values = {
        "@BLOCK@": str(blocks.size),
        "@BLOCKS_X@": str(cols),
        "@BLOCKS_Y@": str(rows),
        "@BLOCK_COUNT@": str(rows * cols),
        "@BLOCK_CLASS@": ",".join(map(str, blocks.classes.ravel().tolist())),
        "@PINHOLE_COUNT@": str(blocks.pinhole.size),
        "@PINHOLE@": pinhole,
    }
    source = OSL_SOURCE
    for token, value in values.items():
        source = source.replace(token, value)
    return source


def compile_shader(folder, blocks=None):
    """Compile ``shader_source(blocks)`` with Cycles' compiler.

    Returns
    -------
    str, the OSO bytecode.

    Raises
    ------
    RuntimeError: the compiler failed (its messages go to the console).
    """
    source = os.path.join(folder, "multiscale_camera.osl")
    target = os.path.join(folder, "multiscale_camera.oso")
    with open(source, "w", encoding="utf-8") as out:
        out.write(shader_source(blocks))
    if not _cycles_module().osl_compile(source, target):
        raise RuntimeError("the custom camera's OSL shader did not compile (see the console)")
    with open(target, encoding="utf-8") as oso:
        return oso.read()


def camera_space(points, vectors, matrix_world):
    """World -> OSL camera space (+Z forward, +Y up, +X right).

    Cycles uses the camera object's matrix without its scale, with Z flipped (Blender
    cameras look down -Z).

    Parameters
    ----------
    points, vectors : (..., 3) float64 world positions and directions.
    matrix_world : (4, 4) float64, the camera object's world matrix.

    Returns
    -------
    (..., 3) float64 positions, (..., 3) float64 directions in camera space.
    """
    m = np.asarray(matrix_world, dtype=np.float64)
    rot = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    flip = np.array([1.0, 1.0, -1.0])
    p = (np.asarray(points) - m[:3, 3]) @ rot * flip
    v = np.asarray(vectors) @ rot * flip
    return p, v


def pad_edges(a, pad):
    """Extend (H, W, C) by ``pad`` pixels on every side by linear extrapolation from the
    two outermost rows and columns (one row or column: repeated).

    Returns
    -------
    (H + 2 pad, W + 2 pad, C) array of ``a``'s dtype.
    """
    out = a
    for axis in (0, 1):
        n = out.shape[axis]
        first = np.take(out, [0], axis=axis)
        last = np.take(out, [n - 1], axis=axis)
        if n > 1:
            step0 = first - np.take(out, [1], axis=axis)
            step1 = last - np.take(out, [n - 2], axis=axis)
        else:
            step0 = step1 = np.zeros_like(first)
        before = [first + step0 * (pad - i) for i in range(pad)]
        after = [last + step1 * (i + 1) for i in range(pad)]
        out = np.concatenate(before + [out] + after, axis=axis)
    return out


def plane_rays(origin, direction, min_forward=MIN_FORWARD):
    """Rays in two-plane form: where each crosses the plane z = depth, and its slopes.

    A ray is then four numbers that interpolate bilinearly between pixels, and exactly
    so across a pinhole camera's pixels (both are affine in the pixel position there).

    Parameters
    ----------
    origin, direction : (..., 3) float64, camera space (+Z forward), world units;
        direction unit (zero for a pixel without a ray).
    min_forward : float, the least z component of a direction the table holds.

    Returns
    -------
    depth : float, world units: the plane's z, the nearest origin of the rays it holds.
    table : (..., 4) float64: x and y (world units) where the ray crosses z = depth, and
        its slopes dx/dz, dy/dz; ``UNUSABLE`` in all four for a ray heading less than
        ``min_forward`` forward.
    back : (...) float64 >= 0, world units: how far before its origin each ray crosses
        the plane, along the ray (0 where the table does not hold it).
    """
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    dz = direction[..., 2]
    held = dz >= min_forward
    depth = float(origin[..., 2][held].min()) if held.any() else 0.0
    dz = np.where(held, dz, 1.0)
    back = np.where(held, (origin[..., 2] - depth) / dz, 0.0)
    table = np.empty((*origin.shape[:-1], 4))
    table[..., :2] = origin[..., :2] - back[..., None] * direction[..., :2]
    table[..., 2:] = direction[..., :2] / dz[..., None]
    table[~held] = UNUSABLE
    return depth, table, back


@dataclass(frozen=True)
class PinholeBlocks:
    """Which blocks of pixels show a rig camera's own pinhole rays, and those rays.

    size : int, pixels per block side; blocks run from the top-left corner.
    classes : (rows, cols) int32: 0 where the tables give the rays, c > 0 where every
        pixel of the block shows rig camera c's pinhole ray (camera numbers from 1).
    pinhole : (N, 18) float64, per rig camera, in the render camera's space (+Z forward,
        world units) as affine functions of Cycles' raster position (rx, ry) in [0, 1],
        (0, 0) the bottom left: origin (on the camera's near plane) at (0, 0), its
        derivatives along rx and ry, then the same for the direction (not unit: its
        component along that camera's view axis is 1).
    """

    size: int
    classes: np.ndarray
    pinhole: np.ndarray


def pinhole_rays(camera, px, py):
    """A rig camera's own rays through image points, in world space.

    Parameters
    ----------
    camera : core.camera.PinholeCamera. px, py : arrays of one shape S, that camera's
        pixel coordinates (top-left origin, centres at + 0.5).

    Returns
    -------
    origin : (*S, 3) float64, world units, on the camera's near plane.
    direction : (*S, 3) float64, its component along the camera's view axis is 1.
    """
    unit = camera.directions(px, py)
    origin = camera.near_points(unit)
    return origin, unit / (unit @ camera.forward)[..., None]


def pinhole_affine(camera, matrix_world):
    """(18,) float64: ``camera``'s rays in the render camera's space as affine functions
    of the raster position (``PinholeBlocks.pinhole``'s layout)."""
    w, h = camera.width, camera.height
    # raster (0, 0), (1, 0), (0, 1) in pixels, top-left origin
    px = np.array([0.0, w, 0.0])
    py = np.array([h, h, 0.0])
    origin, direction = pinhole_rays(camera, px, py)
    o, d = camera_space(origin, direction, matrix_world)
    return np.concatenate([o[0], o[1] - o[0], o[2] - o[0], d[0], d[1] - d[0], d[2] - d[0]])


def pinhole_classes(tables, cameras, tolerance_px=PINHOLE_TOLERANCE_PX):
    """Per pixel, the rig camera whose own pinhole ray the pixel's first-hit ray is.

    A pixel's ray (``tables``' origin and direction) is camera i's pinhole ray through
    that pixel's centre when their directions differ by at most ``tolerance_px`` of
    camera i's pixels, the table's origin lies that close to the pinhole ray's line (as
    seen from camera i's eye), and not before its start on camera i's near plane (the
    march found nothing between the two).

    Parameters
    ----------
    tables : tables.RayTables of an H x W image. cameras : sequence of PinholeCamera,
        the rig's, at that image size.
    tolerance_px : float, pixels of each camera.

    Returns
    -------
    (H, W) int32: 0 for none, i + 1 for the rig's camera i.
    """
    height, width = tables.hit.shape
    px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    classes = np.zeros((height, width), dtype=np.int32)
    length = np.sqrt(dot3(tables.direction, tables.direction))
    for i, camera in enumerate(cameras):
        origin, direction = pinhole_rays(camera, px, py)
        direction /= np.sqrt(dot3(direction, direction))[..., None]
        # the camera's pixel, as an angle at unit distance (its narrowest, off axis)
        xmin, xmax, ymin, ymax = camera.view_plane()
        pixel = min((xmax - xmin) / width, (ymax - ymin) / height)
        pixel /= 1.0 + max(xmin * xmin, xmax * xmax) + max(ymin * ymin, ymax * ymax)
        limit = tolerance_px * pixel
        rel = tables.origin - origin
        along = dot3(rel, direction)
        rel -= along[..., None] * direction
        off = np.sqrt(dot3(rel, rel))
        eye = tables.origin - camera.eye
        seen_from = np.sqrt(dot3(eye, eye))
        bend = tables.direction - direction
        turn = np.sqrt(dot3(bend, bend))
        same = (
            (length > 0)
            & (turn <= limit)
            & (off <= limit * seen_from)
            & (along >= -limit * camera.clip_start)
            & (classes == 0)
        )
        classes[same] = i + 1
    return classes


def pinhole_blocks(classes, cameras, matrix_world, max_blocks=MAX_BLOCKS):
    """Square blocks of pixels that all show one rig camera's pinhole rays.

    Parameters
    ----------
    classes : (H, W) int32, ``pinhole_classes``. cameras : the rig's PinholeCameras.
    matrix_world : (4, 4) float64, the render camera's world matrix.
    max_blocks : int, the most blocks the image may be cut into.

    Returns
    -------
    PinholeBlocks, with the smallest block size that gives at most ``max_blocks``.
    """
    height, width = classes.shape
    size = max(1, int(np.ceil(np.sqrt(width * height / max_blocks))))
    while -(-width // size) * -(-height // size) > max_blocks:
        size += 1
    rows, cols = -(-height // size), -(-width // size)
    padded = np.pad(classes, ((0, rows * size - height), (0, cols * size - width)), mode="edge")
    cells = padded.reshape(rows, size, cols, size)
    low, high = cells.min(axis=(1, 3)), cells.max(axis=(1, 3))
    blocks = np.where(low == high, low, 0).astype(np.int32)
    pinhole = np.stack([pinhole_affine(cam, matrix_world) for cam in cameras])
    return PinholeBlocks(size, blocks, pinhole)


def write_tables(folder, tables, matrix_world, frame, should_stop=None):
    """Write the hand-off's tables (camera space, padded) as uncompressed float EXRs.

    The two-plane table (RGBA: ``plane_rays``) holds every ray that heads forward and
    whose line meets no surface between the plane and the ray's origin (cast on
    ``frame``'s tree); the others are marked there, and only then are the origin and
    direction tables (RGB) written too.

    Returns
    -------
    dict of the shader's parameters: "ray_table", "origin_table", "direction_table"
    (str paths, "" when not written), "plane" (float, world units); and "back" (float,
    world units), the longest stretch a ray was moved back to the plane.
    """
    origin, direction = camera_space(tables.origin, tables.direction, matrix_world)
    depth, table, back = plane_rays(origin, direction)
    moved = back > MOVED * frame.scale
    blocked = blocked_before(
        frame, tables.origin[moved], tables.direction[moved], back[moved], should_stop
    )
    held = np.ones(back.shape, dtype=bool)
    held[moved] = ~blocked
    held &= table[..., 0] != UNUSABLE
    table[~held] = UNUSABLE
    params = {"plane": depth, "origin_table": "", "direction_table": "", "back": 0.0}
    if held.any():
        params["back"] = float(back[held].max())
    padded = pad_edges(table, PAD)
    path = os.path.join(folder, "rays.exr")
    write_channels(path, {c: padded[..., i] for i, c in enumerate("RGBA")}, compress=False)
    params["ray_table"] = path
    if not held.all():
        for name, values in (("origin", origin), ("direction", direction)):
            padded = pad_edges(values, PAD)
            path = os.path.join(folder, f"{name}.exr")
            write_channels(path, {c: padded[..., i] for i, c in enumerate("RGB")}, compress=False)
            params[f"{name}_table"] = path
    return params


def index_pass_name(version=None):
    """Cycles' name of the object index pass: "Object Index" from Blender 5, else "IndexOB"."""
    import bpy

    return "Object Index" if tuple(version or bpy.app.version) >= (5, 0, 0) else "IndexOB"


def _set_custom_camera(cam, bytecode, params, reach):
    """Turn the evaluated camera datablock ``cam`` into our custom camera."""
    cam.type = "CUSTOM"
    cam.custom_mode = "INTERNAL"
    cam.custom_bytecode = bytecode
    cam.custom_bytecode_hash = hashlib.sha1(bytecode.encode()).hexdigest()
    # rays start on the tables' origins: nothing may clip them
    cam.clip_start = 1e-6
    cam.clip_end = max(cam.clip_end, reach)
    props = cam.cycles_custom
    for key, value in params.items():
        props[key] = value


def render(engine, depsgraph, frame):
    """Render ``frame`` with Cycles into ``engine``'s result.

    Returns
    -------
    bool : True when the hand-off ran (or was cancelled / failed and said so), False
    when it cannot run here (a warning says why; the caller renders with Solid).
    """
    import bpy

    reason = unsupported_reason()
    if reason is not None:
        engine.report({"WARNING"}, f"Multiscale: {reason}; rendering with Solid shading")
        return False
    camera = engine.camera_override or depsgraph.scene_eval.camera
    if camera is None or camera.type != "CAMERA":
        engine.fail("Multiscale: Cycles shading needs a scene camera")
        return True
    width, height = frame.size
    folder = tempfile.mkdtemp(prefix="multiscale-cycles-")
    LAST_SECONDS.clear()
    LAST_BLOCKS.clear()
    clock = [time.perf_counter()]

    def lap(stage):
        now = time.perf_counter()
        LAST_SECONDS[stage] = now - clock[0]
        clock[0] = now

    try:
        engine.update_stats("", "Multiscale: marching rays for Cycles")
        given_up = parallel.given_up()
        try:
            tables = ray_tables(
                frame, engine.test_break, progress=lambda f: engine.update_progress(0.2 * f)
            )
        except Cancelled:
            return True
        if parallel.given_up() > given_up:
            engine.report({"WARNING"}, f"Multiscale: {WORKERS_GIVEN_UP}")
        lap("march")
        if engine.test_break():
            return True
        try:
            params = write_tables(folder, tables, camera.matrix_world, frame, engine.test_break)
        except Cancelled:
            return True
        cameras = frame.rig.cameras
        blocks = pinhole_blocks(
            pinhole_classes(tables, cameras), cameras, np.asarray(camera.matrix_world)
        )
        LAST_BLOCKS.update(block=blocks.size, share=float(np.mean(blocks.classes > 0)))
        bytecode = compile_shader(folder, blocks)
        finite = np.where(tables.hit, tables.distance, 0.0)
        reach = (
            float(finite.max(initial=0.0))
            + params.pop("back")
            + float(frame.field.rig.cameras[-1].clip_end)
        )
        params.update(width=width, height=height, pad=PAD)
        _set_custom_camera(camera.data, bytecode, params, max(reach, frame.scale) * 4.0)
        settings = depsgraph.scene_eval.cycles
        settings.device = "CPU"  # OSL custom cameras run on the CPU (and OptiX) only
        settings.use_denoising = False
        index_name = index_pass_name()
        for name, channels, chan_id in (
            ("Depth", 1, "Z"),
            ("Normal", 3, "XYZ"),
            (index_name, 1, "X"),
            ("Membership", 1, "X"),
        ):
            engine.add_pass(name, channels, chan_id)
        lap("tables")
        engine.update_stats("", "Multiscale: Cycles")
        _run_cycles(engine, depsgraph, bpy.data)
        lap("cycles")
        if engine.test_break():
            return True
        _write_own_passes(engine, tables, index_name, _region(depsgraph.scene.render, *frame.size))
        lap("passes")
        print(
            f"Multiscale (Cycles): {width}x{height}, {tables.casts} segment casts, "
            f"{LAST_BLOCKS['share']:.0%} in pinhole blocks of {blocks.size} px, "
            + ", ".join(f"{k} {v:.2f} s" for k, v in LAST_SECONDS.items())
        )
        return True
    except (ExrError, RuntimeError, OSError) as err:
        engine.fail(f"Multiscale: Cycles hand-off failed: {err}")
        return True
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _run_cycles(engine, depsgraph, data):
    """Run a Cycles session on ``engine`` as Blender drives Cycles' own RenderEngine:
    update (create, reset), render, render_frame_finish (which writes the tiles Cycles
    kept on disk when the image is larger than its tile size), free."""
    from cycles import engine as cycles_engine

    cycles_engine.create(engine, data)
    try:
        cycles_engine.reset(engine, data, depsgraph)
        cycles_engine.render(engine, depsgraph)
        cycles_engine.render_frame_finish(engine)
    finally:
        cycles_engine.free(engine)


def _region(render, width, height):
    """The rendered region (x, y, w, h) in pixels, y from the bottom: the render border
    when one is used (as Blender rounds it), else the whole image."""
    if not render.use_border:
        return 0, 0, width, height
    x0, x1 = int(render.border_min_x * width), int(render.border_max_x * width)
    y0, y1 = int(render.border_min_y * height), int(render.border_max_y * height)
    return x0, y0, x1 - x0, y1 - y0


def _write_own_passes(engine, tables, index_name, region):
    """Depth (arc length along the bent ray) and Membership come from our tables; the
    other passes stay as Cycles wrote them (IndexOB copies Cycles' object index).

    region : (x, y, w, h) pixels of the result, y from the bottom (``_region``).
    """
    result = engine.get_result()
    layer = result.layers[0]
    x0, y0, width, rows = region
    data = {}
    for render_pass in layer.passes:
        buf = np.empty(width * rows * render_pass.channels, dtype=np.float32)
        try:
            render_pass.rect.foreach_get(buf)
        except (TypeError, ValueError, RuntimeError):
            engine.report(
                {"WARNING"}, "Multiscale: Depth and Membership are Cycles' own in this render"
            )
            return
        data[render_pass.name] = buf
    # our tables are top-first; the result's rows run bottom-up
    window = (slice(y0, y0 + rows), slice(x0, x0 + width))
    depth = np.where(tables.hit, tables.depth, MISS_DEPTH).astype(np.float32)[::-1]
    data["Depth"] = np.ascontiguousarray(depth[window]).ravel()
    data["Membership"] = np.ascontiguousarray(tables.membership[::-1][window]).ravel()
    for name in ("IndexOB", "Object Index"):
        if name in data and name != index_name and index_name in data:
            data[name] = data[index_name]
    out = engine.begin_result(0, 0, width, rows)
    for render_pass in out.layers[0].passes:
        if render_pass.name in data:
            render_pass.rect.foreach_set(data[render_pass.name])
    engine.end_result(out)
