"""Operators for masks: a new mask with a picture of the camera's view to paint over
(asking first before it replaces a painted one, which is kept to be put back), painting
it in an Image Editor over that picture (made or remade on demand), and keeping painted
masks when the file is saved."""

import bpy
import gpu
import numpy as np
from bpy.props import BoolProperty

from ..adapters.cameras import pinhole_from_object, render_size
from ..adapters.lights import world_colour
from ..adapters.masks import image_from_rgba, image_pixels, new_mask_image
from ..render.checks import scene_tree
from ..render.guide import guide_size, solid_view
from .context import list_item

MASK_SUFFIX = " mask"
GUIDE_SUFFIX = " guide"
PREVIOUS_SUFFIX = " mask (previous)"


def painted(image):
    """True when ``image`` has a pixel that is not black: replacing it would lose work."""
    rgba = image_pixels(image) if image is not None else None
    return rgba is not None and bool((rgba[..., :3] > 0.0).any())


def keep_previous(item):
    """Before a new mask replaces a painted one: keep the old mask as ``<camera> mask
    (previous)`` (a fake user and packed pixels keep it through save and reload) in
    ``item.previous_mask``, dropping an older previous one no list item uses.
    Returns the kept image, or None when nothing painted was there."""
    old = item.mask
    if not painted(old):
        return None
    prev = item.previous_mask
    if prev is not None and prev != old and not _in_use(prev):
        bpy.data.images.remove(prev)
    old.name = item.camera.name + PREVIOUS_SUFFIX
    old.use_fake_user = True
    if old.is_dirty and (old.packed_file or old.source == "GENERATED"):
        old.pack()
    item.previous_mask = old
    return old


def _in_use(image):
    """Whether a listed camera of any scene uses ``image`` as its mask."""
    return any(
        item.mask == image
        for scene in bpy.data.scenes
        if hasattr(scene, "multiscale")
        for item in scene.multiscale.cameras
    )


def guide_key(obj, scene):
    """What a camera's guide depends on, as a string: the camera's placement, its lens
    and sensor, its clipping and the render's size and pixel aspect."""
    cam, r = obj.data, scene.render
    values = (
        *np.asarray(obj.matrix_world, dtype=np.float64).ravel(),
        cam.lens,
        cam.sensor_width,
        cam.sensor_height,
        cam.shift_x,
        cam.shift_y,
        cam.clip_start,
        cam.clip_end,
        *render_size(scene),
        r.pixel_aspect_x,
        r.pixel_aspect_y,
    )
    return f"{cam.type} {cam.sensor_fit} " + " ".join(f"{v:.6g}" for v in values)


def guide_state(item, scene):
    """ "missing", "stale" (the camera, lens or resolution changed since it was made) or
    "ok" for the guide of a list item with a camera; "" without a camera."""
    obj = item.camera
    if obj is None or obj.type != "CAMERA":
        return ""
    if item.guide is None:
        return "missing"
    return "ok" if item.guide_key == guide_key(obj, scene) else "stale"


def make_guide(context, item):
    """(Re)make the guide of ``item``'s camera; returns how it was drawn."""
    scene = context.scene
    item.guide, how = _render_guide(context, item.camera, scene)
    item.guide_key = guide_key(item.camera, scene)
    return how


def _render_guide(context, obj, scene):
    """The camera's own view as an image: the viewport's Workbench drawing offscreen where
    a GPU context exists, else our solid raycast. Returns (image, how)."""
    name = obj.name + GUIDE_SUFFIX
    size = guide_size(*render_size(scene))
    if not bpy.app.background:
        try:
            rgba = _workbench_view(context, obj, size)
            if rgba is not None:
                return image_from_rgba(name, rgba), "Workbench"
        except (RuntimeError, ValueError, SystemError) as err:  # no GPU after all
            print(f"Multiscale: Workbench guide failed ({err}); using the solid raycast")
    depsgraph = context.evaluated_depsgraph_get()
    cam = pinhole_from_object(obj.evaluated_get(depsgraph), depsgraph.scene)
    geometry, tree = scene_tree(depsgraph)
    rgba = solid_view(cam, geometry, tree, world_colour(scene), size)
    return image_from_rgba(name, rgba, colorspace="Linear Rec.709"), "solid raycast"


