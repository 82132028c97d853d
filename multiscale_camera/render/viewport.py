"""The viewport's Rendered shading: the multiscale image at reduced resolution.

``view_update`` marks the picture stale after any edit; ``view_draw`` redraws it from
the cached field (a light or a material edit re-shades at once). A field that is not
cached yet is built on a worker thread (numpy only, no bpy), polled from the main
thread by a ``bpy.app.timers`` callback that stores it and asks the viewport to redraw;
meanwhile the viewport says so. Geometry, BVH casts and shading stay on the main
thread, at a size small enough to keep the viewport responsive.
"""

import threading

import numpy as np

from ..core.errors import Cancelled, RigError, SolverDidNotConverge

# The viewport picture is at most this many pixels wide: about 37k rays at 16:9, under a
# second of casts per redraw.
VIEW_MAX_WIDTH = 256


def preview_pixels(size, max_width=VIEW_MAX_WIDTH):
    """Pixels of the render (width, height) that the viewport picture samples.

    Returns
    -------
    ix : (w,) int, iy : (h,) int, the render columns and rows (centres of equal blocks).
    """
    width, height = size
    w = min(width, max_width)
    h = max(1, round(height * w / width))
    ix = ((np.arange(w) + 0.5) * width / w).astype(int).clip(0, width - 1)
    iy = ((np.arange(h) + 0.5) * height / h).astype(int).clip(0, height - 1)
    return ix, iy


def preview_image(frame, max_width=VIEW_MAX_WIDTH):
    """The multiscale image of ``frame`` (pipeline.Frame) at reduced size.

    Returns
    -------
    (h, w, 4) float32 linear RGBA, row 0 at the top: pixel (j, i) is the render's pixel
    (iy[j], ix[i]) of ``preview_pixels``.
    """
    from .pipeline import _cast_and_shade, _rgba

    ix, iy = preview_pixels(frame.size, max_width)
    gy, gx = np.meshgrid(iy, ix, indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    # each shown pixel's own ray, as the render casts it (one sample at its centre)
    seg = frame.sampler.segments(gx + 0.5, gy + 0.5, gx, gy)
    hits, shaded = _cast_and_shade(frame, seg, None)
    rgba = _rgba(frame, hits, shaded)
    return rgba.reshape(len(iy), len(ix), 4).astype(np.float32)


class _Build:
    """A field build on a worker thread for the viewport (one at a time)."""

    def __init__(self, key, rig, method, settings):
        self.key, self.rig, self.method, self.settings = key, rig, method, settings
        self.field = None
        self.error = None
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        from ..core.methods import prepare

        try:
            self.field = prepare(self.rig, self.method, self.settings, self.stop.is_set)
        except Cancelled:
            pass
        except Exception as err:  # shown in the viewport by the main thread
            self.error = err


STATE = {"build": None, "message": ""}


def _poll_build():
    """Timer callback (main thread): store a finished build, redraw the viewports."""
    import bpy

    from ..io import cache

    job = STATE["build"]
    if job is None:
        return None
    if job.thread.is_alive():
        return 0.25
    STATE["build"] = None
    if job.field is not None:
        job.field.notices = list(job.rig.notices)
        cache.CACHE.put(job.key, job.field)
        STATE["message"] = ""
        scene = bpy.context.scene
        if scene is not None and scene.multiscale.show_preview:
            from ..ui import preview  # the ray preview follows every build

            preview.update(scene, job.field)
    elif job.error is not None:
        STATE["message"] = f"Multiscale: {job.error}"
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()
    return None


def frame_for_view(depsgraph):
    """The pipeline Frame when the scene's field is cached; otherwise start building it
    in the background and return None (``STATE["message"]`` says why)."""
    import bpy

    from ..adapters.scene import field_settings, rig_from_scene
    from ..core.methods import field_key
    from ..io import cache
    from . import pipeline

    scene = depsgraph.scene
    s = scene.multiscale
    try:
        rig = rig_from_scene(scene)
    except RigError as err:
        STATE["message"] = f"Multiscale: {err}"
        return None
    settings = field_settings(scene)
    key = field_key(rig, s.method, settings)
    _ = cache.CACHE.folder  # resolved on the main thread
    if cache.CACHE.get(key, rig) is None:
        job = STATE["build"]
        if job is not None and job.key != key:
            job.stop.set()  # an older rig: its field is no longer wanted
            job = None
        if job is None:
            job = _Build(key, rig, s.method, settings)
            STATE["build"] = job
            job.thread.start()
            bpy.app.timers.register(_poll_build, first_interval=0.25)
        STATE["message"] = "Multiscale: building the ray field..."
        return None
    try:
        return pipeline.prepare_frame(depsgraph)
    except (RigError, SolverDidNotConverge) as err:
        STATE["message"] = f"Multiscale: {err}"
        return None


def camera_rect(context, scene):
    """(x, y, w, h) of the scene camera's frame in the region, in camera view; else the
    region, letterboxed to the render's aspect."""
    from bpy_extras.view3d_utils import location_3d_to_region_2d

    region, rv3d = context.region, context.region_data
    r = scene.render
    aspect = (r.resolution_x * r.pixel_aspect_x) / max(r.resolution_y * r.pixel_aspect_y, 1e-9)
    cam = scene.camera
    if rv3d is not None and rv3d.view_perspective == "CAMERA" and cam is not None:
        frame = [cam.matrix_world @ v for v in cam.data.view_frame(scene=scene)]
        pts = [location_3d_to_region_2d(region, rv3d, p) for p in frame]
        if all(p is not None for p in pts):
            xs, ys = [p.x for p in pts], [p.y for p in pts]
            return min(xs), min(ys), max(xs) - min(xs), max(ys) - min(ys)
    w, h = region.width, region.height
    if w / max(h, 1) > aspect:
        return (w - h * aspect) / 2, 0, h * aspect, h
    return 0, (h - w / aspect) / 2, w, w / aspect


class ViewDraw:
    """The picture one engine instance shows in a viewport."""

    def __init__(self):
        self.stale = True
        self.pixels = None  # (h, w, 4) float32, bottom row first, or None
        self.message = ""

    def update(self):
        self.stale = True

    def draw(self, engine, context, depsgraph):
        import blf
        import gpu
        from gpu_extras.presets import draw_texture_2d

        scene = depsgraph.scene
        if self.stale or self.pixels is None:
            frame = frame_for_view(depsgraph)
            if frame is not None:
                self.pixels = np.ascontiguousarray(preview_image(frame)[::-1])
                self.stale = False
                STATE["message"] = ""
        if self.pixels is not None:
            # the texture lives only while the viewport draws: a GPU texture freed later,
            # outside a GPU context (when the engine goes), crashes Blender
            h, w = self.pixels.shape[:2]
            buf = gpu.types.Buffer("FLOAT", w * h * 4, self.pixels.ravel().tolist())
            texture = gpu.types.GPUTexture((w, h), format="RGBA16F", data=buf)
            x, y, rw, rh = camera_rect(context, scene)
            gpu.state.blend_set("ALPHA_PREMULT")
            engine.bind_display_space_shader(scene)
            draw_texture_2d(texture, (x, y), rw, rh)
            engine.unbind_display_space_shader()
            gpu.state.blend_set("NONE")
            del texture, buf
        if STATE["message"]:
            blf.position(0, 20, 40, 0)
            blf.size(0, 14)
            blf.color(0, 1.0, 1.0, 1.0, 1.0)
            blf.draw(0, STATE["message"])
            if STATE["build"] is not None:
                self.stale = True  # draw again once the field is there
