"""Operators ``multiscale.*``: editing the camera list, checking the rig, rendering."""

import time

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..adapters.scene import rig_from_scene
from ..core.errors import RigError, SolverDidNotConverge
from ..core.report import build_report, headline, to_json
from ..render import pipeline
from ..render.volume import prepare_volumes


def _settings(context):
    return context.scene.multiscale


def _evaluated(context):
    """The scene as the depsgraph evaluates it: object matrices up to date."""
    return context.evaluated_depsgraph_get().scene


class MULTISCALE_OT_camera_add(bpy.types.Operator):
    """Add the selected cameras (or the active one) to the end of the list, or an empty
    item to fill in when no camera is selected"""

    bl_idname = "multiscale.camera_add"
    bl_label = "Add Camera"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        settings = _settings(context)
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
        return len(_settings(context).cameras) > 0

    def execute(self, context):
        settings = _settings(context)
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
        return len(_settings(context).cameras) > 1

    def execute(self, context):
        settings = _settings(context)
        i = settings.active_index
        j = i - 1 if self.direction == "UP" else i + 1
        if not 0 <= j < len(settings.cameras):
            return {"CANCELLED"}
        settings.cameras.move(i, j)
        settings.active_index = j
        return {"FINISHED"}


class MULTISCALE_OT_validate(bpy.types.Operator):
    """Check the camera list and masks and say what would stop or spoil a render"""

    bl_idname = "multiscale.validate"
    bl_label = "Check Rig"

    def execute(self, context):
        try:
            rig = rig_from_scene(_evaluated(context))
            # volume sources and transfer functions too: a missing file shows here
            _volumes, said = prepare_volumes(context.evaluated_depsgraph_get())
        except RigError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        for notice in list(rig.notices) + said:
            self.report({"WARNING"}, notice)
        self.report({"INFO"}, f"The rig of {len(rig.cameras)} cameras is ready to render")
        return {"FINISHED"}


class MULTISCALE_OT_compute_field(bpy.types.Operator):
    """Build the ray field of the camera list (or reuse the cached one) and measure it:
    preserved-ray error per camera, folds, timings. The report is kept in the scene"""

    bl_idname = "multiscale.compute_field"
    bl_label = "Compute Field"

    def execute(self, context):
        scene = context.scene
        start = time.perf_counter()
        try:
            fld, built = pipeline.build_field(_evaluated(context))
        except (RigError, SolverDidNotConverge) as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        report = build_report(fld, scene.multiscale.quality, sum(fld.seconds.values()))
        report["cached"] = not built
        scene.multiscale.report = to_json(report)
        for notice in fld.notices + fld.warnings:
            self.report({"WARNING"}, notice)
        line = headline(report)
        self.report(
            {"INFO"},
            f"{line} ({'built' if built else 'cached'}, {time.perf_counter() - start:.1f} s)",
        )
        return {"FINISHED"}


class MULTISCALE_OT_render(bpy.types.Operator):
    """Render the multiscale image into Render Result with the Multiscale engine"""

    bl_idname = "multiscale.render"
    bl_label = "Render Multiscale"

    write_still: BoolProperty(
        name="Write Image", default=False, description="Save the image to the output path"
    )

    def execute(self, context):
        scene = context.scene
        try:
            rig_from_scene(_evaluated(context))
        except RigError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        if scene.render.engine != "MULTISCALE":
            scene.render.engine = "MULTISCALE"
            self.report({"INFO"}, "Render engine set to Multiscale")
        if scene.camera is None:
            # Blender refuses to render a scene without an active camera
            scene.camera = scene.multiscale.cameras[0].camera
            self.report({"INFO"}, f"Scene camera set to '{scene.camera.name}'")
        if bpy.app.background:
            bpy.ops.render.render(write_still=self.write_still)
        else:
            bpy.ops.render.render("INVOKE_DEFAULT", write_still=self.write_still)
        return {"FINISHED"}


class MULTISCALE_OT_export_rays(bpy.types.Operator):
    """Write every pixel's first-hit ray (origin, direction, hit distance, membership) as a
    multi-channel EXR, and the bent rays' polylines beside it as .npz"""

    bl_idname = "multiscale.export_rays"
    bl_label = "Export Rays"

    filepath: StringProperty(
        name="File Path",
        subtype="FILE_PATH",
        default="",
        description="The EXR to write; the polylines go to the same name with .npz",
    )
    filter_glob: StringProperty(default="*.exr", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        scene = getattr(context, "scene", None)
        if scene is None or len(scene.multiscale.cameras) == 0:
            cls.poll_message_set("Add cameras to the Multiscale camera list first")
            return False
        return True

    def invoke(self, context, _event):
        if not self.filepath:
            self.filepath = bpy.path.ensure_ext(bpy.path.abspath("//rays") or "rays", ".exr")
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from ..io.exr import ExrError
        from ..io.rays import export_rays

        if not self.filepath:
            self.report({"ERROR"}, "Export Rays needs a file path")
            return {"CANCELLED"}
        path = bpy.path.ensure_ext(bpy.path.abspath(self.filepath), ".exr")
        try:
            frame = pipeline.prepare_frame(context.evaluated_depsgraph_get())
            exr_path, npz_path = export_rays(frame, path)
        except (RigError, SolverDidNotConverge, ExrError, OSError) as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        for notice in frame.notices:
            self.report({"WARNING"}, notice)
        width, height = frame.size
        self.report({"INFO"}, f"Wrote {width}x{height} rays to {exr_path} and {npz_path}")
        return {"FINISHED"}


CLASSES = (
    MULTISCALE_OT_camera_add,
    MULTISCALE_OT_camera_remove,
    MULTISCALE_OT_camera_move,
    MULTISCALE_OT_validate,
    MULTISCALE_OT_compute_field,
    MULTISCALE_OT_render,
    MULTISCALE_OT_export_rays,
)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
