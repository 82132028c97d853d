"""Operators that check the rig, build and measure its field, render, export the rays,
and show or clear what was built. Fields come from the field service
(``render.fields.SERVICE``)."""

import json

import bpy
from bpy.props import BoolProperty, StringProperty

from ..adapters.scene import rig_from_scene
from ..core.diagnostics import Diagnostics, interrupt_stops
from ..core.errors import Cancelled
from ..core.quality import headline, readable, size_text
from ..render import pipeline
from ..render.checks import validate_scene
from ..render.export import export_rays
from ..render.failures import failure_message
from ..render.fields import SERVICE, publish_report
from ..render.memory import MemoryBudgetError, guard_memory
from ..render.surface import scene_surface_errors, with_surface
from ..render.volume import prepare_volumes
from .context import evaluated_scene, settings_of


class MULTISCALE_OT_validate(bpy.types.Operator):
    """Check the camera list and masks and say what would stop or spoil a render"""

    bl_idname = "multiscale.validate"
    bl_label = "Check Rig"

    def execute(self, context):
        ok, _rig, _messages = run_validation(self, context)
        return {"FINISHED"} if ok else {"CANCELLED"}


def store_validation(settings, errors, warnings):
    """Keep a check's messages in ``scene.multiscale.validation`` for the panel."""
    settings.validation = json.dumps(
        [{"level": "ERROR", "text": t} for t in errors]
        + [{"level": "WARNING", "text": t} for t in warnings]
    )


def run_validation(op, context):
    """Every check of the rig (``render.checks.validate_scene``), reported through the
    operator ``op`` and kept for the panel. Returns (ok, rig or None, warnings)."""
    settings = settings_of(context)
    try:
        rig, messages = validate_scene(context.evaluated_depsgraph_get())
        # volume sources and transfer functions too: a missing file shows here
        _volumes, said = prepare_volumes(context.evaluated_depsgraph_get())
        messages = list(messages) + list(said)
    except Exception as err:  # a RigError says what to change; anything else, what failed
        message = failure_message(err, "Check Rig")
        store_validation(settings, [message], [])
        op.report({"ERROR"}, message)
        return False, None, []
    store_validation(settings, [], messages)
    for notice in messages:
        op.report({"WARNING"}, notice)
    if not messages:
        op.report({"INFO"}, f"The rig of {len(rig.cameras)} cameras is ready to render")
    return True, rig, messages


# What a cancelled build says (Esc in the window, Ctrl-C headless).
CANCELLED = "Field build cancelled; nothing was changed"


