"""The viewport's Rendered shading: the multiscale image at reduced resolution.

``view_update`` marks the picture stale after any edit; ``view_draw`` redraws it from
the cached field (a light or a material edit re-shades at once). A field that is not
cached yet is built in the background by the field service (``fields.SERVICE.start``),
which stores it and asks the viewport to redraw when it is done; meanwhile the viewport
says so. Geometry, BVH casts and shading stay on the main
thread, at a size small enough to keep the viewport responsive.
"""

import blf
import gpu
import numpy as np
from bpy_extras.view3d_utils import location_3d_to_region_2d
from gpu_extras.presets import draw_texture_2d

from . import pipeline
from .failures import failure_message
from .fields import SERVICE
from .memory import guard_memory
from .pipeline import _cast_and_shade, _rgba

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
    ix, iy = preview_pixels(frame.size, max_width)
    gy, gx = np.meshgrid(iy, ix, indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    # each shown pixel's own ray, as the render casts it (one sample at its centre)
    seg = frame.sampler.segments(gx + 0.5, gy + 0.5, gx, gy)
    hits, shaded = _cast_and_shade(frame, seg, None)
    rgba = _rgba(frame, hits, shaded)
    return rgba.reshape(len(iy), len(ix), 4).astype(np.float32)


def frame_for_view(depsgraph, view):
    """The pipeline Frame when the scene's field is cached; otherwise start building it
    in the background (the field service) and return None, ``view.message`` saying why.

    ``view`` : ViewDraw, the picture that asked (it keeps the build it waits for). A
    build whose estimated memory passes the scene's budget is not started (the picture
    says why, ``memory.guard_memory``); the picture itself, at most ``VIEW_MAX_WIDTH``
    pixels wide, is not weighed as a render.
    """
    try:
        # drawing: no stepping through the frames for a shot's layout
        request = SERVICE.request(depsgraph.scene, depsgraph=depsgraph, step_frames=False)
        if SERVICE.cached(request) is None:
            guard_off = guard_memory(depsgraph.scene, request)  # before large allocations
            view.build = SERVICE.start(request)
            view.message = "Multiscale: building the ray field..." + (
                f" ({guard_off})" if guard_off else ""
            )
            return None
        return pipeline.prepare_frame(depsgraph, step_frames=False, render=False)
    except Exception as err:  # said on the picture, as the render says it
        view.message = f"Multiscale: {failure_message(err, 'The viewport picture')}"
        return None


def camera_rect(context, scene):
    """(x, y, w, h) of the scene camera's frame in the region, in camera view; else the
    region, letterboxed to the render's aspect."""
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
    """The picture one engine instance shows in a viewport.

    stale : bool, redraw from the field at the next draw. pixels : (h, w, 4) float32,
    bottom row first, or None. message : str, shown over the picture ("" for none).
    build : render.fields.FieldBuild the picture waits for, or None.
    """

    def __init__(self):
        self.stale = True
        self.pixels = None
        self.message = ""
        self.build = None

    def update(self):
        self.stale = True

    def draw(self, engine, context, depsgraph):
        scene = depsgraph.scene
        build = self.build
        if build is not None and not build.alive():
            self.build = None
            if build.error is not None:
                self.message = f"Multiscale: {build.error}"
                self.stale = False  # nothing to draw until the scene changes
        if self.stale or self.pixels is None:
            frame = frame_for_view(depsgraph, self) if self.stale else None
            if frame is not None:
                self.pixels = np.ascontiguousarray(preview_image(frame)[::-1])
                self.stale = False
                self.message = ""
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
        if self.message:
            blf.position(0, 20, 40, 0)
            blf.size(0, 14)
            blf.color(0, 1.0, 1.0, 1.0, 1.0)
            blf.draw(0, self.message)
