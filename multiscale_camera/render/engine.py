"""The ``MULTISCALE`` render engine: a thin shell around ``pipeline``."""

import time
from contextlib import contextmanager

import bpy
import numpy as np

from ..core.diagnostics import Diagnostics, interrupt_stops
from ..core.errors import Cancelled
from . import cycles, pipeline, viewport, workers
from .failures import failure_message
from .fields import SERVICE, publish_report

# What a render stopped by Ctrl-C says (it writes nothing, and `-f` exits 1).
INTERRUPTED = "Render cancelled (Ctrl-C); nothing was written"


class MultiscaleRenderEngine(bpy.types.RenderEngine):
    bl_idname = "MULTISCALE"
    bl_label = "Multiscale"
    bl_use_postprocess = True
    bl_use_preview = False

    def render(self, depsgraph):
        """Render the frame; any error ends it with one message (``fail``), so that
        Blender writes no file and the render operator does not finish. Ctrl-C in
        background mode stops it as Esc does in the window, and writes nothing."""
        with interrupt_stops() as interrupted:
            self._interrupted = interrupted
            try:
                self._render(depsgraph)
            except Cancelled:
                if interrupted.is_set():
                    self.fail(f"Multiscale: {INTERRUPTED}")
            except Exception as err:  # every failure is said, never a traceback alone
                self.fail(f"Multiscale: {failure_message(err)}")

    def should_stop(self):
        """Esc (``test_break``), or Ctrl-C during this render."""
        return self.test_break() or self._interrupted.is_set()

    @contextmanager
    def ctrl_c_to_blender(self):
        """For a call into Blender's C code that polls Blender's break flag and runs no
        Python until it ends (Cycles' own render): Ctrl-C goes to Blender's own handler
        (``Interrupt.to_host``; in `blender -b` it sets that flag), and a break heard in
        background mode is then this render's Ctrl-C."""
        try:
            with self._interrupted.to_host():
                yield
        finally:
            if bpy.app.background and self.test_break():
                self._interrupted.set()

    def _render(self, depsgraph):
        start = time.perf_counter()
        self.update_stats("", "Multiscale: building rays")
        diag = Diagnostics(should_stop=self.should_stop)
        try:  # the scene's report is the field's, measured once: none when it failed
            frame = pipeline.prepare_frame(depsgraph, diag, report=True)
        except Cancelled:
            raise
        except Exception:
            publish_report(depsgraph.scene, None)
            raise
        scene = depsgraph.scene
        publish_report(scene, frame.report)  # again with the frame's jump once rendered
        print(pipeline.rebuilt_line(frame.rebuilt))
        reported = self.say(diag, 0)
        if scene.multiscale.shading == "CYCLES":
            if cycles.render(self, depsgraph, frame):
                if self._interrupted.is_set():  # the hand-off stopped for Ctrl-C: fail
                    raise Cancelled()
                return
        width, height = frame.size
        for name, channels, chan_id, _kind in pipeline.PASSES[1:]:
            self.add_pass(name, channels, chan_id)
        processes = workers.worker_count(frame.processes)
        shown = ShownRows(height, width)
        hits = np.zeros((height, width, pipeline.HIT_PASS[1]), dtype=np.float32)
        with diag.stage("render"):
            for (row0, row1), passes in workers.render_tiles(
                frame, pipeline.tiles(frame), processes, self.should_stop
            ):
                hits[row0:row1] = passes[pipeline.HIT_PASS[0]]
                if shown.add(row0, row1, passes):
                    self.show(shown, frame, diag)
                # what the tile loop had to say (workers given up) is said at once
                reported = self.say(diag, reported)
            self.show(shown, frame, diag)
        sequence = SERVICE.sequence
        index = sequence.object_index(frame.geometry.object_names, hits[..., 3])
        render_key = (bpy.data.filepath, scene.name, depsgraph.view_layer.name)
        step = max(1, scene.frame_step)
        jump = sequence.add(render_key, scene.frame_current, step, index, hits[..., :3])
        publish_report(scene, with_frame(frame.report, jump.as_dict()))
        if jump.px is not None:
            print(
                f"Multiscale: frame {scene.frame_current}: first hits moved {jump.px:.3f} px "
                f"(p95) since frame {scene.frame_current - max(1, scene.frame_step)}; worst "
                f"of the sequence {jump.worst_px:.3f} px at frame {jump.worst_frame}"
            )
        seconds = time.perf_counter() - start
        print(
            f"Multiscale: {width}x{height}, {frame.samples} samples, {frame.rays} rays, "
            f"{frame.casts} segment casts, {frame.shadow_casts} shadow casts, {seconds:.2f} s "
            f"({', '.join(f'{k} {v:.2f} s' for k, v in frame.seconds.items())})"
        )

    def say(self, diag, reported):
        """Report the messages ``diag`` has said since the first ``reported``; returns
        how many it has said in all."""
        for message in diag.since(reported):  # Level names are Blender's report types
            self.report({message.level.name}, f"Multiscale: {message.text}")
        return len(diag.messages)

    def show(self, shown, frame, diag):
        """Write the tiles ``shown`` holds into the Render Result, with the progress and
        the status text."""
        rows = shown.take()
        if rows is None:
            return
        row0, row1, passes = rows
        self.write_rows(passes, row0, row1, shown.height, shown.width)
        self.update_progress(row1 / shown.height)
        self.update_stats("", stats_line(frame, row1, shown.height, diag))

    def write_rows(self, passes, row0, row1, height, width):
        """Write image rows (row 0 at the top) into the Render Result (rows bottom-up)."""
        result = self.begin_result(0, height - row1, width, row1 - row0)
        layer = result.layers[0]
        for render_pass in layer.passes:
            data = passes.get(render_pass.name)
            if data is None and render_pass.name == "Object Index":
                data = passes["IndexOB"]
            if data is not None and data.shape[-1] == render_pass.channels:
                render_pass.rect.foreach_set(data[::-1].ravel())
        self.end_result(result)

    def fail(self, message):
        """End the render as failed. The ERROR report is what stops Blender from saving
        the image and makes the render operator raise (bpy 5.0.1 wheel and Blender);
        ``error_set`` alone still saves it. Both: the message shows in the render
        window too."""
        self.report({"ERROR"}, message)
        self.error_set(message)

    # --- the viewport's Rendered shading (render/viewport.py) ---------------------------

    def view_update(self, context, depsgraph):
        self._viewport().update()

    def view_draw(self, context, depsgraph):
        self._viewport().draw(self, context, depsgraph)

    def _viewport(self):
        if getattr(self, "_view", None) is None:
            self._view = viewport.ViewDraw()
        return self._view

    def update_render_passes(self, scene=None, renderlayer=None):
        for name, channels, chan_id, kind in pipeline.PASSES:
            self.register_pass(scene, renderlayer, name, channels, chan_id, kind)


