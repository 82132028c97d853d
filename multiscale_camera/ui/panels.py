"""The 3D viewport's sidebar tab "Multiscale"."""

import json
import textwrap

import bpy

from ..adapters.cameras import pinhole_from_object
from ..adapters.masks import animated_kind
from ..core.quality import guard_pairs, headline
from ..render import cycles
from ..render.fields import SERVICE
from . import preview
from .mask_ops import guide_state
from .volume import draw_transfer_function


def _report(settings):
    """The last build report as a dict, or None when there is none (or it is unreadable)."""
    try:
        report = json.loads(settings.report) if settings.report else None
    except ValueError:
        return None
    return report if isinstance(report, dict) and "cameras" in report else None


def _draw_shading(layout, settings):
    """The shading choice where Cycles can take the rays (Blender 4.5+), else why not."""
    reason = cycles.unsupported_reason()
    if reason is None:
        layout.prop(settings, "shading", expand=True)
    else:
        layout.label(text=reason, icon="INFO")


class MULTISCALE_UL_cameras(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_property, index):
        row = layout.row(align=True)
        row.label(text=f"{index + 1}.")
        if item.camera is None:
            row.alert = True
            row.prop(item, "camera", text="", icon="ERROR")
        else:
            row.label(
                text=item.camera.name if item.mask is not None else f"{item.camera.name} (no mask)"
            )
        draw_item_buttons(row, item, index)


class MULTISCALE_PT_main(bpy.types.Panel):
    bl_label = "Multiscale Camera"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Multiscale"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.multiscale
        layout.label(text="Cameras, largest scale first:")
        row = layout.row()
        row.template_list(
            "MULTISCALE_UL_cameras", "", settings, "cameras", settings, "active_index", rows=3
        )
        col = row.column(align=True)
        col.operator("multiscale.camera_add", icon="ADD", text="")
        col.operator("multiscale.camera_remove", icon="REMOVE", text="")
        col.separator()
        col.operator("multiscale.camera_move", icon="TRIA_UP", text="").direction = "UP"
        col.operator("multiscale.camera_move", icon="TRIA_DOWN", text="").direction = "DOWN"
        if 0 <= settings.active_index < len(settings.cameras):
            item = settings.cameras[settings.active_index]
            box = layout.box()
            box.prop(item, "camera")
            draw_camera_settings(box, context, item)
        col = layout.column(align=True)
        col.prop(settings, "method")
        col.prop(settings, "quality")
        if settings.quality == "CUSTOM":
            col.prop(settings, "accuracy_px")
        col.prop(settings, "beta")
        col.prop(settings, "samples")
        col.prop(settings, "simplify_px")
        _draw_shading(layout, settings)
        row = layout.row(align=True)
        row.prop(settings, "volume_step")
        row.prop(settings, "volume_shading", text="", icon="LIGHT_SUN")
        row = layout.row(align=True)
        row.operator("multiscale.validate", icon="CHECKMARK")
        row.operator("multiscale.compute_field", icon="FORCE_MAGNETIC")
        report = _report(settings)
        if report is not None:
            box = layout.box()
            draw_headline(box, report, wrap_width(context))
            box.operator("multiscale.report_show", icon="TEXT")
        row = layout.row()
        row.scale_y = 1.4
        row.operator("multiscale.render", icon="RENDER_STILL")
        layout.operator("multiscale.export_rays", icon="EXPORT")


def wrap_width(context):
    """Characters of label text that fit the region's width (about 7 px a character at
    UI scale 1, less the icon and the margins)."""
    region = getattr(context, "region", None)
    width = region.width if region is not None else 300
    scale = context.preferences.system.ui_scale if context.preferences else 1.0
    return max(20, int((width - 60) / (6.5 * scale)))


def draw_headline(layout, report, chars=44):
    """The report's headline on two lines and its warnings, wrapped to ``chars``."""
    line = headline(report)
    method, _, rest = line.partition(": ")
    col = layout.column(align=True)
    col.label(text=f"{method}{' (cached)' if report.get('cached') else ''}", icon="INFO")
    col.label(text=rest, icon="BLANK1")
    warnings = report.get("warnings", [])
    for warning in warnings[:3]:
        col = layout.column(align=True)
        for k, text in enumerate(_wrap(warning, chars)[:4]):
            col.label(text=text, icon="ERROR" if k == 0 else "BLANK1")
    if len(warnings) > 3:
        layout.label(text=f"{len(warnings) - 3} more in the full report", icon="BLANK1")


def shading_option_shown():
    """The Cycles hand-off needs the OSL custom camera of Blender 4.5+: hidden before."""
    return cycles.unsupported_reason() is None


def draw_item_buttons(row, item, index):
    """Select and look-through buttons of a camera list row."""
    if item.camera is None:
        return
    op = row.operator("multiscale.camera_select", text="", icon="RESTRICT_SELECT_OFF", emboss=False)
    op.index = index
    op = row.operator("multiscale.camera_view", text="", icon="VIEW_CAMERA", emboss=False)
    op.index = index


def guard_cameras(context):
    """Names of the cameras whose near distance breaks the guide guard (the handle from
    the previous camera would reach behind their eye); empty when the rig cannot tell."""
    settings = context.scene.multiscale
    objs = [i.camera for i in settings.cameras]
    if len(objs) < 2 or any(o is None or o.type != "CAMERA" for o in objs):
        return set()
    try:
        cams = [pinhole_from_object(o, context.scene) for o in objs]
        pairs = guard_pairs(cams, settings.beta, (cams[0].width, cams[0].height))
    except Exception:  # a rig validation explains; the panel only hints
        return set()
    return {cams[j + 1].name for j in pairs}


