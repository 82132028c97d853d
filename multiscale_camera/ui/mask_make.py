"""Operators that make masks from the scene and from shapes (given, or dragged in the
Image Editor), remake a camera's guide and
put a replaced mask back. Every mask stays an ordinary image, to be painted further."""

import bpy
import gpu
import numpy as np
from bpy.props import EnumProperty, FloatProperty, FloatVectorProperty, IntProperty
from gpu_extras.batch import batch_for_shader

from ..adapters.cameras import pinhole_from_object, render_size
from ..adapters.masks import mask_values, new_mask_image, write_mask_values
from ..render.checks import scene_tree
from ..render.guide import silhouette
from .context import list_item
from .mask_ops import MASK_SUFFIX, PREVIOUS_SUFFIX, make_guide
from .mask_shapes import dilate, drag_box, outline, soft_shape

MODE_ITEMS = [
    ("ADD", "Add", "Keep the camera's view where the shape is (white), on top of the mask"),
    ("SUBTRACT", "Subtract", "Hide the camera's view where the shape is (black)"),
]
SHAPE_ITEMS = [
    ("CIRCLE", "Circle", "A circle of the smaller of width and height"),
    ("ELLIPSE", "Ellipse", "An ellipse of the given width and height"),
    ("ROUNDED_RECT", "Rounded Rectangle", "A rectangle with rounded corners"),
]


class _CameraItemOperator:
    """Acts on the active item of the camera list, which needs a camera object."""

    @classmethod
    def poll(cls, context):
        item = list_item(context)
        if item is None or item.camera is None or item.camera.type != "CAMERA":
            cls.poll_message_set("Pick a camera in the Multiscale list first")
            return False
        return True


def mask_target(item, scene):
    """(image, values): the item's mask and its grey values, made (black, at the render
    size, named after the camera) when it has none."""
    if item.mask is None or mask_values(item.mask) is None:
        width, height = render_size(scene)
        item.mask = new_mask_image(item.camera.name + MASK_SUFFIX, width, height)
    return item.mask, mask_values(item.mask)


def combine(values, shape, mode):
    """The mask's grey ``values`` with ``shape`` (both (h, w) in [0, 1]) added (maximum)
    or subtracted (minimum with its complement)."""
    if mode == "SUBTRACT":
        return np.minimum(values, 1.0 - shape)
    return np.maximum(values, shape)


class MULTISCALE_OT_mask_from_selected(_CameraItemOperator, bpy.types.Operator):
    """Make or extend the active camera's mask from the selected objects' silhouette as
    that camera sees them, grown by a margin"""

    bl_idname = "multiscale.mask_from_selected"
    bl_label = "Mask from Selected"
    bl_options = {"REGISTER"}

    margin: IntProperty(
        name="Margin",
        default=4,
        min=0,
        max=256,
        subtype="PIXEL",
        description="Grow the silhouette by this many pixels",
    )
    mode: EnumProperty(name="Mode", items=MODE_ITEMS, default="ADD")

    def execute(self, context):
        item = list_item(context)
        obj = item.camera
        names = {o.name for o in context.selected_objects if o.type not in {"CAMERA", "LIGHT"}}
        if not names:
            self.report({"ERROR"}, "Select the objects whose silhouette makes the mask")
            return {"CANCELLED"}
        depsgraph = context.evaluated_depsgraph_get()
        try:
            cam = pinhole_from_object(obj.evaluated_get(depsgraph), depsgraph.scene)
        except Exception as err:  # an orthographic camera, ...: say so in the report
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        image, values = mask_target(item, context.scene)
        h, w = values.shape
        geometry, tree = scene_tree(depsgraph)
        seen = silhouette(cam, geometry, tree, names, (w, h))
        if not seen.any():
            self.report(
                {"WARNING"},
                f"'{obj.name}' sees none of the selected objects: the mask is unchanged",
            )
            return {"CANCELLED"}
        grown = dilate(seen, self.margin)
        write_mask_values(image, combine(values, grown.astype(np.float32), self.mode))
        self.report(
            {"INFO"},
            f"Mask '{image.name}': {int(seen.sum())} pixels of {len(names)} object(s) seen "
            f"by '{obj.name}', {self.margin} px margin ({self.mode.lower()})",
        )
        return {"FINISHED"}


