"""Viewport previews drawn with the ``gpu`` module.

- In the 3D viewport (toggle ``scene.multiscale.show_preview``): the bent rays of a
  sparse pixel grid, from camera 1's near plane to where they leave the bending
  stretch, coloured by membership (camera 1 blue ... last camera orange), the chained
  frusta of the cameras (eye to near plane, near plane to the next near plane), and
  folds among the drawn rays marked in red. Redrawn from the newest field after each
  build.
- In the Image Editor: a camera's guide (its own view) over its mask at the opacity
  ``scene.multiscale.guide_opacity``
  while the mask is shown, so the mask can be painted over the picture.

Lines are computed with numpy (``preview_lines``, a module without bpy); drawing needs a GPU
context, which background Blender lacks: there the lines are computed, nothing is
drawn, nothing fails.
"""

import bpy
import gpu
from gpu_extras.batch import batch_for_shader

from ..adapters.scene import rig_from_scene
from ..render.fields import SERVICE
from .preview_lines import FOLD_COLOUR, frustum_lines, preview_lines

# --- Blender side ------------------------------------------------------------------------


class RayPreview:
    """What the 3D viewport's ray preview draws, and the draw handlers that draw it and
    the guide under a mask; one is made in ``register()``.

    Attributes
    ----------
    lines : dict of ``preview_lines`` (or frusta only), or None when off.
    note : str, a short note for the panel ("" when the rays are shown).
    """

    def __init__(self):
        self.lines = None
        self.note = ""
        self.view_handler = None
        self.image_handler = None

    def update(self, scene, fld=None):
        """Recompute what the preview draws for ``scene`` (from ``fld``, else the newest
        field of the scene's rig in memory) and add or remove the draw handler.

        Returns a short note for the user ("" when the rays are shown)."""
        settings = scene.multiscale
        if not settings.show_preview:
            self.lines = None
            self._remove_view_handler()
            _redraw()
            return ""
        note = ""
        try:
            if fld is None:
                request = SERVICE.request(scene, step_frames=False)  # drawn: no stepping
                fld = SERVICE.cached(request, memory_only=True)
            if fld is not None:
                self.lines = preview_lines(fld, settings.preview_rays)
            else:
                rig = rig_from_scene(scene, frames=SERVICE.mask_frames)
                pos, col = frustum_lines(rig.cameras)
                self.lines = {"frusta": pos, "frustum_colours": col, "count": 0}
                note = "Compute the field to see the rays; the frusta are shown"
        except Exception as err:  # a rig that cannot build: say so, draw nothing
            self.lines = None
            note = f"No preview: {err}"
        self.note = note
        self._add_view_handler()
        _redraw()
        return note

    def forget(self):
        """After a file loads: the old file's lines go; redraw for the new one if its
        preview is on."""
        self.lines, self.note = None, ""
        scene = bpy.context.scene
        if scene is not None and hasattr(scene, "multiscale") and scene.multiscale.show_preview:
            self.update(scene)
        else:
            self._remove_view_handler()

    def start(self):
        """Add the Image Editor's guide handler (where a GPU context exists)."""
        if _gpu_available() and self.image_handler is None:
            self.image_handler = bpy.types.SpaceImageEditor.draw_handler_add(
                _draw_image_guide, (), "WINDOW", "POST_PIXEL"
            )

    def stop(self):
        """Remove every draw handler; nothing is drawn any more."""
        self._remove_view_handler()
        if self.image_handler is not None:
            bpy.types.SpaceImageEditor.draw_handler_remove(self.image_handler, "WINDOW")
            self.image_handler = None
        self.lines = None

    def _add_view_handler(self):
        if self.view_handler is None and _gpu_available():
            self.view_handler = bpy.types.SpaceView3D.draw_handler_add(
                self.draw_view3d, (), "WINDOW", "POST_VIEW"
            )

    def _remove_view_handler(self):
        if self.view_handler is not None:
            bpy.types.SpaceView3D.draw_handler_remove(self.view_handler, "WINDOW")
            self.view_handler = None

    def draw_view3d(self):
        lines = self.lines
        if not lines:
            return
        gpu.state.blend_set("ALPHA")
        gpu.state.depth_test_set("LESS_EQUAL")
        _draw_lines(lines.get("frusta"), lines.get("frustum_colours"), 1.5)
        _draw_lines(lines.get("rays"), lines.get("ray_colours"), 1.5)
        folds = lines.get("folds")
        if folds is not None and len(folds):
            shader = gpu.shader.from_builtin(
                "POINT_UNIFORM_COLOR" if _has_shader("POINT_UNIFORM_COLOR") else "UNIFORM_COLOR"
            )
            batch = batch_for_shader(shader, "POINTS", {"pos": folds.tolist()})
            gpu.state.point_size_set(8.0)
            shader.bind()
            shader.uniform_float("color", FOLD_COLOUR)
            batch.draw(shader)
        gpu.state.depth_test_set("NONE")
        gpu.state.blend_set("NONE")


