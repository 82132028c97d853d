"""The field service: the one way to a scene's ray field, for every caller.

The render, Compute Field, the viewport's Rendered shading and the ray preview all get
their field here: the request is read from the scene (``request``, main thread), looked
up in the field cache (memory, then disk: ``io.cache``), built when missing (here, or on
a worker thread with ``start``), stored, and measured once when a report is asked for.
What a build has to say reaches the caller's ``Diagnostics`` by one policy (``_say``);
nothing a caller says is written onto the field, which the cache shares among callers.
When a build started with ``start`` ends, the service stores it and tells its listeners
(the ray preview registers one), on the main thread.

``SERVICE`` is the one instance; it owns the caches: fields, the frame's BVH tree
(``trees``, see ``pipeline.scene_tree``), decoded volume sources (``volume_grids``),
what a build of an animated rig may take from the frame before it (``reuse``,
``core.methods.FrameReuse``), the last shot's layout and AUTO's method for it
(``shots``, ``choices``) and the first hits of the frame rendered last
(``sequence``, ``render.sequence``).
"""

from __future__ import annotations

import hashlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import bpy
import numpy as np

from ..adapters.masks import MaskFrames
from ..adapters.scene import cache_folder_of, field_settings, rig_from_scene
from ..adapters.shot import (
    animation_digest,
    masks_source_digest,
    sampled_rigs,
    shot_rigs,
    shot_samples,
)
from ..adapters.volumes import VolumeGridCache
from ..core.diagnostics import Diagnostics, Level
from ..core.errors import Cancelled
from ..core.geometry import Rig
from ..core.methods import (
    FrameReuse,
    Settings,
    choose_shot_method,
    field_key,
    plan_shot,
    prepare,
    settings_for,
)
from ..core.quality import build_report, crossing_messages, empty_mask_messages, to_json
from ..core.runtime import gave_up, runtime
from ..io.cache import DEFAULT_LIMIT_MB, FieldCache
from ..io.locks import POLL_SECONDS as LOCK_POLL_SECONDS
from .sequence import Sequence

# Methods whose grids a rig in motion keeps for a whole shot (``FieldService.shot_layout``).
SHOT_METHODS = ("SCALAR_FIELD", "AUTO")
# Worker processes of a build, the simplification or the ray tables gave way.
WORKERS_GIVEN_UP = (
    "Worker processes died, stopped making progress or could not be used; their work "
    "went on in Blender's process, only slower. Render > Performance > Threads: Fixed at "
    "1 keeps it there from the start"
)
# How often a background build is polled from the main thread, seconds.
POLL_SECONDS = 0.25


# The live picture's job thread (render/live.py), and how long a build waits for it.
LIVE_THREAD = "multiscale-live"
LIVE_WAIT_SECONDS = 10.0


@dataclass(frozen=True)
class FieldRequest:
    """What a field depends on, read from the scene on the main thread.

    rig : core.geometry.Rig. method, quality : str, the scene's enum names.
    settings : core.methods.Settings. key : str, the cache key (``field_key``).
    notices : tuple of str, what reading the scene adjusted (resampled masks, shared
        pixels) and the checks every build gets (empty masks, crossing frusta).
    limit_mb : float, the disk cache's size limit.
    folder : str or None, the scene's own cache folder (absolute), None: the default.
    """

    rig: Rig
    method: str
    quality: str
    settings: Settings
    key: str
    notices: tuple[str, ...]
    limit_mb: float = DEFAULT_LIMIT_MB
    folder: str | None = None


@dataclass(frozen=True)
class FieldResult:
    """A field and how it was had.

    field : RayField (shared with the cache: read it, never write to it).
    built : bool, built for this request (False: from the cache).
    report : dict or None, the build report (schema of docs/report.md) with "cached"
        set, when one was asked for.
    seconds : float, wall time from the request to the result.
    """

    field: object
    built: bool
    report: dict | None = None
    seconds: float = 0.0


