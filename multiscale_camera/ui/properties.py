"""Scene settings: ``bpy.types.Scene.multiscale`` and its camera list.

The names here are a public contract (docs/architecture.md): users' scripts and tests set
``scene.multiscale.cameras``, ``method``, ``quality`` and friends directly.
"""

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from . import preview

METHOD_ITEMS = [
    ("AUTO", "Auto", "The cheapest method that meets the accuracy target on this rig"),
    ("IMAGE_BLEND", "Image Blend", "Blend each pixel's curved rays by harmonic mask weights"),
    ("LINEAR", "Linear", "Linear interpolation of ray directions between preserved regions"),
    ("VECTOR_FIELD", "Vector Field", "Smooth the tangent vectors directly (paper eq. 3)"),
    (
        "SCALAR_FIELD",
        "Scalar Field",
        "Smooth a membership field and blend tangent fields (paper eq. 5, 6)",
    ),
]

# The cheapest method that meets the accuracy target on the rig, and says why
# (docs/methods.md, docs/report.md).
DEFAULT_METHOD = "AUTO"

QUALITY_ITEMS = [
    ("PREVIEW", "Preview", "Fast; about 2 px accuracy"),
    ("STANDARD", "Standard", "About 0.5 px accuracy"),
    ("HIGH", "High", "About 0.25 px accuracy"),
    ("CUSTOM", "Custom", "Use the accuracy given in pixels"),
]

SHADING_ITEMS = [
    ("SOLID", "Solid", "Multiscale Camera's own shading: base colour, lights and shadows"),
    ("CYCLES", "Cycles", "Hand the bent rays to Cycles (Blender 4.5+)"),
]


def _preview_toggled(self, context):
    preview.update(context.scene)


def _pack_mask(self, _context):
    """Keep a mask loaded from a file (PNG, EXR, ... from another tool) inside the .blend,
    so the render does not depend on the file staying where it was. A movie (never
    packed) plays its own length, as Blender's image users set it when one is opened."""
    image = self.mask
    if image is not None and image.source == "MOVIE" and image.frame_duration > 0:
        self.mask_frames = image.frame_duration
    if image is not None and image.packed_file is None and image.source == "FILE":
        try:
            image.pack()
        except RuntimeError as err:  # a missing file: the rig check reports the mask
            print(f"Multiscale: mask '{image.name}' could not be packed ({err})")


def _poll_camera(_self, obj):
    return obj.type == "CAMERA"


class MultiscaleCameraItem(bpy.types.PropertyGroup):
    camera: PointerProperty(
        name="Camera",
        type=bpy.types.Object,
        poll=_poll_camera,
        description="A perspective camera; the list runs from the largest scale to the smallest",
    )
    mask: PointerProperty(
        name="Mask",
        type=bpy.types.Image,
        description="White where this camera's view is preserved in the final image",
        update=_pack_mask,
    )
    transfer_function: PointerProperty(
        name="Transfer Function",
        type=bpy.types.Texture,
        description="Colour ramp from density to colour and opacity, for volumes",
    )
    guide: PointerProperty(
        name="Guide",
        type=bpy.types.Image,
        description="This camera's own view, shown under the mask while it is painted",
    )
    guide_key: StringProperty(
        name="Guide Key",
        default="",
        description="The camera, lens and resolution the guide was made for (stale when "
        "they change)",
    )
    previous_mask: PointerProperty(
        name="Previous Mask",
        type=bpy.types.Image,
        description="The mask New Mask replaced, kept to be put back",
    )
    # An image sequence or movie as the mask plays as Blender's image users play it.
    mask_frames: IntProperty(
        name="Frames",
        default=100,
        min=0,
        description="Frames of the mask's image sequence or movie to play (as an image "
        "user's Frames)",
    )
    mask_frame_start: IntProperty(
        name="Start",
        default=1,
        description="Scene frame at which the mask's image sequence or movie starts playing",
    )
    mask_frame_offset: IntProperty(
        name="Offset",
        default=0,
        description="Added to the sequence's or movie's frame number (the file or movie "
        "frame read is numbered 1 + offset at the start frame)",
    )
    mask_cyclic: BoolProperty(
        name="Cyclic",
        default=False,
        description="Play the mask's image sequence or movie again after its last frame",
    )


# Paths that may start with "//" (Blender 5 warns without the option, which older ones may lack).
BLEND_RELATIVE = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (5, 0, 0) else set()


