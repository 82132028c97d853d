"""The live picture: while a mask is painted or a camera moves, a PREVIEW field and a
small render of the multiscale image are remade in the background
(``render.live.LiveJob``) and shown as the image "Multiscale Live" and in the corner of
the Image Editor that shows a listed mask.

A timer (registered in ``register()``) asks about ten times a second what the picture
depends on (``LivePicture.key_of``: the render size, the rig's settings, every listed
camera's placement, lens and clipping, and a CRC-32 of each mask's pixels, read into
one buffer per mask: those shown in an Image Editor every ``SHOWN_SECONDS`` or more, so
that reading them takes at most 1/``READ_SHARE`` of the time, the others one per look,
each every ``OTHERS_SECONDS`` or more, within the same share). A change cancels the job
under way; once nothing has changed for ``SETTLE_SECONDS`` and the shown masks have been
read again since (the stroke has ended) and the cancelled job has ended, a new one
starts with the pixels just read, so no two run at once. After a change the timer
comes back when the settling ends and the shown masks are due to be read again
(``LivePicture.settle_wait``), not a whole look later; while a job runs it asks every
``POLL_SECONDS`` whether the job has ended (looking at the masks every
``TICK_SECONDS`` still), so the picture shows within that long of its end.
The work runs on the job's thread and the field service's worker processes, but the
looks hold the main thread: with the demo's three masks at 1920x1080 (two cores, load
about 7) reading one mask takes about 35 ms, a look 0.3 ms (median) to 0.13 s (95th
percentile), and the look that starts a job 0.2 to 0.4 s (reading the rig, its
checks and the scene's triangles; ``bench/live_tick.py``). Nothing runs while the toggle
(``scene.multiscale.live_picture``) is off, while a render or another field build is
under way, or while nothing shows the picture (no Image Editor shows a listed mask or
the live image; in background Blender, always).

The state lives on one ``LivePicture``, made by ``register()`` and kept by the field
service (``fields.SERVICE.live``).
"""

from __future__ import annotations

import time
import zlib

import blf
import bpy
import gpu
import numpy as np
from bpy.app.handlers import persistent

from ..render.failures import failure_message
from ..render.fields import SERVICE
from ..render.live import LiveJob
from .mask_ops import guide_key
from .preview import draw_texture

# The image that holds the live picture.
IMAGE_NAME = "Multiscale Live"
# How often the timer looks for changes while the picture is wanted, and otherwise.
TICK_SECONDS = 0.1
IDLE_SECONDS = 0.5
# While a job runs, how often the timer asks whether it has ended (no look at the
# masks in between): its picture is shown within this long of its end.
POLL_SECONDS = 0.02
# A change must have settled this long before a job starts (a stroke has ended).
SETTLE_SECONDS = 0.15
# The shortest interval the timer asks for when it waits for the settling to end.
MIN_WAIT_SECONDS = 0.005
# Masks an Image Editor shows are read again at most this often, and no more often than
# takes 1/READ_SHARE of the time (a 1920x1080 mask takes tens of milliseconds); the
# others at most every OTHERS_SECONDS.
SHOWN_SECONDS = 0.2
READ_SHARE = 20
OTHERS_SECONDS = 2.0
# How long unregister waits for a cancelled job's thread to end.
STOP_WAIT_SECONDS = 10.0
# The corner picture's width as a fraction of the Image Editor's region.
CORNER_FRACTION = 0.3


def pixel_checksum(image, buffers=None):
    """A position-sensitive checksum of ``image``'s pixels: the CRC-32 of their float32
    bytes (a painted, moved, flipped or turned mask changes it), or 0 for an image
    without pixels. ``buffers`` : dict, image name -> a float32 buffer reused between
    reads (no new 33 MB array per read of a 1920x1080 mask)."""
    w, h = image.size
    if w == 0 or h == 0:
        return 0
    n = w * h * image.channels
    buf = None if buffers is None else buffers.get(image.name)
    if buf is None or buf.size != n:
        buf = np.empty(n, dtype=np.float32)
        if buffers is not None:
            buffers[image.name] = buf
    image.pixels.foreach_get(buf)
    return zlib.crc32(memoryview(buf).cast("B"))