# Least seconds between two updates of the Render Result while tiles come in. Blender
# redraws its window after each update (result, progress or status text); in a window
# drawn by software OpenGL a redraw costs tens of milliseconds of CPU that the render's
# workers need (measured on the demo: 0.7 CPU s of drawing per 4 s render at one
# update a tile, docs/performance.md).
SHOW_SECONDS = 1.0


class ShownRows:
    """Tiles done but not yet written into the Render Result: ``add`` them as they come
    (in order, row 0 at the top) and ``take`` the rows they cover, at most once every
    ``SHOW_SECONDS`` (the first tile at once).

    height, width : int, the image's size in pixels.
    """

    def __init__(self, height, width, seconds=SHOW_SECONDS):
        self.height, self.width, self.seconds = height, width, seconds
        self.pending = []  # [(row0, row1, passes)], in order
        self.last = None  # time.perf_counter() of the last take

    def add(self, row0, row1, passes):
        """Keep tile ``row0 .. row1 - 1``'s ``passes`` (dict name -> (rows, W, C)
        float32); True when it is time to show what is kept."""
        self.pending.append((row0, row1, passes))
        now = time.perf_counter()
        return self.last is None or now - self.last >= self.seconds

    def take(self):
        """(row0, row1, passes) of every kept tile, joined (None when none is kept)."""
        if not self.pending:
            return None
        self.last = time.perf_counter()
        tiles, self.pending = self.pending, []
        if len(tiles) == 1:
            return tiles[0]
        names = tiles[0][2].keys()
        passes = {name: np.concatenate([t[2][name] for t in tiles]) for name in names}
        return tiles[0][0], tiles[-1][1], passes


def with_frame(report, jump):
    """``report`` (None: no report) with ``jump`` (``Sequence.add``'s, as a dict) in its
    ``frame`` record (docs/report.md)."""
    if report is None:
        return None
    return dict(report, frame=dict(report.get("frame", {}), **jump))


def stats_line(frame, row, height, diag):
    """The engine's status text: rows done, rays and segment casts per second of the
    tile loop so far (``diag``'s running "render" stage)."""
    seconds = max(diag.running_seconds("render"), 1e-9)
    return (
        f"Multiscale: {row}/{height} rows | {frame.rays / seconds / 1e6:.2f} M rays/s | "
        f"{frame.casts / seconds / 1e6:.2f} M segment casts/s"
    )


# Blender's own property panels that should show for this engine too.
_SHARED_PANEL_ENGINES = {"BLENDER_RENDER"}


def _compatible_panels():
    for panel in bpy.types.Panel.__subclasses__():
        engines = getattr(panel, "COMPAT_ENGINES", None)
        if engines and engines & _SHARED_PANEL_ENGINES:
            yield panel


@bpy.app.handlers.persistent  # kept across file loads: it is what runs after them
def forget_sequence_on_load(*_args):
    """A loaded file's first frame starts a sequence of its own (``render.sequence``)."""
    SERVICE.forget_sequence()


def register():
    bpy.utils.register_class(MultiscaleRenderEngine)
    if forget_sequence_on_load not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(forget_sequence_on_load)
    for panel in _compatible_panels():
        panel.COMPAT_ENGINES.add(MultiscaleRenderEngine.bl_idname)


def unregister():
    if forget_sequence_on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(forget_sequence_on_load)
    for panel in _compatible_panels():
        panel.COMPAT_ENGINES.discard(MultiscaleRenderEngine.bl_idname)
    bpy.utils.unregister_class(MultiscaleRenderEngine)
