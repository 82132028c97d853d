"""The Image Editor while a listed camera's mask is shown: every other camera's mask in
its own colour, the transition bands (no mask claims them) and the guidelines' warnings
(``mask_shapes.overlay_rgba``, drawn with the ``gpu`` module over the mask and its
guide), the guide made again when it is stale (a timer), and the sidebar tab
"Multiscale" with the guide's opacity and the mask tools.

Drawing needs a GPU context, which background Blender lacks: there the panel registers
and nothing is drawn.
"""

import time

import blf
import bpy
import gpu
import numpy as np

from ..adapters.masks import mask_from_image
from ..adapters.scene import mask_frame
from ..render.fields import SERVICE
from ..render.guide import guide_size
from .mask_ops import guide_key, guide_state, make_guide
from .mask_shapes import overlay_rgba
from .preview import draw_texture
from .preview_lines import PALETTE

# The overlay is computed at most this wide (then stretched over the mask), and again
# at most this often while painting, seconds.
OVERLAY_MAX_WIDTH = 480
REFRESH_SECONDS = 1.0
# The masks not shown are read again at most this often, seconds.
OTHERS_SECONDS = 5.0
# How often shown masks' guides are checked for staleness, seconds.
GUIDE_CHECK_SECONDS = 1.0
SHAPE_ICONS = (
    ("CIRCLE", "MESH_CIRCLE"),
    ("ELLIPSE", "SPHERECURVE"),
    ("ROUNDED_RECT", "MESH_PLANE"),
)
COLOUR_NAMES = ("blue", "green", "orange", "purple", "yellow")


def shown_index(scene, image):
    """Index in the camera list of the item whose mask is ``image``, or -1."""
    if image is None or not hasattr(scene, "multiscale"):
        return -1
    for i, item in enumerate(scene.multiscale.cameras):
        if item.mask is not None and item.mask == image:
            return i
    return -1


def guides_due(scene, images, failed=None):
    """List items whose mask is one of ``images`` (those shown in Image Editors) and
    whose guide is missing or stale, but for those whose last remake for the same camera
    state failed (``failed``: camera name -> ``guide_key``)."""
    failed = failed or {}
    due = []
    for item in scene.multiscale.cameras:
        if item.mask is None or not any(item.mask == image for image in images):
            continue
        if guide_state(item, scene) not in {"missing", "stale"}:
            continue
        if failed.get(item.camera.name) == guide_key(item.camera, scene):
            continue
        due.append(item)
    return due


def _guide_timer():
    """Timer: remake the missing or stale guides of masks shown in Image Editors."""
    context = bpy.context
    scene = context.scene
    wm = context.window_manager
    if OVERLAY is None or scene is None or not hasattr(scene, "multiscale") or wm is None:
        return GUIDE_CHECK_SECONDS
    if not scene.multiscale.auto_guide or bpy.app.is_job_running("RENDER"):
        return GUIDE_CHECK_SECONDS
    for window in wm.windows:
        areas = [a for a in window.screen.areas if a.type == "IMAGE_EDITOR"]
        images = [a.spaces.active.image for a in areas]
        failed = OVERLAY.failed_guides
        for item in guides_due(scene, [i for i in images if i is not None], failed):
            try:
                with context.temp_override(window=window):
                    make_guide(bpy.context, item)
            except Exception as err:  # say it once, in the console and the panel's state
                failed[item.camera.name] = guide_key(item.camera, scene)
                print(f"Multiscale: no guide for '{item.camera.name}' ({err})")
            for area in areas:
                area.tag_redraw()
    return GUIDE_CHECK_SECONDS


def rig_masks(scene, size):
    """Bool (h, w) masks of the listed cameras at ``size`` = (w, h), first to last (an
    item without a mask gives an empty one)."""
    w, h = size
    return [
        mask_from_image(item.mask, w, h, mask_frame(item, scene), frames=SERVICE.mask_frames)[0]
        for item in scene.multiscale.cameras
    ]


class MaskOverlay:
    """The overlay's texture, recomputed when the shown mask, the list or the opacity
    change, or ``REFRESH_SECONDS`` after the last time (strokes change pixels, which
    Blender does not announce)."""

    def __init__(self):
        self.handler = None
        self.key = None
        self.stamp = 0.0
        self.texture = None
        self.messages = []
        self.cache = {}  # list index -> (key, time read, bool mask)
        # camera name -> the guide_key whose guide could not be made (not tried again)
        self.failed_guides = {}

    def start(self):
        if not bpy.app.background and self.handler is None:
            self.handler = bpy.types.SpaceImageEditor.draw_handler_add(
                self.draw, (), "WINDOW", "POST_PIXEL"
            )

    def stop(self):
        if self.handler is not None:
            bpy.types.SpaceImageEditor.draw_handler_remove(self.handler, "WINDOW")
            self.handler = None
        self.texture, self.key, self.messages, self.cache = None, None, [], {}

    def refresh(self, scene, shown):
        """Recompute the overlay for mask ``shown`` of ``scene``'s list if it is due."""
        settings = scene.multiscale
        image = settings.cameras[shown].mask
        key = (
            shown,
            settings.overlay_opacity,
            tuple((i.mask.name, *i.mask.size) if i.mask else () for i in settings.cameras),
        )
        now = time.monotonic()
        if key == self.key and now - self.stamp < REFRESH_SECONDS:
            return
        self.key, self.stamp = key, now
        size = guide_size(*image.size, max_width=OVERLAY_MAX_WIDTH)
        masks = self.masks_for(scene, shown, size, now)
        rgba, self.messages = overlay_rgba(masks, shown, settings.overlay_opacity)
        self.texture = _texture(rgba)

    def masks_for(self, scene, shown, size, now):
        """``rig_masks`` of ``scene`` at ``size``: the shown mask read each time, the
        others kept for ``OTHERS_SECONDS`` (reading a 1080p mask takes about 18 ms)."""
        out, cache = [], {}
        for j, item in enumerate(scene.multiscale.cameras):
            frame = mask_frame(item, scene)
            key = (item.mask.name, *item.mask.size, *size, frame) if item.mask else size
            kept = self.cache.get(j)
            if j != shown and kept and kept[0] == key and now - kept[1] < OTHERS_SECONDS:
                cache[j] = kept
            else:
                mask = mask_from_image(item.mask, *size, frame, frames=SERVICE.mask_frames)[0]
                cache[j] = (key, now, mask)
            out.append(cache[j][2])
        self.cache = cache
        return out

    def draw(self):
        context = bpy.context
        space, region, scene = context.space_data, context.region, context.scene
        image = getattr(space, "image", None)
        shown = shown_index(scene, image) if scene is not None else -1
        if shown < 0 or not scene.multiscale.show_mask_overlay or image.size[0] == 0:
            return
        try:
            self.refresh(scene, shown)
        except Exception as err:  # never break the editor's drawing
            print(f"Multiscale: no mask overlay ({err})")
            return
        x0, y0 = region.view2d.view_to_region(0.0, 0.0, clip=False)
        x1, y1 = region.view2d.view_to_region(1.0, 1.0, clip=False)
        draw_texture(self.texture, (x0, y0, x1, y1))
        blf.size(0, 13)
        for k, text in enumerate(self.messages):  # top left, under the header
            blf.position(0, 12, region.height - 30 - 18 * k, 0)
            blf.color(0, 1.0, 0.85, 0.2, 1.0)
            blf.draw(0, text)


