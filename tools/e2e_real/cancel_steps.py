"""Run inside a real Blender window on the demo scene: Esc pressed in each stage of a
render, through the window's own escape path, and the render's end timed.

For each step, a method and one of its stages (SCALAR_FIELD's fill, solve and trace at
the demo's size, then the simplification and the tile loop; VECTOR_FIELD's tangents at
the demo's size; AUTO's, which builds
IMAGE_BLEND on the demo and measures it, at 1920x1080: the weight solve, the measure
along the rays and the fold count; Cycles' own render of the hand-off at 1024 samples,
``CYCLES:cycles``), a render is started as F12 starts it (``render.render`` invoked: a
render job whose ``test_break`` hears Esc), and a quarter of a second after the render
enters the stage (``Diagnostics.stage``, or the hand-off's ``_run_cycles``, patched
here; a second for Cycles, whose sync comes first) xdotool presses Escape over the
window. A stage too short for that (``HELD``: the measure along the rays, the ray
simplification, the tangents) has Escape pressed as it starts, and its work waits (at most
``HOLD_SECONDS``) until the render job's ``test_break`` says the key arrived, so that
the stage's own cancel check is what hears it. Logged per step: ``key_to_end``, the time
from the key to the end of the render job (``bpy.app.is_job_running('RENDER')``), and
``heard_to_end``, from the first time the engine's cancel check said stop (``heard``:
the render job's ``test_break``, asked at least every 0.1 s; during Cycles' own render,
which asks it from C, a thread asks it every 10 ms from the key on) to that end. The
second is what the extension controls and is bounded at 2 s; the first adds the key's
way in (xdotool, the X server, Blender's event loop), which took up to 1.5 s at load
average 13 on 2 cores while the engine was asking every 0.1 s (the threads' stacks half
a second after an unheard key are logged). A render whose engine never hears the key
fails the step, as does one that hears it outside the stage (``heard_in``: the stages
open when it first did).

Started by ``make e2e-real`` (tools/e2e_real/run.sh) in a real Blender window with the
demo scene open, ``E2E_LOG`` naming the log file.

Quits Blender when done; a step that fails is logged and ends the run.
"""

import json
import os
import subprocess
import sys
import threading
import time
import traceback
from contextlib import contextmanager

import bpy

LOG = os.environ.get("E2E_LOG", "cancel_log.json")
# METHOD:stage, or a stage alone (SCALAR_FIELD's); CYCLES: the hand-off (AUTO's field)
STEPS = (
    "fill,solve,trace,simplify,render,VECTOR_FIELD:tangents,"
    "AUTO:solve,AUTO:measure,AUTO:folds,CYCLES:cycles"
)
STAGES = tuple(os.environ.get("CANCEL_STAGES", STEPS).split(","))
# the render size (percent of the demo's 640x360) per method, 300 for those not named:
# IMAGE_BLEND's stages last long enough to press a key in at 1920x1080 (the solve about
# 2 s, the fold count several seconds), a fraction of a second at 640x360
PERCENT = {"SCALAR_FIELD": 100, "VECTOR_FIELD": 100, "CYCLES": 100}
DELAY = 0.25  # seconds into the stage
CYCLES_DELAY = 1.0  # seconds into Cycles' own render (its sync takes a fraction of that)
CYCLES_SAMPLES = 1024  # minutes of Cycles' work uncancelled
# Escape as the stage starts, its work held until the key is heard: the measure (about
# 0.4 s at 1920x1080), the simplification (under the key's 0.25 s delay on an idle
# machine: its Escape came after it had ended, and the tile loop heard it) and
# VECTOR_FIELD's tangents at 640x360 (its Escape was heard in the solve after it)
HELD = {"measure", "simplify", "tangents"}
HOLD_SECONDS = 5.0
BOUND = 2.0
log = {"version": bpy.app.version_string, "steps": []}
T0 = time.time()
# "open": the stages open per thread (ident -> list of names, innermost last)
state = {"stage": None, "pressed": None, "entered": [], "open": {}, "step": 0}
engine_lock = threading.Lock()  # the render's engine is asked from other threads under it


def note(step, **info):
    log["steps"].append({"step": step, "time": round(time.time() - T0, 2), **info})
    with open(LOG, "w") as f:
        json.dump(log, f, indent=1)
    print("E2E", step, info, flush=True)


def module(tail):
    """The installed extension's module whose name ends with ``tail``."""
    for name, mod in list(sys.modules.items()):
        if name.endswith(tail):
            return mod
    raise LookupError(tail)


