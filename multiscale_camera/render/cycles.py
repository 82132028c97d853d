"""Cycles hand-off (Blender 4.5+): Cycles shades the bent rays with the scene's own
materials, lights, world and sample count.

Our march finds, for every pixel, the straight segment that holds the first hit
(``tables.ray_tables``). Those rays, in the render camera's space, go to a float EXR
table in a temporary folder in two-plane form (``cycles_rays.plane_rays``: where each
ray crosses one plane in front of the camera, and its slopes), so that an OSL custom
camera (``cycles_shader``) gets a ray from one bilinear four-channel texture lookup at
the raster position Cycles asks for; Cycles' own sub-pixel jitter then gives
interpolated rays (anti-aliasing) and Cycles renders into this engine's Render Result.
A ray the two-plane table cannot hold (one that does not head forward, or whose line
meets a surface between the plane and its origin) is marked there, and the shader
reads it from origin and direction tables.

A texture lookup costs far more per camera sample than the rest of the custom camera
(about 0.4 us against nearly nothing, measured on the bpy 5.0.1 wheel: OpenImageIO's
texture system, whatever the file's layout). Where a whole block of pixels shows one
rig camera's own pinhole rays (its preserved region, the march's segments on that
camera's straight rays), the shader computes the ray from that camera's parameters
instead (``cycles_rays.pinhole_classes``): origin and direction are affine in the
raster position, so the rays at Cycles' jittered sub-pixel positions are exact there
too.

Nothing the user made is touched: the custom camera is set on the render depsgraph's
evaluated copy of the scene camera (and Cycles' device and denoiser on the evaluated
copy of the scene); Blender throws those copies away after the render, whatever
happens. The temporary folder is removed at the end, also on failure or cancel.
"""

import hashlib
import shutil
import tempfile
import time
from dataclasses import dataclass, replace

import bpy
import numpy as np

from ..core.errors import Cancelled
from ..core.runtime import gave_up, runtime
from ..io.exr import ExrError
from .cycles_rays import PAD, pinhole_blocks, pinhole_classes, write_tables
from .cycles_shader import compile_shader, cycles_module
from .pipeline import WORKERS_GIVEN_UP
from .tables import ray_tables

# The custom camera (camera.type = 'CUSTOM') came with Blender 4.5.
MIN_VERSION = (4, 5, 0)
# Depth written where a ray hits nothing, as in the other passes (pipeline.MISS_DEPTH).
MISS_DEPTH = 1e10
# Cycles polls Blender's break flag (Esc, Ctrl-C) between its batches of samples, and
# schedules batches of up to 30 s of work headless (`blender -b`), up to 2 s in the
# first 10 s of a render in the window and up to 15 s after (Cycles'
# render_scheduler.cpp): a batch never spans more than a tile, so the hand-off renders
# in tiles of at most this many pixel samples (about 0.4 s a tile measured on the
# two-camera test scene with 2 cores shared, docs/performance.md), at least ``MIN_TILE``
# px a side (Cycles' own least tile size), in the window as headless.
TILE_PIXEL_SAMPLES = 1 << 17
MIN_TILE = 8


@dataclass(frozen=True)
class HandoffReport:
    """What one Cycles hand-off did: its stages' wall-clock seconds and its pinhole blocks.

    A stage the hand-off did not finish (cancelled or failed before its end) is None,
    and so are the block figures before the blocks were made.

    march : float or None, seconds marching the rays into tables (``tables.ray_tables``).
    tables : float or None, seconds writing the tables, finding the pinhole blocks,
        compiling the shader and setting up the custom camera.
    cycles : float or None, seconds of Cycles' own render.
    passes : float or None, seconds writing Depth and Membership into the result.
    block : int or None, pixels per side of the pinhole blocks.
    share : float or None, in [0, 1]: the share of the image's blocks that show a rig
        camera's own pinhole rays (``cycles_rays.PinholeBlocks``).
    """

    march: float | None = None
    tables: float | None = None
    cycles: float | None = None
    passes: float | None = None
    block: int | None = None
    share: float | None = None

    def seconds(self):
        """dict str -> float: the finished stages' seconds, in the order they ran."""
        stages = {
            "march": self.march,
            "tables": self.tables,
            "cycles": self.cycles,
            "passes": self.passes,
        }
        return {stage: s for stage, s in stages.items() if s is not None}


def unsupported_reason(version=None):
    """Why the hand-off cannot run in this Blender, or None when it can.

    Parameters
    ----------
    version : tuple of int, optional; ``bpy.app.version`` by default.
    """
    version = tuple(version or bpy.app.version)
    if version < MIN_VERSION:
        return (
            "Cycles shading needs Blender 4.5 or later (OSL custom cameras); "
            f"this is Blender {'.'.join(map(str, version))}"
        )
    cyc = cycles_module()
    if cyc is None:
        return "Cycles shading needs Cycles, which this Blender lacks"
    if not getattr(cyc, "with_osl", True):
        return "Cycles shading needs Cycles built with OSL, which this Blender lacks"
    if "cycles" not in bpy.types.Scene.bl_rna.properties:
        return "Cycles shading needs the Cycles add-on: enable it in Preferences > Add-ons"
    return None