# The preview of this session: made in register(), None while unregistered.
PREVIEW = None


def update(scene, fld=None):
    """``RayPreview.update`` of the registered preview ("" when there is none); the
    field service calls it when a background build has stored a field."""
    return PREVIEW.update(scene, fld) if PREVIEW is not None else ""


def note():
    """The preview's note for the panel ("" when there is none)."""
    return PREVIEW.note if PREVIEW is not None else ""


def _gpu_available():
    return not bpy.app.background


def _redraw():
    wm = getattr(bpy.context, "window_manager", None)
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type in {"VIEW_3D", "IMAGE_EDITOR"}:
                area.tag_redraw()


def _line_shader():
    try:
        return gpu.shader.from_builtin("POLYLINE_SMOOTH_COLOR"), True
    except (ValueError, SystemError):
        return gpu.shader.from_builtin("SMOOTH_COLOR"), False


def _draw_lines(pos, col, width):
    if pos is None or len(pos) == 0:
        return
    shader, poly = _line_shader()
    batch = batch_for_shader(shader, "LINES", {"pos": pos.tolist(), "color": col.tolist()})
    shader.bind()
    if poly:
        region = bpy.context.region
        shader.uniform_float("viewportSize", (region.width, region.height))
        shader.uniform_float("lineWidth", width)
    batch.draw(shader)


def _has_shader(name):
    try:
        gpu.shader.from_builtin(name)
        return True
    except (ValueError, SystemError):
        return False


# --- the guide under a mask in the Image Editor --------------------------------------------


def _guide_for(image, scene):
    for item in scene.multiscale.cameras:
        if item.mask is not None and item.mask == image:
            return item.guide
    return None


def _draw_image_guide():
    space, region = bpy.context.space_data, bpy.context.region
    scene = bpy.context.scene
    image = getattr(space, "image", None)
    if image is None or scene is None or not hasattr(scene, "multiscale"):
        return
    guide = _guide_for(image, scene)
    if guide is None or guide.size[0] == 0:
        return
    x0, y0 = region.view2d.view_to_region(0.0, 0.0, clip=False)
    x1, y1 = region.view2d.view_to_region(1.0, 1.0, clip=False)
    draw_texture(gpu.texture.from_image(guide), (x0, y0, x1, y1), scene.multiscale.guide_opacity)


def draw_texture(texture, rect, opacity=None):
    """Draw ``texture`` (GPUTexture) over the region rectangle ``rect`` (x0, y0, x1, y1,
    region pixels), alpha-blended; at ``opacity`` (0..1) where Blender has the
    IMAGE_COLOR shader, else (or with None) as it is."""
    if texture is None:
        return
    x0, y0, x1, y1 = rect
    name = "IMAGE_COLOR" if opacity is not None and _has_shader("IMAGE_COLOR") else "IMAGE"
    shader = gpu.shader.from_builtin(name)
    batch = batch_for_shader(
        shader,
        "TRI_FAN",
        {
            "pos": ((x0, y0), (x1, y0), (x1, y1), (x0, y1)),
            "texCoord": ((0, 0), (1, 0), (1, 1), (0, 1)),
        },
    )
    gpu.state.blend_set("ALPHA")
    shader.bind()
    if name == "IMAGE_COLOR":
        shader.uniform_float("color", (1.0, 1.0, 1.0, opacity))
    shader.uniform_sampler("image", texture)
    batch.draw(shader)
    gpu.state.blend_set("NONE")


@bpy.app.handlers.persistent  # kept across file loads: it is what runs after them
def _on_load(*_args):
    if PREVIEW is not None:
        PREVIEW.forget()


def register():
    global PREVIEW
    PREVIEW = RayPreview()
    PREVIEW.start()
    if _on_load not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_on_load)
    SERVICE.add_listener(update)


def unregister():
    global PREVIEW
    SERVICE.remove_listener(update)
    if _on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load)
    if PREVIEW is not None:
        PREVIEW.stop()
    PREVIEW = None