def window_area():
    win = bpy.context.window_manager.windows[0]
    area = max(win.screen.areas, key=lambda a: a.width * a.height)
    return win, area


def press_escape():
    win, area = window_area()
    x, y = area.x + area.width // 2, win.height - (area.y + area.height // 2)
    state["pressed"] = time.perf_counter()
    subprocess.Popen(["xdotool", "mousemove", str(x), str(y), "key", "Escape"])
    threading.Timer(0.5, where_unheard).start()
    if state["stage"] == "cycles":  # Cycles asks test_break itself, from C
        threading.Thread(target=watch_break, daemon=True).start()


def watch_break():
    """From the key on, ask the render job's ``test_break`` every 10 ms (under
    ``engine_lock``, while the render runs) and note when it first says stop: the break
    Cycles' own render polls."""
    while state.get("heard") is None and state.get("returned") is None:
        with engine_lock:
            engine = state.get("engine")
            broken = engine is not None and engine.test_break()
        if broken:
            hear()
            return
        time.sleep(0.01)


def hear():
    """Note the first time the key was heard, and the stages open then."""
    with engine_lock:
        if state.get("heard") is None:
            state["heard"] = time.perf_counter()
            state["heard_in"] = list(state["open"].get(state.get("render_thread"), []))


def where_unheard():
    """Half a second after the key, unheard: what every thread is doing (logged)."""
    if state.get("heard") is not None:
        return
    stacks = {}
    for ident, frame in sys._current_frames().items():
        lines = []
        while frame is not None and len(lines) < 8:
            code = frame.f_code
            lines.append(f"{os.path.basename(code.co_filename)}:{frame.f_lineno} {code.co_name}")
            frame = frame.f_back
        stacks[str(ident)] = lines
    state["unheard"] = stacks


def hold(name):
    """Press Escape now and wait until the render job's ``test_break`` says it arrived
    (at most ``HOLD_SECONDS``; the stage ``name`` then runs and its check hears it)."""
    press_escape()
    engine = state.get("engine")
    waited = time.perf_counter()
    while engine is not None and time.perf_counter() - waited < HOLD_SECONDS:
        if engine.test_break():
            break
        time.sleep(0.01)
    state["held"] = round(time.perf_counter() - waited, 3)


@contextmanager
def entered(name, delay=DELAY):
    """A thread enters stage ``name``; on the render job's thread (not another job's,
    such as the viewport's picture), if it is the one wanted, a timer presses Escape
    ``delay`` s later, or for a stage of ``HELD`` Escape is pressed at once and the stage
    waits for it (``hold``)."""
    here = threading.get_ident()
    rendering = here == state.get("render_thread")
    opened = state["open"].setdefault(here, [])
    opened.append(name)
    if rendering:
        state["entered"].append(name)
    try:
        wanted = rendering and name == state["stage"]
        if wanted and state["pressed"] is None and not state.get("timer"):
            if name in HELD:
                hold(name)
            else:
                state["timer"] = threading.Timer(delay, press_escape)
                state["timer"].start()
        yield
    finally:
        opened.pop()


def arm():
    """Patch ``Diagnostics.stage`` and the hand-off's ``_run_cycles`` (``entered``), the
    engine's cancel check (``heard``) and its render (the engine, and when it returns)."""
    diagnostics = module("multiscale_camera.core.diagnostics")
    stage = diagnostics.Diagnostics.stage

    @contextmanager
    def armed(self, name):
        with entered(name), stage(self, name):
            yield self

    diagnostics.Diagnostics.stage = armed
    cycles = module("multiscale_camera.render.cycles")
    run_cycles = cycles._run_cycles

    def cycles_run(*args, **kwargs):
        with entered("cycles", CYCLES_DELAY):
            return run_cycles(*args, **kwargs)

    cycles._run_cycles = cycles_run
    # when the engine first hears the key (and in which stages), and when its render
    # returns
    engine = module("multiscale_camera.render.engine").MultiscaleRenderEngine
    should_stop, render = engine.should_stop, engine.render

    def heard(self):
        stop = should_stop(self)
        if stop:
            hear()
        return stop

    def rendered(self, depsgraph):
        state["engine"], state["render_thread"] = self, threading.get_ident()
        try:
            return render(self, depsgraph)
        finally:
            with engine_lock:
                state["returned"] = time.perf_counter()
                state["engine"] = None

    engine.should_stop, engine.render = heard, rendered


