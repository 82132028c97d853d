"""Operators ``multiscale.*``: editing the camera list, checking the rig, rendering."""

import time

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from ..adapters.scene import field_settings, rig_from_scene
from ..core.errors import RigError, SolverDidNotConverge
from ..core.quality import build_report, headline, to_json
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
        ok, _rig, _messages = run_validation(self, context)
        return {"FINISHED"} if ok else {"CANCELLED"}


def store_validation(settings, errors, warnings):
    """Keep a check's messages in ``scene.multiscale.validation`` for the panel."""
    import json

    settings.validation = json.dumps(
        [{"level": "ERROR", "text": t} for t in errors]
        + [{"level": "WARNING", "text": t} for t in warnings]
    )


def run_validation(op, context):
    """Every check of the rig (``render.checks.validate_scene``), reported through the
    operator ``op`` and kept for the panel. Returns (ok, rig or None, warnings)."""
    from ..render.checks import validate_scene

    settings = _settings(context)
    try:
        rig, messages = validate_scene(context.evaluated_depsgraph_get())
        # volume sources and transfer functions too: a missing file shows here
        _volumes, said = prepare_volumes(context.evaluated_depsgraph_get())
        messages = list(messages) + list(said)
    except RigError as err:
        store_validation(settings, [str(err)], [])
        op.report({"ERROR"}, str(err))
        return False, None, []
    store_validation(settings, [], messages)
    for notice in messages:
        op.report({"WARNING"}, notice)
    if not messages:
        op.report({"INFO"}, f"The rig of {len(rig.cameras)} cameras is ready to render")
    return True, rig, messages


class MULTISCALE_OT_compute_field(bpy.types.Operator):
    """Build the ray field of the camera list (or reuse the cached one) and measure it:
    preserved-ray error per camera, folds, timings. The report is kept in the scene.
    Checks the rig first; in a window the build runs in the background (Esc cancels)"""

    bl_idname = "multiscale.compute_field"
    bl_label = "Compute Field"

    _job = None
    _timer = None

    def execute(self, context):
        request = self._request(context)
        if request is None:
            return {"CANCELLED"}
        if request.field is None:
            try:
                request.run()
            except (RigError, SolverDidNotConverge) as err:
                self.report({"ERROR"}, str(err))
                return {"CANCELLED"}
        return self._finish(context, request)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        request = self._request(context)
        if request is None:
            return {"CANCELLED"}
        if request.field is not None:
            return self._finish(context, request)
        self._job = BuildJob(request)
        self._job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        context.workspace.status_text_set("Multiscale: building the ray field (Esc cancels)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            # everything else goes on to Blender: the build must not block the interface
            return {"PASS_THROUGH"}
        context.window_manager.progress_update(job.progress())
        if job.alive():
            return {"RUNNING_MODAL"}
        return self._done(context)

    def _done(self, context):
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)
        job = self._job
        if job.cancelled:
            self.report({"WARNING"}, "Field build cancelled; nothing was changed")
            return {"CANCELLED"}
        if job.error is not None:
            self.report({"ERROR"}, str(job.error))
            return {"CANCELLED"}
        return self._finish(context, job.request)

    def _request(self, context):
        ok, rig, _messages = run_validation(self, context)
        return FieldRequest(_settings(context), rig) if ok else None

    def _finish(self, context, request):
        from . import preview

        scene = context.scene
        fld, built = request.field, request.built
        if built:
            failed = request.store()
            if failed:
                self.report({"WARNING"}, failed)
        report = request.report
        if report is None:  # a field cached without its report: measure it once
            report = build_report(fld, scene.multiscale.quality, sum(fld.seconds.values()))
            fld.report = dict(report)
        report["cached"] = not built
        scene.multiscale.report = to_json(report)
        for notice in fld.warnings:
            self.report({"WARNING"}, notice)
        if request.gave_up:
            self.report({"WARNING"}, pipeline.WORKERS_GIVEN_UP)
        self.report(
            {"INFO"},
            f"{headline(report)} ({'built' if built else 'cached'}, "
            f"{time.perf_counter() - request.start:.1f} s)",
        )
        preview.update(scene, fld)
        return {"FINISHED"}