class _ShapeProperties:
    """The parameters of a soft shape."""

    shape: EnumProperty(name="Shape", items=SHAPE_ITEMS, default="ELLIPSE")
    centre: FloatVectorProperty(
        name="Centre",
        size=2,
        default=(0.5, 0.5),
        min=-1.0,
        max=2.0,
        subtype="COORDINATES",
        description="Centre in the image, 0 to 1 from its bottom-left corner",
    )
    size: FloatVectorProperty(
        name="Size",
        size=2,
        default=(0.3, 0.3),
        min=0.0,
        max=4.0,
        description="Width and height as fractions of the image's width and height",
    )
    corner_radius: FloatProperty(
        name="Corner Radius",
        default=16.0,
        min=0.0,
        subtype="PIXEL",
        description="Rounded rectangle's corner radius, pixels",
    )
    feather: FloatProperty(
        name="Feather",
        default=8.0,
        min=0.0,
        subtype="PIXEL",
        description="Width of the soft edge, pixels, centred on the shape's outline",
    )
    mode: EnumProperty(name="Mode", items=MODE_ITEMS, default="ADD")

    def write_shape(self, context):
        """Write the shape into the active item's mask; returns the mask."""
        item = list_item(context)
        image, values = mask_target(item, context.scene)
        h, w = values.shape
        centre = (self.centre[0] * w, (1.0 - self.centre[1]) * h)  # row 0 at the top
        size = (self.size[0] * w, self.size[1] * h)
        shape = soft_shape(
            self.shape, w, h, centre, size, radius=self.corner_radius, feather=self.feather
        )
        write_mask_values(image, combine(values, shape, self.mode))
        return image


class MULTISCALE_OT_mask_shape(_ShapeProperties, _CameraItemOperator, bpy.types.Operator):
    """Add (or cut) a soft shape to the active camera's mask: a circle, an ellipse or a
    rounded rectangle with a feathered edge"""

    bl_idname = "multiscale.mask_shape"
    bl_label = "Add Mask Shape"
    bl_options = {"REGISTER"}

    def invoke(self, context, event):
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        image = self.write_shape(context)
        self.report({"INFO"}, f"Mask '{image.name}': {self.shape.lower()} ({self.mode.lower()})")
        return {"FINISHED"}