def draw_camera_settings(layout, context, item):
    """Near distance (with the guard warning), mask, guide, transfer function of the
    active list item."""
    obj = item.camera
    if obj is not None and obj.type == "CAMERA":
        row = layout.row()
        broken = obj.name in guard_cameras(context)
        row.alert = broken
        row.prop(obj.data, "clip_start", text="Near Distance")
        if broken:
            col = layout.column(align=True)
            col.alert = True
            col.label(text="Too close to the eye for the guides:", icon="ERROR")
            col.label(text="raise Near Distance (or lower Beta)")
    layout.template_ID(item, "mask", new="multiscale.mask_new", open="image.open")
    said = animated_mask_wording(item)
    if said is not None:
        col = layout.column(align=True)
        icon = "SEQUENCE" if item.mask.source == "SEQUENCE" else "FILE_MOVIE"
        col.label(text=said[0], icon=icon)
        if said[1]:
            note = col.row()
            note.alert = item.mask.size[0] == 0
            note.label(text=said[1], icon="ERROR" if note.alert else "INFO")
        row = col.row(align=True)
        row.prop(item, "mask_frames")
        row.prop(item, "mask_frame_start")
        row = col.row(align=True)
        row.prop(item, "mask_frame_offset")
        row.prop(item, "mask_cyclic", toggle=True)
    row = layout.row(align=True)
    row.operator("multiscale.mask_new", icon="FILE_NEW")
    row.operator("multiscale.mask_paint", icon="BRUSH_DATA")
    row = layout.row(align=True)
    row.operator("multiscale.mask_from_selected", icon="SELECT_SET")
    row.operator("multiscale.mask_shape", icon="MESH_CIRCLE")
    draw_guide_state(layout, context, item)
    if item.previous_mask is not None:
        col = layout.column(align=True)
        col.label(text=f"Kept: {item.previous_mask.name}", icon="FILE_BACKUP")
        col.operator("multiscale.mask_restore", icon="LOOP_BACK")
    draw_transfer_function(layout, item)


def animated_mask_wording(item):
    """What the camera's settings say of an animated mask: (heading, note or ""), or
    None for a still mask. The note says when the item plays another number of frames
    than the movie has (past the movie's end its last frame holds), or when Blender
    cannot play the movie."""
    kind = animated_kind(item.mask)
    if kind is None:
        return None
    if item.mask.source == "SEQUENCE":
        return "Mask sequence, read at each frame:", ""
    if item.mask.size[0] == 0:
        return "Mask movie Blender cannot play:", "file missing or not a video; reads empty"
    length = item.mask.frame_duration
    note = ""
    if length != item.mask_frames:
        note = f"The movie has {length} frames; Frames plays {item.mask_frames}"
    return f"Mask movie ({length} frames), read at each frame:", note


def draw_guide_state(layout, context, item):
    """The guide's name, and a warning with Update Guide when it is stale."""
    state = guide_state(item, context.scene)
    if state == "stale":
        col = layout.column(align=True)
        col.alert = True
        col.label(text="Guide is stale: camera, lens or size changed", icon="ERROR")
        col.operator("multiscale.guide_update", icon="FILE_REFRESH")
    elif state == "ok":
        layout.label(text=f"Guide: {item.guide.name}", icon="IMAGE_REFERENCE")
    elif state == "missing" and item.mask is not None:
        layout.label(text="No guide yet: Paint Mask makes one", icon="INFO")


def _validation(settings):
    try:
        found = json.loads(settings.validation) if settings.validation else []
    except ValueError:
        return []
    return found if isinstance(found, list) else []


class MULTISCALE_PT_validation(bpy.types.Panel):
    bl_label = "Checks"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Multiscale"
    bl_parent_id = "MULTISCALE_PT_main"

    def draw(self, context):
        layout = self.layout
        found = _validation(context.scene.multiscale)
        if not context.scene.multiscale.validation:
            layout.label(text="Not checked yet: Check Rig", icon="QUESTION")
        elif not found:
            layout.label(text="No problems found", icon="CHECKMARK")
        for entry in found:
            icon = "CANCEL" if entry.get("level") == "ERROR" else "ERROR"
            col = layout.column(align=True)
            col.alert = entry.get("level") == "ERROR"
            for k, line in enumerate(_wrap(str(entry.get("text", "")), wrap_width(context))):
                col.label(text=line, icon=icon if k == 0 else "BLANK1")


def _wrap(text, width):
    return textwrap.wrap(text, width) or [""]


class MULTISCALE_PT_preview(bpy.types.Panel):
    bl_label = "Preview and Cache"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Multiscale"
    bl_parent_id = "MULTISCALE_PT_main"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        settings = context.scene.multiscale
        layout = self.layout
        row = layout.row(align=True)
        row.prop(settings, "show_preview", icon="LIGHT_SUN", toggle=True)
        row.prop(settings, "preview_rays", text="Rays")
        if settings.show_preview and preview.note():
            layout.label(text=preview.note(), icon="INFO")
        layout.prop(settings, "live_picture", toggle=True, icon="RENDER_RESULT")
        if settings.live_picture and SERVICE.live is not None and SERVICE.live.status():
            layout.label(text=SERVICE.live.status(), icon="INFO")
        row = layout.row(align=True)
        row.prop(settings, "cache_limit_mb", text="Cache (MB)")
        row.operator("multiscale.cache_clear", icon="TRASH")
        layout.prop(settings, "cache_folder", text="Folder")
        layout.prop(settings, "memory_budget_mb", text="Memory Budget (MB, 0: free memory)")


CLASSES = (
    MULTISCALE_UL_cameras,
    MULTISCALE_PT_main,
    MULTISCALE_PT_validation,
    MULTISCALE_PT_preview,
)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