class MULTISCALE_OT_compute_field(bpy.types.Operator):
    """Build the ray field of the camera list (or reuse the cached one) and measure it:
    preserved-ray error per camera, folds, timings. The report is kept in the scene.
    Checks the rig first; in a window the build runs in the background (Esc cancels)"""

    bl_idname = "multiscale.compute_field"
    bl_label = "Compute Field"

    _build = None
    _diag = None
    _timer = None
    _checked = 0  # the rig check's messages at the start of ``_diag``

    def execute(self, context):
        # headless, Ctrl-C stops the build as Esc does in the window
        with interrupt_stops() as interrupted:
            request, diag = self._request(context, interrupted.is_set)
            if request is None:
                return {"CANCELLED"}
            try:
                result = SERVICE.get(request, diag, measure=True, announce=True)
            except Cancelled:
                self.report({"WARNING"}, CANCELLED)
                return {"CANCELLED"}
            except Exception as err:  # every failure is said, and leaves no old report
                return self._failed(context, err)
        return self._finish(context, result, diag)

    def _failed(self, context, err):
        publish_report(context.scene, None)
        self.report({"ERROR"}, failure_message(err, "Compute Field"))
        return {"CANCELLED"}

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        request, diag = self._request(context)
        if request is None:
            return {"CANCELLED"}
        if SERVICE.cached(request) is not None:
            return self._finish(context, SERVICE.get(request, diag, True, True), diag)
        self._build, self._diag = SERVICE.start(request, measure=True), diag
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        context.workspace.status_text_set("Multiscale: building the ray field (Esc cancels)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        build = self._build
        if event.type == "ESC" and event.value == "PRESS":
            build.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            # everything else goes on to Blender: the build must not block the interface
            return {"PASS_THROUGH"}
        context.window_manager.progress_update(build.progress())
        if build.alive():
            return {"RUNNING_MODAL"}
        return self._done(context)

    def _done(self, context):
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)
        build = self._build
        result = SERVICE.finish(build, self._diag)
        if build.cancelled:
            self.report({"WARNING"}, CANCELLED)
            return {"CANCELLED"}
        if build.error is not None:
            return self._failed(context, build.error)
        return self._finish(context, result, self._diag)

    def _request(self, context, should_stop=None):
        """(FieldRequest, Diagnostics with ``should_stop``) after the rig check and the
        memory guard, or (None, None). The check's warnings, reported already, start the
        Diagnostics so none is said twice."""
        ok, rig, messages = run_validation(self, context)
        if not ok:
            publish_report(context.scene, None)
            return None, None
        scene = evaluated_scene(context)
        request = SERVICE.request(scene, rig)
        try:  # before anything large is allocated
            guard_off = guard_memory(scene, request)
        except MemoryBudgetError as err:
            publish_report(context.scene, None)
            self.report({"ERROR"}, str(err))
            return None, None
        if guard_off:  # said once a session: no budget, nothing is refused
            self.report({"WARNING"}, guard_off)
        diag = Diagnostics(should_stop=should_stop)
        diag.extend(messages)
        self._checked = len(diag.messages)
        return request, diag

    def _finish(self, context, result, diag):
        # the rays' first hits in this scene: what the picture shows (docs/report.md)
        errors = scene_surface_errors(result.field, context.evaluated_depsgraph_get())
        report = with_surface(result.report, errors)
        publish_report(context.scene, report)
        for message in diag.since(self._checked):
            self.report({"WARNING"}, message.text)
        self.report(
            {"INFO"},
            f"{headline(report)} ({'built' if result.built else 'cached'}, {result.seconds:.1f} s)",
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
            rig_from_scene(evaluated_scene(context), frames=SERVICE.mask_frames)
        except Exception as err:
            self.report({"ERROR"}, failure_message(err, "Render Multiscale"))
            return {"CANCELLED"}
        if scene.render.engine != "MULTISCALE":
            scene.render.engine = "MULTISCALE"
            self.report({"INFO"}, "Render engine set to Multiscale")
        if scene.camera is None:
            # Blender refuses to render a scene without an active camera
            scene.camera = scene.multiscale.cameras[0].camera
            self.report({"INFO"}, f"Scene camera set to '{scene.camera.name}'")
        try:
            if bpy.app.background:
                bpy.ops.render.render(write_still=self.write_still)
            else:
                bpy.ops.render.render("INVOKE_DEFAULT", write_still=self.write_still)
        except RuntimeError as err:  # the engine's or Blender's own message, said once
            self.report({"ERROR"}, blender_error(err))
            return {"CANCELLED"}
        return {"FINISHED"}


def blender_error(err):
    """The text of the RuntimeError an operator raised with its ERROR reports, without
    Blender's "Error: " prefix: "Error: A\nError: B" -> "A; B"."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return "; ".join(line.removeprefix("Error: ") for line in lines)


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
        if not self.filepath:
            self.report({"ERROR"}, "Export Rays needs a file path")
            return {"CANCELLED"}
        path = bpy.path.ensure_ext(bpy.path.abspath(self.filepath), ".exr")
        try:
            # rays only: the guard weighs the build, not a render
            frame = pipeline.prepare_frame(context.evaluated_depsgraph_get(), render=False)
            exr_path, npz_path = export_rays(frame, path)
        except Exception as err:  # every failure is said, never a traceback
            self.report({"ERROR"}, failure_message(err, "Export Rays"))
            return {"CANCELLED"}
        for notice in frame.notices:
            self.report({"WARNING"}, notice)
        width, height = frame.size
        self.report({"INFO"}, f"Wrote {width}x{height} rays to {exr_path} and {npz_path}")
        return {"FINISHED"}


class MULTISCALE_OT_report_show(bpy.types.Operator):
    """Show the last build report in full (also kept in the text 'Multiscale Report')"""

    bl_idname = "multiscale.report_show"
    bl_label = "Full Report"

    lines = []

    @classmethod
    def poll(cls, context):
        return bool(settings_of(context).report)

    def execute(self, context):
        try:
            report = json.loads(settings_of(context).report)
        except ValueError:
            self.report({"ERROR"}, "The stored report is not readable; compute the field again")
            return {"CANCELLED"}
        text = bpy.data.texts.get(REPORT_TEXT) or bpy.data.texts.new(REPORT_TEXT)
        self.lines = readable(report)
        text.from_string("\n".join(self.lines) + "\n\n" + settings_of(context).report + "\n")
        return {"FINISHED"}

    def invoke(self, context, event):
        result = self.execute(context)
        if "FINISHED" in result:
            return context.window_manager.invoke_popup(self, width=620)
        return result

    def draw(self, context):
        col = self.layout.column(align=True)
        for line in self.lines:
            col.label(text=line)
        col.separator()
        col.label(text=f"In full (JSON): Text Editor > '{REPORT_TEXT}'", icon="TEXT")


REPORT_TEXT = "Multiscale Report"


class MULTISCALE_OT_cache_clear(bpy.types.Operator):
    """Delete every cached ray field (in memory and on disk); the next render rebuilds"""

    bl_idname = "multiscale.cache_clear"
    bl_label = "Clear Cache"

    def execute(self, context):
        size = SERVICE.cache.size_bytes()
        removed = SERVICE.clear()
        self.report({"INFO"}, f"Removed {removed} cached fields ({size_text(size)})")
        return {"FINISHED"}


CLASSES = (
    MULTISCALE_OT_validate,
    MULTISCALE_OT_compute_field,
    MULTISCALE_OT_render,
    MULTISCALE_OT_export_rays,
    MULTISCALE_OT_report_show,
    MULTISCALE_OT_cache_clear,
)