class FieldBuild:
    """A field build on a worker thread: numpy only, no bpy. The main thread polls
    ``alive`` and ends it with ``FieldService.finish``.

    Attributes
    ----------
    request : FieldRequest. field : RayField or None (None until built).
    error : Exception or None (the build failed; shown by the caller).
    cancelled : bool. diagnostics : Diagnostics of the build (its cancel check counts
        ``checks``, a rough progress).
    """

    def __init__(self, request: FieldRequest, measure: bool):
        self.request = request
        self.measure = measure
        self.start = time.perf_counter()
        self.field = None
        self.report = None
        self.error = None
        self.cancelled = False
        self.gave_up = False
        self.result = None  # the FieldResult, once finished
        self._stop = threading.Event()
        self.diagnostics = Diagnostics(should_stop=self._stop.is_set)
        self._thread = threading.Thread(target=self._run, name="multiscale-field", daemon=True)

    def _run(self):
        try:
            self.field, self.gave_up = _build(self.request, self.diagnostics)
            if self.measure:
                self.report = _measure(self.field, self.request, self.start, self.diagnostics)
        except Cancelled:
            self.cancelled = True
        except Exception as err:  # handed to the main thread, reported there
            self.error = err

    def launch(self) -> None:
        """Start the build's thread."""
        self._thread.start()

    def alive(self) -> bool:
        return self._thread.is_alive()

    def cancel(self) -> None:
        self._stop.set()

    def progress(self) -> int:
        """0..99: a rough measure (the build's checks for cancellation so far)."""
        return min(99, int(100 * (1 - 1 / (1 + self.diagnostics.checks / 40))))


