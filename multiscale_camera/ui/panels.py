"""The 3D viewport's sidebar tab "Multiscale"."""

import json

import bpy

from ..core.report import headline
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
    from ..render.cycles import unsupported_reason

    reason = unsupported_reason()
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
            row.prop(item, "camera", text="", emboss=False, icon="CAMERA_DATA")
        row.label(text="", icon="IMAGE_DATA" if item.mask is not None else "BLANK1")


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
            box.template_ID(item, "mask", new="image.new", open="image.open")
            draw_transfer_function(box, item)
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
            box.label(text=headline(report), icon="INFO")
            for warning in report.get("warnings", [])[:4]:
                box.label(text=warning, icon="ERROR")
        row = layout.row()
        row.scale_y = 1.4
        row.operator("multiscale.render", icon="RENDER_STILL")
        layout.operator("multiscale.export_rays", icon="EXPORT")


CLASSES = (MULTISCALE_UL_cameras, MULTISCALE_PT_main)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