def start(step):
    method, _, stage = step.rpartition(":")
    method = method or "SCALAR_FIELD"
    state.update(stage=stage, pressed=None, timer=None, entered=[], began=time.perf_counter())
    state.update(heard=None, heard_in=None, held=None, returned=None, unheard=None)
    state.update(render_thread=None)
    scene = bpy.context.scene
    percent = PERCENT.get(method, 300)
    if method == "CYCLES":  # the hand-off, long enough to press a key in
        scene.multiscale.method, scene.multiscale.shading = "AUTO", "CYCLES"
        scene.cycles.samples, scene.cycles.use_adaptive_sampling = CYCLES_SAMPLES, False
    else:
        scene.multiscale.method, scene.multiscale.shading = method, state["shading"]
    scene.render.resolution_percentage = percent
    with bpy.context.temp_override(window=bpy.context.window_manager.windows[0]):
        bpy.ops.multiscale.cache_clear()  # every render builds its field afresh
        scene.render.filepath = os.path.join(os.path.dirname(LOG), "cancelled_")
        bpy.ops.render.render("INVOKE_DEFAULT")
    note("render started", stage=stage, method=method, percent=percent)


def watch():
    """Timer: when the render job has ended, log the stage's time and start the next."""
    stage = state["stage"]
    if bpy.app.is_job_running("RENDER"):
        if time.perf_counter() - state["began"] > 600:
            note("failed", stage=stage, reason="the render ran 600 s")
            return quit_blender()
        return 0.01
    ended = time.perf_counter()
    if state["pressed"] is None and stage in state["entered"]:
        note("failed", stage=stage, reason="the render ended before Escape", seen=state["entered"])
        return quit_blender()
    if state["pressed"] is None:  # nested grids: the solve runs inside "fill"
        note("skipped", stage=stage, reason="not a stage of this build", seen=state["entered"])
    else:
        key_to_end = ended - state["pressed"]
        if state.get("unheard"):
            note("unheard after 0.5 s", stacks=state.pop("unheard"))
        if state.get("heard") is None:
            note(
                "failed",
                stage=stage,
                reason="the engine never heard Escape",
                key_to_end=round(key_to_end, 3),
            )
            return quit_blender()
        since = {
            key: round(state[key] - state["pressed"], 3)
            for key in ("heard", "returned")
            if state.get(key) is not None
        }
        stopping = ended - state["heard"]
        note(
            "cancelled",
            stage=stage,
            key_to_end=round(key_to_end, 3),
            heard_to_end=round(stopping, 3),
            within=stopping < BOUND,
            heard_in=state["heard_in"],
            **({"held": state["held"]} if state.get("held") is not None else {}),
            **since,
        )
        if stage not in state["heard_in"]:
            note(
                "failed",
                stage=stage,
                reason=f"Escape was heard in {state['heard_in']}, not in {stage}: the stage "
                "ended before the key arrived (a stage that short belongs in HELD)",
            )
            return quit_blender()
        if stopping >= BOUND and os.environ.get("CANCEL_KEEP_GOING") != "1":
            note("failed", stage=stage, reason=f"{stopping:.2f} s from the break to the end")
            return quit_blender()
    state["step"] += 1
    rest = STAGES[state["step"] :]
    if not rest:
        note("done")
        return quit_blender()
    bpy.app.timers.register(lambda: run(rest[0]), first_interval=1.0)
    return None


def run(stage):
    try:
        start(stage)
        bpy.app.timers.register(watch, first_interval=0.05)
    except Exception:
        note("failed", stage=stage, error=traceback.format_exc())
        quit_blender()
    return None


def quit_blender():
    bpy.app.timers.register(lambda: bpy.ops.wm.quit_blender() and None, first_interval=0.5)
    return None


def begin():
    try:
        bpy.context.preferences.view.render_display_type = "NONE"  # keys go to this window
        bpy.context.scene.multiscale.method = "SCALAR_FIELD"
        bpy.context.scene.multiscale.quality = "PREVIEW"
        state["shading"] = bpy.context.scene.multiscale.shading  # the file's, between steps
        arm()
        note("armed", stages=list(STAGES), uptime=open("/proc/loadavg").read().split()[:3])
    except Exception:
        note("failed", error=traceback.format_exc())
        return quit_blender()
    run(STAGES[0])
    return None


bpy.app.timers.register(begin, first_interval=3.0)