class FieldService:
    """Ray fields for scenes: cache lookup, build, notices, background builds.

    Parameters
    ----------
    cache : io.cache.FieldCache, or None for one in the extension's user folder.
    """

    def __init__(self, cache: FieldCache | None = None):
        self.cache = cache if cache is not None else FieldCache(lazy_folder=True)
        self.trees = {}  # pipeline.scene_tree's last result, keyed on its triangles
        self.volume_grids = VolumeGridCache()  # decoded volume sources, every frame
        self.mask_frames = MaskFrames()  # decoded frames of mask image sequences
        self.reuse = FrameReuse()  # claims and solutions of the last animated build
        self.sequence = Sequence()  # the last frame's first hits: frame-to-frame jumps
        self.shots = {}  # the layout of the last shot (``shot_layout``)
        self.choices = {}  # AUTO's method for the last shot (``shot_choice``)
        self._listeners: list[Callable] = []
        self._build: FieldBuild | None = None
        self.live = None  # the live picture (ui/live_picture.py), made by its register()
        # (request, method) -> None, raising to refuse AUTO's further candidates: the
        # memory guard's (render/memory.py sets it), asked through ``Diagnostics.guard``
        self.candidate_guard: Callable | None = None
        # request key -> (bytes, where from): the budget the memory guard last found
        # for a request, for AUTO's further candidates (render/memory.py), a few kept
        self.budgets: dict = {}

    # --- requests ------------------------------------------------------------------

    def request(
        self,
        scene,
        rig: Rig | None = None,
        depsgraph=None,
        quality: str | None = None,
        step_frames: bool = True,
        steady: bool | None = None,
    ) -> FieldRequest:
        """The field request of ``scene`` (main thread; an evaluated scene, so that
        object matrices are current), for ``rig`` when the caller has read it already.
        With ``depsgraph`` (a render's) the cameras are read as it evaluated them, at
        its frame (``adapters.scene.rig_from_scene``). ``quality`` (an enum name of
        ``scene.multiscale.quality``) replaces the scene's (the live picture asks for
        PREVIEW). ``step_frames`` False (a request made while drawing) takes a rig in
        motion's shot layout only when it is known already (``shot_layout``).
        ``steady=False`` builds without the frame reuse (``SERVICE.reuse``) or a shot
        layout, which the live picture must leave to the render's frames. Raises
        RigError when the rig cannot render."""
        group = scene.multiscale
        rig = rig if rig is not None else rig_from_scene(scene, depsgraph, frames=self.mask_frames)
        settings = field_settings(scene)
        if quality is not None and quality != group.quality:
            preset = settings_for(quality, group.accuracy_px)  # the rest as the scene's
            settings = replace(
                settings,
                accuracy_px=preset.accuracy_px,
                max_voxels=preset.max_voxels,
                cubic=preset.cubic,
                nested=preset.nested,
            )
        if steady is not None:
            settings = replace(settings, steady=steady)
        if settings.steady and group.method == "AUTO":
            choice = self.shot_choice(scene, rig, settings, depsgraph, step_frames)
            settings = replace(settings, shot=choice)
        if settings.steady and group.method in SHOT_METHODS and not _blends(settings):
            layout = self.shot_layout(scene, rig, settings, depsgraph, step_frames)
            settings = replace(settings, layout=layout)
        notices = tuple(rig.notices) + tuple(empty_mask_messages(rig))
        notices += tuple(crossing_messages(rig))
        folder, said = cache_folder_of(scene)
        notices += (said,) if said else ()
        _ = self.cache.folder  # found on the main thread (it asks bpy)
        return FieldRequest(
            rig=rig,
            method=group.method,
            quality=quality or group.quality,
            settings=settings,
            key=field_key(rig, group.method, settings),
            notices=notices,
            limit_mb=float(getattr(group, "cache_limit_mb", DEFAULT_LIMIT_MB)),
            folder=folder,
        )

    def shot_layout(self, scene, rig, settings, depsgraph=None, step_frames=True):
        """The layout of the shot ``scene``'s frame range makes for a rig in motion
        (``core.methods.plan_shot``), the same at every frame of it: worked out once
        per shot (its cameras' animation, masks, size and settings) and kept. None where
        the frames cannot be stepped (a render on a thread of its own, or not
        ``step_frames``) and the shot's layout is not known: each frame then gets a
        layout of its own."""
        mask_bytes = np.packbits(np.ascontiguousarray(rig.masks)).tobytes()
        key = (
            animation_digest(scene),
            hashlib.sha1(mask_bytes).hexdigest(),
            rig.size,
            rig.beta,
            tuple(c.name for c in rig.cameras),
            repr(settings),
        )
        if key not in self.shots:
            rigs = shot_rigs(scene, rig, depsgraph) if step_frames else None
            if rigs is None:
                return None
            self.shots = {key: plan_shot(rigs, settings)}  # one shot at a time
        return self.shots[key]

    def shot_choice(self, scene, rig, settings, depsgraph=None, step_frames=True):
        """AUTO's one method for the shot of a rig in motion (``core.methods.ShotChoice``):
        IMAGE_BLEND measured on the frames ``adapters.shot.shot_samples`` picks (each
        frame's cameras and masks), chosen once per shot (its cameras' animation, masks,
        size and settings) and kept, so no frame measures again. The frames and each
        measure depend on the shot alone: every process of a farm chooses alike. None
        where the frames cannot be stepped and the shot's choice is not known (AUTO then
        builds SCALAR_FIELD and says the shot was not measured)."""
        key = (
            animation_digest(scene),
            masks_source_digest(scene, rig),
            rig.size,
            rig.beta,
            tuple(c.name for c in rig.cameras),
            repr(replace(settings, layout=None, shot=None)),
        )
        if key not in self.choices:
            samples = None
            if step_frames:
                samples = sampled_rigs(scene, shot_samples(scene), depsgraph, self.mask_frames)
            if samples is None:
                return None
            self.choices = {key: choose_shot_method(samples, settings)}  # one shot at a time
        return self.choices[key]

    def cached(self, request: FieldRequest, memory_only: bool = False):
        """The cached field of ``request`` (memory, then disk unless ``memory_only``),
        or None."""
        if memory_only:
            return self.cache.memory.get(request.key)
        self._use(request)
        return self.cache.get(request.key, request.rig)

    # --- getting a field -------------------------------------------------------------

    def get(
        self,
        request: FieldRequest,
        diag: Diagnostics | None = None,
        measure: bool = False,
        announce: bool = False,
    ) -> FieldResult:
        """The field of ``request``: cached, or built here (steered by ``diag``).

        ``diag`` receives what the build has to say (``_say``). With ``measure`` the
        result carries the build report (measured once per field). With ``announce``
        (main thread only) the listeners are told of the field, as after a background
        build.

        Returns
        -------
        FieldResult.

        Raises
        ------
        RigError, SolverDidNotConverge: the rig cannot be built. Cancelled.
        """
        diag = diag if diag is not None else Diagnostics()
        start = time.perf_counter()
        fld = self.cached(request)
        built = gave_up = False
        if fld is None:  # a build: the live picture's job stops first
            self.stop_live()
            fld, gave_up, stored = self._build_once(request, diag, start if measure else None)
            built = stored is not None
        diag.extend(self.cache.take_notices())  # a damaged entry deleted, memory only
        report = _measure(fld, request, start, diag) if measure else None
        if built:
            _say(request, fld, diag, gave_up=gave_up, store_failed=stored or None)
        else:
            _say(request, fld, diag)
        if announce:
            self._tell(fld)
        return _result(fld, built, report, start)

    def start(self, request: FieldRequest, measure=False) -> FieldBuild:
        """Build ``request``'s field on a worker thread, or join the build of the same
        field already running; a running build of another field is cancelled (its
        result is no longer wanted). When it ends, the main thread stores it and tells
        the listeners (``finish``)."""
        self.stop_live()
        running = self._build
        if running is not None and running.alive():
            if running.request.key == request.key and (running.measure or not measure):
                return running
            running.cancel()
        build = self._build = FieldBuild(request, measure)
        build.launch()
        bpy.app.timers.register(self._poll, first_interval=POLL_SECONDS)
        return build

    def stop_live(self, wait=LIVE_WAIT_SECONDS):
        """Cancel the live picture's job and wait for it (at most ``wait`` seconds) before
        another build starts, so that no two builds run at once; called from the live
        job's own thread, nothing."""
        live = self.live
        job = getattr(live, "job", None)
        if job is None or threading.current_thread().name == LIVE_THREAD:
            return
        job.cancel()
        job.join(wait)

    def running(self) -> FieldBuild | None:
        """The background build under way, or None."""
        build = self._build
        return build if build is not None and build.alive() else None

    def finish(self, build: FieldBuild, diag: Diagnostics | None = None):
        """End a background build that is no longer alive (main thread): store its
        field and tell the listeners once, say its notices into ``diag``.

        Returns
        -------
        FieldResult, or None when the build was cancelled or failed (``build.error``).
        """
        if build.result is None and build.field is not None:
            failed = self._store(build.request, build.field)
            if failed:
                build.diagnostics.warn(failed)
            build.result = _result(build.field, True, build.report, build.start)
            self._tell(build.field)
        if diag is not None:
            diag.extend(self.cache.take_notices())
        if diag is not None and build.field is not None:
            diag.merge(build.diagnostics)
            _say(build.request, build.field, diag, gave_up=build.gave_up)
        if self._build is build:
            self._build = None
        return build.result

    def _poll(self):
        """Timer callback (main thread): finish the background build once it ends."""
        build = self._build
        if build is None:
            return None
        if build.alive():
            return POLL_SECONDS
        self.finish(build)
        _redraw_views()
        return None

    # --- listeners and the cache -------------------------------------------------------

    def add_listener(self, listener: Callable) -> None:
        """Call ``listener(scene, field)`` on the main thread when a background build
        has stored a field."""
        if listener not in self._listeners:
            self._listeners.append(listener)

    def remove_listener(self, listener: Callable) -> None:
        if listener in self._listeners:
            self._listeners.remove(listener)

    def _tell(self, fld) -> None:
        scene = bpy.context.scene
        for listener in list(self._listeners):
            listener(scene, fld)

    def _build_once(self, request: FieldRequest, diag: Diagnostics, measure_from=None):
        """Build ``request``'s field and store it, unless another process sharing the
        cache folder builds it: the first to take the field's lock (``io.locks``)
        builds, the others wait for the field to appear on disk and read it. A lock
        whose holder died is broken after at most ``io.locks.STALE_SECONDS``.

        Returns
        -------
        (RayField, whether workers were given up, stored) : ``stored`` is None when the
        field came from another process, else "" or the message of a refused write.
        With ``measure_from`` (the request's start, ``time.perf_counter``) the build
        report is measured before the field is stored, so the disk keeps it too.
        """
        self._use(request)
        lock = self.cache.build_lock(request.key)
        if lock is None:  # no disk cache: nothing to share
            fld, gave_up = _build(request, diag)
            return fld, gave_up, self._measure_and_store(request, fld, diag, measure_from)
        waited = time.perf_counter()
        while not lock.acquire():
            diag.check()  # Esc while waiting
            fld = self.cache.peek(request.key, request.rig)
            if fld is not None:
                diag.info(
                    "Another process sharing the cache folder built this field; waited "
                    f"{time.perf_counter() - waited:.1f} s for it"
                )
                return fld, False, None
            time.sleep(LOCK_POLL_SECONDS)
        try:
            fld = self.cache.peek(request.key, request.rig)  # stored while we waited
            if fld is not None:
                return fld, False, None
            start = time.perf_counter()
            fld, gave_up = _build(request, diag)
            stored = self._measure_and_store(request, fld, diag, measure_from)
            self.cache.record_build(request.key, round(time.perf_counter() - start, 3))
        finally:
            lock.release()
        return fld, gave_up, stored

    def _measure_and_store(
        self, request: FieldRequest, fld, diag: Diagnostics, measure_from=None
    ) -> str:
        """Measure ``fld`` (with ``measure_from``, the request's start; ``diag`` steers
        it) before it is stored, so the disk keeps its report too, and store it even
        when the measure fails or is cancelled: a failed measure loses no build. "" or
        the message of a refused write."""
        try:
            if measure_from is not None:
                _measure(fld, request, measure_from, diag)
        finally:
            stored = self._store(request, fld) or ""
        return stored

    def _use(self, request: FieldRequest) -> None:
        """Point the cache at ``request``'s folder and size limit."""
        self.cache.use_folder(request.folder)
        self.cache.limit_mb = request.limit_mb

    def _store(self, request: FieldRequest, fld) -> str | None:
        """Keep ``fld`` in the cache; a message when the disk refused it."""
        self._use(request)
        return self.cache.put(request.key, fld)

    def forget_sequence(self):
        """Drop what a sequence of frames kept (first hits, reuse store, shot layout and
        method): a file load starts afresh, whatever the new file's scenes are called."""
        self.sequence = Sequence()
        self.reuse = FrameReuse()
        self.shots = {}
        self.choices = {}

    def clear(self) -> int:
        """Forget every field (memory and disk), cancel a background build. Returns the
        files removed."""
        if self._build is not None:
            self._build.cancel()
        self.reuse = FrameReuse()  # claims and solutions kept from the last builds
        self.shots = {}
        self.choices = {}
        self.mask_frames.clear()
        return self.cache.clear()