class FieldRequest:
    """A field build asked for by the operator: the rig and settings read from the scene
    on the main thread; ``run`` (any thread, numpy only) builds the field and its report.

    Attributes
    ----------
    field : RayField or None (None until built; set at once on a cache hit).
    built : bool. report : dict or None.
    """

    def __init__(self, settings_group, rig):
        from ..core.methods import field_key
        from ..io import cache

        self.start = time.perf_counter()
        self.rig = rig
        self.method = settings_group.method
        self.quality = settings_group.quality
        self.settings = field_settings(settings_group.id_data)
        self.key = field_key(rig, self.method, self.settings)
        self.cache = cache.CACHE
        self.cache.limit_mb = float(settings_group.cache_limit_mb)
        _ = self.cache.folder  # found on the main thread (it asks bpy)
        self.field = self.cache.get(self.key, rig)
        self.built = False
        self.report = None
        # whether the build's worker processes were given up (it went on in-process)
        self.gave_up = False
        if self.field is not None:
            self.field.notices = list(rig.notices)
            # the report measured when the field was built (measuring takes a while)
            kept = getattr(self.field, "report", None)
            self.report = dict(kept) if kept is not None else None

    def run(self, should_stop=None):
        from ..core import parallel
        from ..core.methods import prepare

        given_up = parallel.given_up()
        fld = prepare(self.rig, self.method, self.settings, should_stop)
        self.gave_up = parallel.given_up() > given_up
        fld.notices = list(self.rig.notices)
        self.report = build_report(fld, self.quality, time.perf_counter() - self.start)
        fld.report = self.report
        self.field, self.built = fld, True

    def store(self):
        return self.cache.put(self.key, self.field)


class BuildJob:
    """``FieldRequest.run`` on a worker thread. The thread touches no bpy: it reads the
    request's numpy rig and writes its result into the request; the modal operator
    polls ``alive`` on a timer and finishes on the main thread."""

    def __init__(self, request):
        import threading

        self.request = request
        self.cancelled = False
        self.error = None
        self._stop = threading.Event()
        self._checks = 0
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _should_stop(self):
        self._checks += 1
        return self._stop.is_set()

    def _run(self):
        from ..core.errors import Cancelled

        try:
            self.request.run(self._should_stop)
        except Cancelled:
            self.cancelled = True
        except Exception as err:  # handed to the main thread, reported there
            self.error = err

    def start(self):
        self._thread.start()

    def alive(self):
        return self._thread.is_alive()

    def cancel(self):
        self._stop.set()

    def progress(self):
        """0..99: a rough measure (the build's checks for cancellation so far)."""
        return min(99, int(100 * (1 - 1 / (1 + self._checks / 40))))


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


def _item(context, index=-1):
    """The camera list item ``index`` (the active one when -1), or None."""
    settings = _settings(context)
    i = settings.active_index if index < 0 else index
    return settings.cameras[i] if 0 <= i < len(settings.cameras) else None


class MULTISCALE_OT_camera_select(bpy.types.Operator):
    """Select this camera in the viewport and make it the active object"""

    bl_idname = "multiscale.camera_select"
    bl_label = "Select Camera"
    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(default=-1, options={"SKIP_SAVE"})

    def execute(self, context):
        item = _item(context, self.index)
        if item is None or item.camera is None:
            self.report({"ERROR"}, "This list item has no camera: pick one first")
            return {"CANCELLED"}
        obj = item.camera
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
            _settings(context).active_index = self.index
        return {"FINISHED"}


class MULTISCALE_OT_camera_view(bpy.types.Operator):
    """Look through this camera: make it the scene camera and show its view"""

    bl_idname = "multiscale.camera_view"
    bl_label = "Look Through"
    bl_options = {"REGISTER", "UNDO"}

    index: IntProperty(default=-1, options={"SKIP_SAVE"})

    def execute(self, context):
        item = _item(context, self.index)
        if item is None or item.camera is None:
            self.report({"ERROR"}, "This list item has no camera: pick one first")
            return {"CANCELLED"}
        context.scene.camera = item.camera
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


MASK_SUFFIX = " mask"
GUIDE_SUFFIX = " guide"


