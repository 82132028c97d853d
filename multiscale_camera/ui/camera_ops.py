"""Operators that edit the camera list: add, remove, move, select, look through."""

import bpy
from bpy.props import EnumProperty, IntProperty

from .context import list_item, settings_of


class MULTISCALE_OT_camera_add(bpy.types.Operator):
    """Add the selected cameras (or the active one) to the end of the list, or an empty
    item to fill in when no camera is selected"""

    bl_idname = "multiscale.camera_add"
    bl_label = "Add Camera"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        settings = settings_of(context)
        listed = {item.camera for item in settings.cameras if item.camera is not None}
        chosen = [o for o in getattr(context, "selected_objects", []) if o.type == "CAMERA"]
        active = context.active_object
        if not chosen and active is not None and active.type == "CAMERA":
            chosen = [active]
        new = [o for o in chosen if o not in listed]
        if chosen and not new:
            self.report({"WARNING"}, "The selected cameras are already in the list")
            return {"CANCELLED"}
        for obj in new or [None]:
            item = settings.cameras.add()
            item.camera = obj
        settings.active_index = len(settings.cameras) - 1
        return {"FINISHED"}


class MULTISCALE_OT_camera_remove(bpy.types.Operator):
    """Remove the active item from the list (the camera object and its mask stay)"""

    bl_idname = "multiscale.camera_remove"
    bl_label = "Remove Camera"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return len(settings_of(context).cameras) > 0

    def execute(self, context):
        settings = settings_of(context)
        settings.cameras.remove(min(settings.active_index, len(settings.cameras) - 1))
        settings.active_index = max(0, min(settings.active_index, len(settings.cameras) - 1))
        return {"FINISHED"}


class MULTISCALE_OT_camera_move(bpy.types.Operator):
    """Move the active camera up (larger scale) or down (smaller scale) in the list"""

    bl_idname = "multiscale.camera_move"
    bl_label = "Move Camera"
    bl_options = {"REGISTER", "UNDO"}

    direction: EnumProperty(items=[("UP", "Up", ""), ("DOWN", "Down", "")], default="UP")

    @classmethod
    def poll(cls, context):
        return len(settings_of(context).cameras) > 1

    def execute(self, context):
        settings = settings_of(context)
        i = settings.active_index
        j = i - 1 if self.direction == "UP" else i + 1
        if not 0 <= j < len(settings.cameras):
            return {"CANCELLED"}
        settings.cameras.move(i, j)
        settings.active_index = j
        return {"FINISHED"}


class _ListedCamera:
    """What the select and look-through buttons share: the camera of list item
    ``index`` (the active one when -1), an error when the item has none."""

    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(default=-1, options={"SKIP_SAVE"})

    def execute(self, context):
        item = list_item(context, self.index)
        if item is None or item.camera is None:
            self.report({"ERROR"}, "This list item has no camera: pick one first")
            return {"CANCELLED"}
        return self.act(context, item.camera)


class MULTISCALE_OT_camera_select(_ListedCamera, bpy.types.Operator):
    """Select this camera in the viewport and make it the active object"""

    bl_idname = "multiscale.camera_select"
    bl_label = "Select Camera"

    def act(self, context, obj):
        layer = context.view_layer
        if layer.objects.get(obj.name) is None:
            self.report({"ERROR"}, f"Camera '{obj.name}' is not in the current view layer")
            return {"CANCELLED"}
        for other in context.selected_objects:
            other.select_set(False)
        obj.hide_set(False)
        obj.select_set(True)
        layer.objects.active = obj
        if self.index >= 0:
            settings_of(context).active_index = self.index
        return {"FINISHED"}


class MULTISCALE_OT_camera_view(_ListedCamera, bpy.types.Operator):
    """Look through this camera: make it the scene camera and show its view"""

    bl_idname = "multiscale.camera_view"
    bl_label = "Look Through"

    def act(self, context, obj):
        context.scene.camera = obj
        space = getattr(context, "space_data", None)
        if space is not None and space.type == "VIEW_3D":
            space.region_3d.view_perspective = "CAMERA"
        elif not bpy.app.background:
            for area in context.screen.areas if context.screen else []:
                if area.type == "VIEW_3D":
                    area.spaces.active.region_3d.view_perspective = "CAMERA"
                    area.tag_redraw()
                    break
        return {"FINISHED"}


CLASSES = (
    MULTISCALE_OT_camera_add,
    MULTISCALE_OT_camera_remove,
    MULTISCALE_OT_camera_move,
    MULTISCALE_OT_camera_select,
    MULTISCALE_OT_camera_view,
)