def cancel_tile(samples, tile_size=None):
    """int, pixels a side of the tiles the hand-off renders in: at most
    ``TILE_PIXEL_SAMPLES`` pixel samples a tile for ``samples`` samples a pixel, never
    below ``MIN_TILE`` nor above the scene's own ``tile_size`` (None: no tiles)."""
    tile = max(MIN_TILE, int(np.sqrt(TILE_PIXEL_SAMPLES / max(int(samples), 1))))
    return min(tile, int(tile_size)) if tile_size else tile


def index_pass_name(version=None):
    """Cycles' name of the object index pass: "Object Index" from Blender 5, else "IndexOB"."""
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
    HandoffReport when the hand-off ran (or was cancelled / failed and said so), None
    when it cannot run here (a warning says why; the caller renders with Solid).
    """
    reason = unsupported_reason()
    if reason is not None:
        engine.report({"WARNING"}, f"Multiscale: {reason}; rendering with Solid shading")
        return None
    report = HandoffReport()
    # Esc, or Ctrl-C headless (the engine's ``should_stop``: its SIGINT handler replaces
    # Blender's, except during Cycles' own render)
    stop = engine.should_stop
    camera = engine.camera_override or depsgraph.scene_eval.camera
    if camera is None or camera.type != "CAMERA":
        engine.fail("Multiscale: Cycles shading needs a scene camera")
        return report
    width, height = frame.size
    folder = tempfile.mkdtemp(prefix="multiscale-cycles-")
    clock = time.perf_counter()

    def lap(stage):
        nonlocal report, clock
        now = time.perf_counter()
        report = replace(report, **{stage: now - clock})
        clock = now

    try:
        engine.update_stats("", "Multiscale: marching rays for Cycles")
        try:
            with runtime().journal() as runs:  # what the march's workers did
                tables = ray_tables(frame, stop, progress=lambda f: engine.update_progress(0.2 * f))
        except Cancelled:
            return report
        if gave_up(runs):
            engine.report({"WARNING"}, f"Multiscale: {WORKERS_GIVEN_UP}")
        lap("march")
        if stop():
            return report
        try:
            params = write_tables(folder, tables, camera.matrix_world, frame, stop)
        except Cancelled:
            return report
        cameras = frame.rig.cameras
        blocks = pinhole_blocks(
            pinhole_classes(tables, cameras), cameras, np.asarray(camera.matrix_world)
        )
        report = replace(report, block=blocks.size, share=float(np.mean(blocks.classes > 0)))
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
        # Esc and Ctrl-C heard within a tile (``TILE_PIXEL_SAMPLES``)
        tile = cancel_tile(settings.samples, settings.tile_size if settings.use_auto_tile else None)
        settings.use_auto_tile, settings.tile_size = True, tile
        index_name = index_pass_name()
        for name, channels, chan_id in (
            ("Depth", 1, "Z"),
            ("Normal", 3, "XYZ"),
            (index_name, 1, "X"),
            ("Membership", 1, "X"),
        ):
            engine.add_pass(name, channels, chan_id)
        lap("tables")
        if stop():  # never start Cycles' own stage once stopped
            return report
        engine.update_stats("", "Multiscale: Cycles")
        # Cycles polls Blender's break flag (Esc, or Ctrl-C headless through Blender's
        # own handler) and runs no Python until it ends: Ctrl-C goes to Blender for it
        with engine.ctrl_c_to_blender():
            _run_cycles(engine, depsgraph, bpy.data)
        lap("cycles")
        if stop():
            return report
        _write_own_passes(engine, tables, index_name, _region(depsgraph.scene.render, *frame.size))
        lap("passes")
        print(
            f"Multiscale (Cycles): {width}x{height}, {tables.casts} segment casts, "
            f"{report.share:.0%} in pinhole blocks of {blocks.size} px, "
            + ", ".join(f"{k} {v:.2f} s" for k, v in report.seconds().items())
        )
        return report
    except (ExrError, RuntimeError, OSError) as err:
        engine.fail(f"Multiscale: Cycles hand-off failed: {err}")
        return report
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _run_cycles(engine, depsgraph, data):
    """Run a Cycles session on ``engine`` as Blender drives Cycles' own RenderEngine:
    update (create, reset), render, render_frame_finish (which writes the tiles Cycles
    kept on disk when the image is larger than its tile size), free."""
    # here only: Cycles' add-on is optional, and present once ``unsupported_reason`` said so
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