def _blends(settings: Settings) -> bool:
    """Whether AUTO keeps IMAGE_BLEND for the shot (no grids: no shot layout)."""
    return settings.shot is not None and settings.shot.method == "IMAGE_BLEND"


def _build(request: FieldRequest, diag: Diagnostics):
    """(RayField, whether worker processes were given up) for ``request``. A rig in
    motion (``Settings.steady``) takes what the frame before left valid (``SERVICE.reuse``)."""
    reuse = SERVICE.reuse if request.settings.steady else None
    if diag.guard is None and SERVICE.candidate_guard is not None:
        guard = SERVICE.candidate_guard
        diag.guard = lambda method: guard(request, method)
    with runtime().journal() as runs, diag.stage("field"):  # what its workers did
        fld = prepare(request.rig, request.method, request.settings, diag, reuse=reuse)
    return fld, gave_up(runs)


def _measure(fld, request: FieldRequest, start: float, diag: Diagnostics | None = None) -> dict:
    """The build report of ``fld`` (measured once, kept with the field), a copy.
    ``diag`` steers the measure (its cancel check; stages "measure" and "folds").

    Raises
    ------
    Cancelled: ``diag`` said so.
    """
    report = getattr(fld, "report", None)
    if report is None:
        report = build_report(
            fld, request.quality, time.perf_counter() - start, request.settings.processes, diag
        )
        fld.report = report  # derived from the field alone: the same for every caller
    return dict(report)