def _workbench_view(context, obj, size):
    """(h, w, 4) float32 display-referred RGBA, row 0 at the top: ``obj``'s view drawn
    offscreen by a 3D viewport in Solid shading (Workbench), or None without a viewport.
    Nothing of the scene or its render settings changes."""
    screen = getattr(context, "screen", None)
    views = [a for a in screen.areas if a.type == "VIEW_3D"] if screen else []
    if not views:
        return None
    area = max(views, key=lambda a: a.width * a.height)
    space = area.spaces.active
    region = next(r for r in area.regions if r.type == "WINDOW")
    w, h = size
    depsgraph = context.evaluated_depsgraph_get()
    view = obj.matrix_world.normalized().inverted()
    projection = obj.calc_matrix_camera(depsgraph, x=w, y=h)
    shading, overlays = space.shading.type, space.overlay.show_overlays
    space.shading.type = "SOLID"  # never our own engine (or Cycles) for the guide
    space.overlay.show_overlays = False  # the scene only: no cameras, grid or cursor
    offscreen = gpu.types.GPUOffScreen(w, h)
    try:
        with offscreen.bind():
            fb = gpu.state.active_framebuffer_get()
            fb.clear(color=(0.0, 0.0, 0.0, 1.0))
            offscreen.draw_view3d(
                context.scene,
                context.view_layer,
                space,
                region,
                view,
                projection,
                do_color_management=True,
            )
            buf = fb.read_color(0, 0, w, h, 4, 0, "FLOAT")
    finally:
        offscreen.free()
        space.shading.type, space.overlay.show_overlays = shading, overlays
    buf.dimensions = w * h * 4
    rgba = np.asarray(buf, dtype=np.float32).reshape(h, w, 4)[::-1].copy()
    rgba[..., 3] = 1.0
    return rgba


class MULTISCALE_OT_mask_new(bpy.types.Operator):
    """Make a black mask at render resolution for the active camera (paint white where
    its view is kept) and a quick picture of its view to paint over"""

    bl_idname = "multiscale.mask_new"
    bl_label = "New Mask"
    bl_options = {"REGISTER", "UNDO"}

    guide: BoolProperty(
        name="Guide", default=True, description="Render the camera's view to paint over"
    )

    @classmethod
    def poll(cls, context):
        item = list_item(context)
        if item is None or item.camera is None:
            cls.poll_message_set("Pick a camera in the Multiscale list first")
            return False
        return True

    def invoke(self, context, event):
        item = list_item(context)
        if item.camera is None or not painted(item.mask):
            return self.execute(context)
        message = (
            f"'{item.mask.name}' is painted. It will be kept as "
            f"'{item.camera.name}{PREVIOUS_SUFFIX}' (Restore Previous Mask puts it back)"
        )
        try:
            return context.window_manager.invoke_confirm(
                self,
                event,
                title="Replace the painted mask?",
                message=message,
                confirm_text="New Mask",
                icon="WARNING",
            )
        except TypeError:  # a Blender whose invoke_confirm takes no texts
            return context.window_manager.invoke_confirm(self, event)

    def execute(self, context):
        scene = context.scene
        item = list_item(context)
        obj = item.camera
        if obj.type != "CAMERA":
            self.report({"ERROR"}, f"'{obj.name}' is not a camera; pick a camera object")
            return {"CANCELLED"}
        width, height = render_size(scene)
        kept = keep_previous(item)
        item.mask = new_mask_image(obj.name + MASK_SUFFIX, width, height)
        how = "no guide"
        if self.guide:
            try:
                how = make_guide(context, item)
            except Exception as err:  # the mask is made; only the picture failed
                self.report({"WARNING"}, f"No guide picture for '{obj.name}': {err}")
        kept_note = f"; the painted one is kept as '{kept.name}'" if kept is not None else ""
        self.report(
            {"INFO"},
            f"Mask '{item.mask.name}' ({width}x{height}) made for '{obj.name}' ({how}); "
            f"paint white where its view is kept{kept_note}",
        )
        return {"FINISHED"}


class MULTISCALE_OT_mask_paint(bpy.types.Operator):
    """Open the active camera's mask in an Image Editor in Paint mode, white brush, the
    camera's view shown over it (made, or remade when stale, first)"""

    bl_idname = "multiscale.mask_paint"
    bl_label = "Paint Mask"

    @classmethod
    def poll(cls, context):
        item = list_item(context)
        if bpy.app.background or context.window is None:
            cls.poll_message_set("Painting needs a Blender window (not available in background)")
            return False
        if item is None or item.mask is None:
            cls.poll_message_set("Make a mask for the active camera first (New Mask)")
            return False
        return True

    def execute(self, context):
        item = list_item(context)
        area = _image_editor_area(context)
        if area is None:
            self.report({"ERROR"}, "No area could be turned into an Image Editor")
            return {"CANCELLED"}
        note = ""
        if guide_state(item, context.scene) in {"missing", "stale"}:
            try:
                note = f"; its view ({make_guide(context, item)}) is drawn over it"
            except Exception as err:  # painting works without the picture
                self.report({"WARNING"}, f"No guide picture for '{item.camera.name}': {err}")
        space = area.spaces.active
        space.image = item.mask
        space.ui_mode = "PAINT"
        _white_brush(context, area)
        area.tag_redraw()
        self.report(
            {"INFO"}, f"Painting '{item.mask.name}': white keeps the view, black hides{note}"
        )
        return {"FINISHED"}