def _render_guide(context, obj, scene):
    """The camera's own view as an image: the viewport's Workbench drawing offscreen where
    a GPU context exists, else our solid raycast. Returns (image, how)."""
    from ..adapters.cameras import pinhole_from_object, render_size
    from ..adapters.lights import world_colour
    from ..adapters.masks import image_from_rgba
    from ..render.checks import scene_tree
    from ..render.guide import guide_size, solid_view

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
    import gpu
    import numpy as np

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
        item = _item(context)
        if item is None or item.camera is None:
            cls.poll_message_set("Pick a camera in the Multiscale list first")
            return False
        return True

    def execute(self, context):
        from ..adapters.cameras import render_size
        from ..adapters.masks import new_mask_image

        scene = context.scene
        item = _item(context)
        obj = item.camera
        if obj.type != "CAMERA":
            self.report({"ERROR"}, f"'{obj.name}' is not a camera; pick a camera object")
            return {"CANCELLED"}
        width, height = render_size(scene)
        item.mask = new_mask_image(obj.name + MASK_SUFFIX, width, height)
        how = "no guide"
        if self.guide:
            try:
                item.guide, how = _render_guide(context, obj, scene)
            except Exception as err:  # the mask is made; only the picture failed
                self.report({"WARNING"}, f"No guide picture for '{obj.name}': {err}")
        self.report(
            {"INFO"},
            f"Mask '{item.mask.name}' ({width}x{height}) made for '{obj.name}' ({how}); "
            "paint white where its view is kept",
        )
        return {"FINISHED"}


class MULTISCALE_OT_mask_paint(bpy.types.Operator):
    """Open the active camera's mask in an Image Editor in Paint mode, white brush, its
    guide shown underneath"""

    bl_idname = "multiscale.mask_paint"
    bl_label = "Paint Mask"

    @classmethod
    def poll(cls, context):
        item = _item(context)
        if bpy.app.background or context.window is None:
            cls.poll_message_set("Painting needs a Blender window (not available in background)")
            return False
        if item is None or item.mask is None:
            cls.poll_message_set("Make a mask for the active camera first (New Mask)")
            return False
        return True

    def execute(self, context):
        item = _item(context)
        area = _image_editor_area(context)
        if area is None:
            self.report({"ERROR"}, "No area could be turned into an Image Editor")
            return {"CANCELLED"}
        space = area.spaces.active
        space.image = item.mask
        space.ui_mode = "PAINT"
        _white_brush(context, area)
        area.tag_redraw()
        self.report({"INFO"}, f"Painting '{item.mask.name}': white keeps the view, black hides")
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


class MULTISCALE_OT_report_show(bpy.types.Operator):
    """Show the last build report in full (also kept in the text 'Multiscale Report')"""

    bl_idname = "multiscale.report_show"
    bl_label = "Full Report"

    lines = []

    @classmethod
    def poll(cls, context):
        return bool(_settings(context).report)

    def execute(self, context):
        import json

        from ..core.quality import readable

        try:
            report = json.loads(_settings(context).report)
        except ValueError:
            self.report({"ERROR"}, "The stored report is not readable; compute the field again")
            return {"CANCELLED"}
        text = bpy.data.texts.get(REPORT_TEXT) or bpy.data.texts.new(REPORT_TEXT)
        self.lines = readable(report)
        text.from_string("\n".join(self.lines) + "\n\n" + _settings(context).report + "\n")
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
        from ..io import cache

        size = cache.CACHE.size_bytes()
        removed = cache.CACHE.clear()
        self.report({"INFO"}, f"Removed {removed} cached fields ({size / 1e6:.1f} MB)")
        return {"FINISHED"}


CLASSES = (
    MULTISCALE_OT_camera_add,
    MULTISCALE_OT_camera_remove,
    MULTISCALE_OT_camera_move,
    MULTISCALE_OT_validate,
    MULTISCALE_OT_compute_field,
    MULTISCALE_OT_render,
    MULTISCALE_OT_export_rays,
    MULTISCALE_OT_camera_select,
    MULTISCALE_OT_camera_view,
    MULTISCALE_OT_mask_new,
    MULTISCALE_OT_mask_paint,
    MULTISCALE_OT_report_show,
    MULTISCALE_OT_cache_clear,
)


@bpy.app.handlers.persistent
def repack_masks(*_args):
    """Before a save: pack masks and guides that were painted (a packed image keeps its
    packed pixels otherwise, and a painted mask would revert on reload), and images made
    in Blender, painted and never saved anywhere (a generated image is saved only as its
    generator settings). Painted images that live in their own files are left alone."""
    for scene in bpy.data.scenes:
        settings = getattr(scene, "multiscale", None)
        for item in settings.cameras if settings is not None else ():
            for image in (item.mask, item.guide):
                if image is None:
                    continue
                if image.is_dirty and (image.packed_file or image.source == "GENERATED"):
                    image.pack()


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.app.handlers.save_pre.append(repack_masks)


def unregister():
    if repack_masks in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(repack_masks)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