def _result(fld, built: bool, report: dict | None, start: float) -> FieldResult:
    if report is not None:
        report = dict(report, cached=not built)
    return FieldResult(fld, built, report, time.perf_counter() - start)


def _say(request: FieldRequest, fld, diag: Diagnostics, gave_up=False, store_failed=None):
    """The notice policy, the same for every caller: what reading the scene adjusted and
    the checks of every build, the field's own build warnings, a cache that could not
    be written, workers that gave way. Messages already said are not repeated."""
    diag.extend(request.notices, Level.WARNING)
    diag.extend(fld.warnings, Level.WARNING)
    if store_failed:
        diag.warn(store_failed)
    if gave_up:
        diag.warn(WORKERS_GIVEN_UP)


def publish_report(scene, report: dict | None) -> None:
    """Keep ``report`` (None: a build that failed) as the scene's build report
    (``scene.multiscale.report``, strict JSON; "" clears it), for the panel and for
    scripts that read it after ``bpy.ops.render.render``. ``scene`` may be a render's
    evaluated scene: its original gets it. Off the main thread (a render in Blender's
    window) it is written by a timer, on the main thread."""
    original = getattr(scene, "original", None) or scene
    text = "" if report is None else to_json(report)

    def write():
        original.multiscale.report = text
        return None

    if bpy.app.background or threading.current_thread() is threading.main_thread():
        write()
    else:
        bpy.app.timers.register(write, first_interval=0.0)


def _redraw_views() -> None:
    wm = getattr(bpy.context, "window_manager", None)
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type in {"VIEW_3D", "IMAGE_EDITOR"}:
                area.tag_redraw()


# The one field service: every caller goes through it.
SERVICE = FieldService()