def _image_editor_area(context):
    """An Image Editor of the current screen; else the 3D viewport split in two, its right
    half turned into one; else a new window turned into one."""
    screen = context.screen
    for area in screen.areas:
        if area.type == "IMAGE_EDITOR":
            return area
    views = [a for a in screen.areas if a.type == "VIEW_3D"]
    if views:
        view = max(views, key=lambda a: a.width * a.height)
        region = next(r for r in view.regions if r.type == "WINDOW")
        before = {a.as_pointer() for a in screen.areas}
        with context.temp_override(area=view, region=region):
            bpy.ops.screen.area_split(direction="VERTICAL", factor=0.5)
        new = [a for a in screen.areas if a.as_pointer() not in before]
        if new:
            new[0].type = "IMAGE_EDITOR"
            return new[0]
    before = {w.as_pointer() for w in context.window_manager.windows}
    bpy.ops.wm.window_new()
    new = [w for w in context.window_manager.windows if w.as_pointer() not in before]
    if not new:
        return None
    area = max(new[0].screen.areas, key=lambda a: a.width * a.height)
    area.type = "IMAGE_EDITOR"
    return area


# Blender 4.3+ keeps brushes as assets; this one paints with a hard edge.
HARD_BRUSH = "brushes/essentials_brushes-mesh_texture.blend/Brush/Paint Hard"


def _white_brush(context, area):
    """A white brush (black as the secondary colour) for the mask; on Blender 4.3+ the
    hard round brush asset too, once the new Image Editor has been drawn (activating it
    in an area that has never been drawn crashes Blender 5.2)."""
    _white(context.tool_settings)
    if bpy.app.version >= (4, 3, 0) and hasattr(bpy.ops.brush, "asset_activate"):
        window, pointer = context.window, area.as_pointer()
        bpy.app.timers.register(lambda: _hard_brush(window, pointer), first_interval=0.5)


def _hard_brush(window, pointer):
    """Timer: activate the hard brush asset in the Image Editor ``pointer`` of
    ``window``, if it is still there and in Paint mode; then make it white."""
    try:
        area = next(a for a in window.screen.areas if a.as_pointer() == pointer)
    except (StopIteration, ReferenceError):
        return None
    space = area.spaces.active
    if area.type != "IMAGE_EDITOR" or getattr(space, "ui_mode", None) != "PAINT":
        return None
    region = next(r for r in area.regions if r.type == "WINDOW")
    try:
        with bpy.context.temp_override(window=window, area=area, region=region):
            bpy.ops.brush.asset_activate(
                asset_library_type="ESSENTIALS", relative_asset_identifier=HARD_BRUSH
            )
    except (RuntimeError, TypeError) as err:
        print(f"Multiscale: no hard brush ({err}); keeping the current one")
    _white(bpy.context.tool_settings)
    return None


def _white(tool_settings):
    """White paint, black secondary colour: on the brush and on the unified colour, which
    Blender 5 keeps per paint mode (``image_paint.unified_paint_settings``) and 4.x for
    all modes (``tool_settings.unified_paint_settings``)."""
    paint = tool_settings.image_paint
    for holder in (
        getattr(paint, "unified_paint_settings", None),
        getattr(tool_settings, "unified_paint_settings", None),
        paint.brush,
    ):
        if holder is not None:
            holder.color = (1.0, 1.0, 1.0)
            holder.secondary_color = (0.0, 0.0, 0.0)


@bpy.app.handlers.persistent
def repack_masks(*_args):
    """Before a save: pack masks and guides that were painted (a packed image keeps its
    packed pixels otherwise, and a painted mask would revert on reload), and images made
    in Blender, painted and never saved anywhere (a generated image is saved only as its
    generator settings). Painted images that live in their own files are left alone."""
    for scene in bpy.data.scenes:
        settings = getattr(scene, "multiscale", None)
        for item in settings.cameras if settings is not None else ():
            for image in (item.mask, item.guide, item.previous_mask):
                if image is None:
                    continue
                if image.is_dirty and (image.packed_file or image.source == "GENERATED"):
                    image.pack()


CLASSES = (MULTISCALE_OT_mask_new, MULTISCALE_OT_mask_paint)