class MultiscaleSettings(bpy.types.PropertyGroup):
    cameras: CollectionProperty(type=MultiscaleCameraItem)
    active_index: IntProperty(name="Active Camera", default=0, min=0)
    method: EnumProperty(
        name="Method",
        items=METHOD_ITEMS,
        default=DEFAULT_METHOD,
        description="How the bent rays are generated",
    )
    quality: EnumProperty(
        name="Quality",
        items=QUALITY_ITEMS,
        default="STANDARD",
        description="Accuracy target of the ray field",
    )
    accuracy_px: FloatProperty(
        name="Accuracy",
        default=0.5,
        min=0.01,
        max=16.0,
        subtype="PIXEL",
        description="Target preserved-ray error in pixels (used as is under Custom quality)",
    )
    beta: FloatProperty(
        name="Beta",
        default=0.2,
        min=0.01,
        max=0.5,
        description="Handle length of the Bezier guides, as a fraction of the distance "
        "between near planes",
    )
    samples: IntProperty(name="Samples", default=1, min=1, max=256, description="Rays per pixel")
    shading: EnumProperty(name="Shading", items=SHADING_ITEMS, default="SOLID")
    simplify_px: FloatProperty(
        name="Ray Simplify",
        default=0.25,
        min=0.0,
        max=8.0,
        subtype="PIXEL",
        description="How far, in pixels, the straight segments cast for a bent ray may "
        "stray from it; larger renders faster (0.25 is below what a pixel shows)",
    )
    report: StringProperty(
        name="Report", default="", description="JSON report of the last field build"
    )
    volume_step: FloatProperty(
        name="Volume Step",
        default=1.0,
        min=0.1,
        max=8.0,
        description="Distance between volume samples along a ray, in voxels; opacity is "
        "corrected for it, so a larger step is faster and coarser",
    )
    volume_shading: BoolProperty(
        name="Volume Shading",
        default=True,
        description="Shade volume samples by the data's gradient (a light at the eye)",
    )
    validation: StringProperty(
        name="Validation",
        default="",
        description="JSON list of the messages of the last check of the rig",
    )
    cache_limit_mb: IntProperty(
        name="Cache Limit",
        default=2048,
        min=16,
        max=1 << 20,
        description="Size limit of the field cache on disk, in MB of 1,048,576 bytes as "
        "Blender counts them (oldest fields go first)",
    )
    memory_budget_mb: IntProperty(
        name="Memory Budget",
        default=0,
        min=0,
        max=1 << 24,
        description="Most memory, in MB of 1,048,576 bytes as Blender counts them, that a "
        "field build or a render may add: beyond what Blender holds already, plus what its "
        "worker processes take; larger work is refused before it starts, saying what to "
        "lower. 0: what the machine has free, less a margin (at least 256 MB)",
    )
    guide_opacity: FloatProperty(
        name="Guide Opacity",
        default=0.5,
        min=0.0,
        max=1.0,
        subtype="FACTOR",
        description="Opacity of the camera's view drawn over its mask in the Image Editor",
    )
    auto_guide: BoolProperty(
        name="Update Guide Automatically",
        default=True,
        description="Remake the guide of a mask shown in an Image Editor about a second "
        "after its camera, lens or the render size changed",
    )
    show_mask_overlay: BoolProperty(
        name="Other Masks",
        default=True,
        description="Draw the other cameras' masks, the transition bands and the mask "
        "warnings over the mask in the Image Editor",
    )
    overlay_opacity: FloatProperty(
        name="Overlay Opacity",
        default=0.35,
        min=0.0,
        max=1.0,
        subtype="FACTOR",
        description="Opacity of the other cameras' masks and the transition bands",
    )
    live_picture: BoolProperty(
        name="Live Picture",
        default=True,
        description="While a mask is shown in an Image Editor, remake a small PREVIEW "
        "render of the multiscale image in the background after each stroke or camera "
        "move (the image 'Multiscale Live', and in the editor's corner)",
    )
    cache_folder: StringProperty(
        name="Cache Folder",
        default="",
        subtype="DIR_PATH",
        options=BLEND_RELATIVE,
        description="Folder of this scene's field cache ('//' = the .blend's folder, so "
        "render farm workers share it with the file); empty: the extension's user folder",
    )
    show_preview: BoolProperty(
        name="Ray Preview",
        default=False,
        description="Draw a sparse grid of the bent rays and the chained frusta in the viewport",
        update=_preview_toggled,
    )
    preview_rays: IntProperty(
        name="Preview Rays",
        default=12,
        min=2,
        max=64,
        description="Rays drawn per image side in the ray preview",
        update=_preview_toggled,
    )


CLASSES = (MultiscaleCameraItem, MultiscaleSettings)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.multiscale = PointerProperty(type=MultiscaleSettings)


def unregister():
    del bpy.types.Scene.multiscale
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