def _texture(rgba):
    """A GPU texture of (h, w, 4) float32 RGBA, row 0 at the top (flipped: GPU rows run
    from the bottom)."""
    h, w = rgba.shape[:2]
    flat = np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel()
    try:
        buf = gpu.types.Buffer("FLOAT", flat.size, flat)
    except TypeError:  # a Blender whose Buffer takes sequences only
        buf = gpu.types.Buffer("FLOAT", flat.size, flat.tolist())
    return gpu.types.GPUTexture((w, h), format="RGBA16F", data=buf)


class MULTISCALE_PT_image_masks(bpy.types.Panel):
    """The Image Editor's sidebar tab "Multiscale": the guide's opacity and state, the
    overlay of the other masks and its warnings, the mask tools."""

    bl_label = "Multiscale Masks"
    bl_space_type = "IMAGE_EDITOR"
    bl_region_type = "UI"
    bl_category = "Multiscale"

    def draw(self, context):
        layout = self.layout
        scene = context.scene
        settings = scene.multiscale
        shown = shown_index(scene, getattr(context.space_data, "image", None))
        if shown < 0:
            layout.label(text="Not a listed camera's mask", icon="INFO")
            layout.label(text="(Paint Mask in the 3D viewport's tab)", icon="BLANK1")
            return
        item = settings.cameras[shown]
        name = item.camera.name if item.camera else "no camera"
        layout.label(text=f"Camera {shown + 1}: {name}", icon="CAMERA_DATA")
        row = layout.row(align=True)
        row.prop(settings, "guide_opacity")
        row.prop(settings, "auto_guide", text="", icon="FILE_REFRESH")
        state = guide_state(item, scene)
        if state in {"stale", "missing"}:
            col = layout.column(align=True)
            col.alert = state == "stale"
            col.label(text="Guide is stale" if state == "stale" else "No guide yet", icon="ERROR")
            if shown == settings.active_index:
                col.operator("multiscale.guide_update", icon="FILE_REFRESH")
        layout.prop(settings, "live_picture", toggle=True, icon="RENDER_RESULT")
        if settings.live_picture and SERVICE.live is not None and SERVICE.live.status():
            layout.label(text=SERVICE.live.status(), icon="INFO")
        row = layout.row(align=True)
        row.prop(settings, "show_mask_overlay", toggle=True, icon="OVERLAY")
        row.prop(settings, "overlay_opacity", text="")
        if settings.show_mask_overlay:
            col = layout.column(align=True)
            for j, other in enumerate(settings.cameras):
                if j != shown:
                    colour = COLOUR_NAMES[j % len(PALETTE)]
                    label = other.camera.name if other.camera else "no camera"
                    col.label(text=f"{j + 1}. {label}: {colour}", icon="BLANK1")
            col.label(text="Transition band: grey", icon="BLANK1")
            for text in OVERLAY.messages if OVERLAY is not None else ():
                col.label(text=text, icon="ERROR")
        if shown == settings.active_index:
            col = layout.column(align=True)
            col.operator("multiscale.mask_from_selected", icon="SELECT_SET")
            col.operator("multiscale.mask_shape", icon="MESH_CIRCLE")
            row = layout.row(align=True)
            row.label(text="Drag:")
            for shape, icon in SHAPE_ICONS:
                row.operator("multiscale.mask_shape_drag", text="", icon=icon).shape = shape


# The overlay of this session: made in register(), None while unregistered.
OVERLAY = None


def register():
    global OVERLAY
    bpy.utils.register_class(MULTISCALE_PT_image_masks)
    OVERLAY = MaskOverlay()
    OVERLAY.start()
    if not bpy.app.background:
        bpy.app.timers.register(_guide_timer, first_interval=GUIDE_CHECK_SECONDS, persistent=True)


def unregister():
    global OVERLAY
    if bpy.app.timers.is_registered(_guide_timer):
        bpy.app.timers.unregister(_guide_timer)
    if OVERLAY is not None:
        OVERLAY.stop()
    OVERLAY = None
    bpy.utils.unregister_class(MULTISCALE_PT_image_masks)