def shown_images(wm):
    """Images shown in the Image Editors of every window of ``wm`` (a set of names)."""
    names = set()
    for window in getattr(wm, "windows", ()):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                image = area.spaces.active.image
                if image is not None:
                    names.add(image.name)
    return names


def to_display(rgba):
    """(h, w, 4) linear RGBA -> sRGB-encoded RGBA in [0, 1] (the standard transfer
    curve), for the corner picture, which is drawn without Blender's view transform."""
    c = np.clip(rgba[..., :3], 0.0, 1.0)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return np.concatenate([srgb, np.clip(rgba[..., 3:4], 0.0, 1.0)], axis=-1).astype(np.float32)


class LivePicture:
    """The live picture's state: the job under way, what was last shown and why.

    key : the change key last seen; changed : ``time.perf_counter`` of its change.
    job : render.live.LiveJob or None. shown_key : the key of the picture shown.
    updates : int, pictures shown so far. seconds : float, from the change to the
    picture of the last one shown. message : str, what the panel says (an error).
    cancelled : int, jobs cancelled by a later change.
    """

    def __init__(self):
        self.key = None
        self.changed = 0.0
        self.job = None
        self.shown_key = None
        self.updates = 0
        self.cancelled = 0
        self.seconds = 0.0
        self.stages = {}  # the last job's seconds per stage
        self.message = ""
        self.mask_sums = {}  # image name -> (checksum, time read, seconds to read)
        self.buffers = {}  # image name -> float32 buffer its pixels are read into
        self.others_read = 0
        self.read_at = 0.0  # when the shown masks were last all read
        self.due_at = 0.0  # when the shown masks will all have been read again
        self.looked = 0.0  # when the masks were last looked at (``key_of``)
        self.display = None  # (h, w, 4) sRGB of the picture, for the corner
        self.texture = None
        self.handler = None
        self.timer = None  # the registered bound ``tick``

    # --- the timer -----------------------------------------------------------------

    def tick(self):
        """Timer callback: see the module's docstring. Returns the next interval."""
        try:
            return self._tick(bpy.context)
        except Exception as err:  # never let the timer die: say it in the panel
            self.message = f"Live picture: {failure_message(err, 'The live picture')}"
            return IDLE_SECONDS

    def _tick(self, context):
        scene = context.scene
        if scene is None or not hasattr(scene, "multiscale"):
            return IDLE_SECONDS
        job = self.job
        if job is not None and not job.alive():
            self.finish(job)
        if not scene.multiscale.live_picture or bpy.app.is_job_running("RENDER"):
            self.cancel()
            return IDLE_SECONDS
        now = time.perf_counter()
        if self.job is not None and now - self.looked < TICK_SECONDS:
            return POLL_SECONDS  # a job runs: its end is looked for, not yet the masks
        shown = shown_images(context.window_manager)
        if not bpy.app.background and not self.wanted(scene, shown):
            return IDLE_SECONDS
        key = self.key_of(scene, shown, now)
        self.looked = now
        if key != self.key:
            self.key, self.changed = key, now
            if self.job is not None and self.job.key != key:
                self.job.cancel()
            return self.settle_wait(now)
        if key == self.shown_key:
            return self.interval()
        if now - self.changed < SETTLE_SECONDS or self.read_at <= self.changed:
            # not settled, or no mask read since the change: a stroke may go on
            return self.settle_wait(now)
        if self.job is not None or SERVICE.running() is not None:
            return self.interval()  # ours winds down, or another build runs
        self.start(context, key)
        return self.interval()

    def interval(self):
        """The next look's interval: ``POLL_SECONDS`` while a job runs (its end is
        looked for), else ``TICK_SECONDS``."""
        return POLL_SECONDS if self.job is not None else TICK_SECONDS

    def settle_wait(self, now):
        """Seconds until a change seen at ``self.changed`` may start a job: until it has
        settled (``SETTLE_SECONDS``) and every shown mask is due to be read again
        (``due_at``), at most ``interval()`` (a job winding down, a later change)."""
        wait = max(self.changed + SETTLE_SECONDS, self.due_at) - now
        return min(self.interval(), max(wait, MIN_WAIT_SECONDS))

    def wanted(self, scene, shown):
        """Whether anything shows the picture: an Image Editor with a listed mask or the
        live image itself."""
        if IMAGE_NAME in shown:
            return True
        return any(i.mask is not None and i.mask.name in shown for i in scene.multiscale.cameras)

    def key_of(self, scene, shown, now):
        """What the picture depends on (a tuple). Masks in ``shown`` (names) are read
        again every ``SHOWN_SECONDS`` or more (``mask_key``), others every
        ``OTHERS_SECONDS``; in background Blender every mask each time."""
        s, r = scene.multiscale, scene.render
        self.read_at = now  # the oldest read of a shown mask, below
        self.due_at = now  # the latest next read of a shown mask, below
        self.others_read = 0  # masks not shown read in this look: one at most
        cameras = []
        for item in s.cameras:
            obj = item.camera
            cam = guide_key(obj, scene) if obj is not None and obj.type == "CAMERA" else None
            cameras.append((cam, self.mask_key(item.mask, shown, now)))
        settings = (s.method, s.beta, s.simplify_px, r.resolution_x, r.resolution_y)
        return (settings, r.resolution_percentage, r.film_transparent, tuple(cameras))

    def mask_key(self, image, shown, now):
        if image is None:
            return None
        kept = self.mask_sums.get(image.name)
        if bpy.app.background:  # scripts and tests: every look reads
            every = 0.0
        elif image.name in shown:
            every = max(SHOWN_SECONDS, READ_SHARE * kept[2]) if kept else 0.0
        else:  # one per look, and no more often than 1/READ_SHARE of the time
            every = max(OTHERS_SECONDS, READ_SHARE * kept[2]) if kept else 0.0
            if kept is not None and self.others_read:
                every = float("inf")
        if kept is None or now - kept[1] >= every:
            if not bpy.app.background and image.name not in shown:
                self.others_read += 1
            t0 = time.perf_counter()
            checksum = pixel_checksum(image, self.buffers)
            kept = self.mask_sums[image.name] = (checksum, now, time.perf_counter() - t0)
        if image.name in shown:
            self.read_at = min(self.read_at, kept[1])
            again = 0.0 if bpy.app.background else max(SHOWN_SECONDS, READ_SHARE * kept[2])
            self.due_at = max(self.due_at, kept[1] + again)
        return (image.name, tuple(image.size), image.source, kept[0])

    def start(self, context, key):
        """Start the job of ``key`` (main thread)."""
        try:
            windows = getattr(context.window_manager, "windows", ())
            if context.window is None and len(windows):  # a timer: a window's view layer
                with context.temp_override(window=windows[0]):
                    depsgraph = bpy.context.evaluated_depsgraph_get()
            else:
                depsgraph = context.evaluated_depsgraph_get()
            self.job = LiveJob.of(
                depsgraph.scene, depsgraph, key, self.changed, pixels=self.buffers
            ).launch()
            self.message = ""
        except Exception as err:  # a rig that cannot render: said until it changes
            self.shown_key = key
            self.message = f"Live picture: {failure_message(err, 'The live picture')}"

    def finish(self, job):
        """A job that ended: show its picture if it is still the one wanted."""
        self.job = None
        if job.error is not None:
            self.shown_key = job.key
            self.message = f"Live picture: {failure_message(job.error, 'The live picture')}"
        elif job.cancelled or job.rgba is None or job.stopped():
            self.cancelled += 1
        else:
            self.publish(job.rgba)
            self.shown_key = job.key
            self.updates += 1
            self.seconds = time.perf_counter() - job.started
            self.stages = dict(job.seconds, field_built=job.built)
            self.message = ""

    def cancel(self):
        if self.job is not None:
            self.job.cancel()
        self.key = None  # the next look starts afresh

    def forget(self):
        """Before another file loads: stop the job, forget what was shown."""
        self.cancel()
        self.shown_key, self.mask_sums, self.message = None, {}, ""
        self.buffers = {}
        self.display = self.texture = None

    # --- showing it --------------------------------------------------------------------

    def publish(self, rgba):
        """Write (h, w, 4) linear RGBA (row 0 at the top) into the image ``IMAGE_NAME``
        (made, or remade at a new size) and redraw what shows it."""
        h, w = rgba.shape[:2]
        image = bpy.data.images.get(IMAGE_NAME)
        if image is not None and tuple(image.size) != (w, h):
            bpy.data.images.remove(image)
            image = None
        if image is None:
            image = bpy.data.images.new(IMAGE_NAME, w, h, alpha=True, float_buffer=True)
        image.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
        image.update()
        self.display, self.texture = to_display(rgba), None
        wm = getattr(bpy.context, "window_manager", None)
        for window in getattr(wm, "windows", ()):
            for area in window.screen.areas:
                if area.type in {"IMAGE_EDITOR", "VIEW_3D"}:
                    area.tag_redraw()

    def status(self):
        """A line for the panel."""
        if self.message:
            return self.message
        if self.job is not None:
            return "Live picture: updating..."
        if self.updates:
            return f"Live picture: {self.seconds:.1f} s after the last change"
        return ""

    def start_drawing(self):
        if not bpy.app.background and self.handler is None:
            self.handler = bpy.types.SpaceImageEditor.draw_handler_add(
                self.draw, (), "WINDOW", "POST_PIXEL"
            )

    def stop(self, wait=STOP_WAIT_SECONDS):
        """Stop the job and wait for its thread (at most ``wait`` seconds), so that none
        uses the worker processes after the add-on shuts them down."""
        if self.job is not None:
            self.job.cancel()
            self.job.join(wait)
        if self.handler is not None:
            bpy.types.SpaceImageEditor.draw_handler_remove(self.handler, "WINDOW")
            self.handler = None
        self.texture = self.display = None

    def draw(self):
        """The picture in the bottom right corner of an Image Editor showing a listed
        mask."""
        context = bpy.context
        scene, region = context.scene, context.region
        image = getattr(context.space_data, "image", None)
        if scene is None or image is None or self.display is None:
            return
        settings = scene.multiscale
        if not settings.live_picture or not any(i.mask == image for i in settings.cameras):
            return
        try:
            if self.texture is None:
                h, w = self.display.shape[:2]
                flat = np.ascontiguousarray(self.display[::-1]).ravel()
                buf = gpu.types.Buffer("FLOAT", flat.size, flat.tolist())
                self.texture = gpu.types.GPUTexture((w, h), format="RGBA16F", data=buf)
            h, w = self.display.shape[:2]
            cw = region.width * CORNER_FRACTION
            ch = cw * h / w
            right, bottom = _regions_over(context)
            x1, y0 = region.width - 12 - right, 12 + bottom
            draw_texture(self.texture, (x1 - cw, y0, x1, y0 + ch))
            blf.size(0, 12)
            blf.color(0, 1.0, 1.0, 1.0, 0.9)
            blf.position(0, x1 - cw, y0 + ch + 6, 0)
            blf.draw(0, "Live" if self.job is None else "Live (updating)")
        except Exception as err:  # never break the editor's drawing
            print(f"Multiscale: no live picture drawn ({err})")


def _regions_over(context):
    """(right, bottom): widths of the sidebar and heights of the asset shelf (the
    brushes in Paint mode) drawn over the editor's picture (region overlap), pixels."""
    if not context.preferences.system.use_region_overlap:
        return 0, 0
    right = bottom = 0
    for region in context.area.regions:
        if region.type == "UI" and region.width > 1:
            right = max(right, region.width)
        elif region.type.startswith("ASSET_SHELF") and region.height > 1:
            bottom += region.height
    return right, bottom


@persistent
def _on_load(_file):
    if SERVICE.live is not None:
        SERVICE.live.forget()


def register():
    picture = SERVICE.live = LivePicture()
    if _on_load not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_on_load)
    picture.start_drawing()
    if not bpy.app.background:
        # the bound method is kept: the timers know a callable by its identity
        picture.timer = picture.tick
        bpy.app.timers.register(picture.timer, first_interval=IDLE_SECONDS, persistent=True)


def unregister():
    if _on_load in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_on_load)
    picture = SERVICE.live
    if picture is None:
        return
    timer = picture.timer
    if timer is not None and bpy.app.timers.is_registered(timer):
        bpy.app.timers.unregister(timer)
    picture.stop()
    SERVICE.live = None