class MULTISCALE_OT_mask_shape_drag(_ShapeProperties, bpy.types.Operator):
    """Drag a box over the active camera's mask in the Image Editor: the soft shape
    fills it (Esc or right click cancels)"""

    bl_idname = "multiscale.mask_shape_drag"
    bl_label = "Drag a Shape"

    @classmethod
    def poll(cls, context):
        item = list_item(context)
        space = context.space_data
        if item is None or item.camera is None or item.mask is None:
            cls.poll_message_set("Make a mask for the active camera first (New Mask)")
            return False
        if (
            context.area is None
            or context.area.type != "IMAGE_EDITOR"
            or (space.image != item.mask)
        ):
            cls.poll_message_set("Show the active camera's mask in an Image Editor (Paint Mask)")
            return False
        return True

    def invoke(self, context, event):
        # the editor's image region (the button may be in its sidebar)
        self._region = next(r for r in context.area.regions if r.type == "WINDOW")
        self._start = self._end = None
        self._handler = bpy.types.SpaceImageEditor.draw_handler_add(
            self._draw, (), "WINDOW", "POST_PIXEL"
        )
        context.window_manager.modal_handler_add(self)
        context.workspace.status_text_set("Drag a box for the shape; Esc or right click cancels")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        context.area.tag_redraw()
        region = self._region
        here = (event.mouse_x - region.x, event.mouse_y - region.y)
        if event.type == "LEFTMOUSE" and event.value == "PRESS":
            self._start = self._end = here
        elif event.type in {"MOUSEMOVE", "INBETWEEN_MOUSEMOVE"} and self._start is not None:
            self._end = here
        elif event.type == "LEFTMOUSE" and event.value == "RELEASE" and self._start:
            self._end = here
            self._finish(context)
            view = region.view2d
            centre, size = drag_box(
                view.region_to_view(*self._start), view.region_to_view(*self._end)
            )
            if min(abs(self._start[0] - here[0]), abs(self._start[1] - here[1])) < 3:
                self.report({"WARNING"}, "Drag a box (a few pixels at least) for the shape")
                return {"CANCELLED"}
            self.centre, self.size = centre, size
            image = self.write_shape(context)
            self.report(
                {"INFO"}, f"Mask '{image.name}': {self.shape.lower()} ({self.mode.lower()})"
            )
            return {"FINISHED"}
        elif event.type in {"ESC", "RIGHTMOUSE"}:
            self._finish(context)
            return {"CANCELLED"}
        elif event.type in {"WHEELUPMOUSE", "WHEELDOWNMOUSE", "MIDDLEMOUSE"}:
            return {"PASS_THROUGH"}  # zoom and pan while placing
        return {"RUNNING_MODAL"}

    def _finish(self, context):
        if self._handler is not None:
            bpy.types.SpaceImageEditor.draw_handler_remove(self._handler, "WINDOW")
            self._handler = None
        context.workspace.status_text_set(None)
        context.area.tag_redraw()

    def _draw(self):
        if self._start is None or self._end is None:
            return
        points = outline(self.shape, self._start, self._end)
        shader = gpu.shader.from_builtin("UNIFORM_COLOR")
        batch = batch_for_shader(shader, "LINE_STRIP", {"pos": points.tolist()})
        shader.bind()
        shader.uniform_float("color", (1.0, 0.85, 0.2, 1.0))
        batch.draw(shader)


class MULTISCALE_OT_guide_update(_CameraItemOperator, bpy.types.Operator):
    """Remake the picture of the active camera's view drawn over its mask (after the
    camera, its lens or the render size changed)"""

    bl_idname = "multiscale.guide_update"
    bl_label = "Update Guide"

    def execute(self, context):
        item = list_item(context)
        try:
            how = make_guide(context, item)
        except Exception as err:  # the scene may not cast (an orthographic camera, ...)
            self.report({"ERROR"}, f"No guide picture for '{item.camera.name}': {err}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Guide '{item.guide.name}' remade ({how})")
        return {"FINISHED"}


class MULTISCALE_OT_mask_restore(bpy.types.Operator):
    """Put back the mask New Mask replaced; the current mask is kept in its place, so
    pressing again swaps back"""

    bl_idname = "multiscale.mask_restore"
    bl_label = "Restore Previous Mask"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        item = list_item(context)
        if item is None or item.previous_mask is None:
            cls.poll_message_set("This camera has no replaced mask to put back")
            return False
        return True

    def execute(self, context):
        item = list_item(context)
        current, previous = item.mask, item.previous_mask
        base = item.camera.name if item.camera is not None else previous.name
        previous.name = "multiscale restore"  # frees the names for the swap
        if current is not None:
            current.name = base + PREVIOUS_SUFFIX
            current.use_fake_user = True
        previous.name = base + MASK_SUFFIX
        previous.use_fake_user = False
        item.mask, item.previous_mask = previous, current
        self.report(
            {"INFO"},
            f"Mask '{previous.name}' put back"
            + (f"; the replaced one is kept as '{current.name}'" if current else ""),
        )
        return {"FINISHED"}


CLASSES = (
    MULTISCALE_OT_mask_from_selected,
    MULTISCALE_OT_mask_shape,
    MULTISCALE_OT_mask_shape_drag,
    MULTISCALE_OT_guide_update,
    MULTISCALE_OT_mask_restore,
)
