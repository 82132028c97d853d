"""Volume sources and transfer functions in the UI.

- ``bpy.types.Object.multiscale_volume``: the volume file an object's box holds, or the
  grid a Volume object renders, and how values map to the transfer functions' [0, 1].
- ``multiscale.transfer_function_new``: a colour-ramp texture with the default transfer
  function, set on the active camera of the list.
- The Object Properties panel "Multiscale Volume".
"""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntVectorProperty, StringProperty

from ..adapters.volumes import openvdb_module
from ..core.volume import DEFAULT_POINTS

VALUE_TYPES = [
    ("UINT8", "8-bit unsigned", ""),
    ("INT8", "8-bit signed", ""),
    ("UINT16", "16-bit unsigned", ""),
    ("INT16", "16-bit signed", ""),
    ("UINT32", "32-bit unsigned", ""),
    ("INT32", "32-bit signed", ""),
    ("FLOAT32", "32-bit float", ""),
    ("FLOAT64", "64-bit float", ""),
]

# Blender 4.5+ warns about "//" paths unless the property says it supports them.
PATH_OPTIONS = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 5, 0) else set()


class MultiscaleVolumeSettings(bpy.types.PropertyGroup):
    use: BoolProperty(
        name="Volume File",
        default=False,
        description="Render a scalar volume file filling this object's bounding box (an "
        "empty's display cube) instead of the object itself",
    )
    filepath: StringProperty(
        name="File",
        subtype="FILE_PATH",
        options=PATH_OPTIONS,
        description=".npy (array indexed [x, y, z]), .raw (x fastest) or .nrrd",
    )
    dims: IntVectorProperty(
        name="Dimensions",
        size=3,
        default=(64, 64, 64),
        min=1,
        description="Voxels along x, y and z of a .raw file",
    )
    value_type: EnumProperty(
        name="Type", items=VALUE_TYPES, default="UINT8", description="Voxel type of a .raw file"
    )
    little_endian: BoolProperty(
        name="Little Endian", default=True, description="Byte order of a .raw file"
    )
    grid: StringProperty(
        name="Grid",
        default="",
        description="Grid of a Volume object to render (empty: 'density', else the first "
        "scalar grid)",
    )
    auto_range: BoolProperty(
        name="Auto Range",
        default=True,
        description="Map the data's minimum and maximum to the ends of the transfer functions",
    )
    range_min: FloatProperty(name="Min", default=0.0, description="Value at the ramps' left end")
    range_max: FloatProperty(name="Max", default=1.0, description="Value at the ramps' right end")


def set_default_ramp(ramp):
    """Make a ColorRamp the default transfer function (``core.volume.DEFAULT_POINTS``)."""
    ramp.interpolation = "LINEAR"
    ramp.color_mode = "RGB"
    elements = ramp.elements
    while len(elements) > 1:
        elements.remove(elements[-1])
    for i, (pos, colour) in enumerate(DEFAULT_POINTS):
        el = elements[0] if i == 0 else elements.new(pos)
        el.position = pos
        el.color = colour


def new_transfer_function(name):
    """A Blend texture whose colour ramp holds the default transfer function."""
    tex = bpy.data.textures.new(name, type="BLEND")
    tex.use_color_ramp = True
    set_default_ramp(tex.color_ramp)
    return tex


class MULTISCALE_OT_transfer_function_new(bpy.types.Operator):
    bl_idname = "multiscale.transfer_function_new"
    bl_label = "New Transfer Function"
    bl_description = (
        "Give the active camera of the list a new transfer function (a colour ramp from "
        "value to colour and opacity)"
    )
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        settings = context.scene.multiscale
        if not 0 <= settings.active_index < len(settings.cameras):
            self.report({"ERROR"}, "Select a camera in the list first")
            return {"CANCELLED"}
        item = settings.cameras[settings.active_index]
        label = item.camera.name if item.camera is not None else str(settings.active_index + 1)
        item.transfer_function = new_transfer_function(f"TF {label}")
        return {"FINISHED"}


class MULTISCALE_PT_object_volume(bpy.types.Panel):
    bl_label = "Multiscale Volume"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return context.object is not None and context.object.type != "CAMERA"

    def draw(self, context):
        layout = self.layout
        obj = context.object
        settings = obj.multiscale_volume
        if obj.type == "VOLUME":
            layout.prop(settings, "grid")
            if openvdb_module() is None:
                box = layout.box()
                box.alert = True
                box.label(text="This Blender has no openvdb module:", icon="ERROR")
                box.label(text="its grids cannot be read; use a .npy, .raw or .nrrd file")
        else:
            layout.prop(settings, "use")
            col = layout.column()
            col.active = settings.use
            col.prop(settings, "filepath")
            if settings.filepath.lower().endswith(".raw"):
                col.prop(settings, "dims")
                col.prop(settings, "value_type")
                col.prop(settings, "little_endian")
        col = layout.column(align=True)
        col.prop(settings, "auto_range")
        sub = col.row(align=True)
        sub.active = not settings.auto_range
        sub.prop(settings, "range_min")
        sub.prop(settings, "range_max")


def draw_transfer_function(layout, item):
    """The camera item's transfer function: its texture and colour ramp (panels.py)."""
    layout.template_ID(item, "transfer_function", new="multiscale.transfer_function_new")
    tex = item.transfer_function
    if tex is None:
        layout.label(text="Default transfer function", icon="INFO")
    elif not tex.use_color_ramp:
        layout.prop(tex, "use_color_ramp", text="Use Colour Ramp")
    else:
        layout.template_color_ramp(tex, "color_ramp", expand=True)


CLASSES = (
    MultiscaleVolumeSettings,
    MULTISCALE_OT_transfer_function_new,
    MULTISCALE_PT_object_volume,
)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.multiscale_volume = bpy.props.PointerProperty(type=MultiscaleVolumeSettings)


def unregister():
    del bpy.types.Object.multiscale_volume
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
