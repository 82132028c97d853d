"""Time Compute Field and the render of the open file, as a user runs them, in a real
Blender window or with ``blender -b`` (tools/e2e_real/timing.sh, ``make e2e-timing``).

    blender demo.blend --python timing.py -- --out DIR/window.json
    blender -b demo.blend --python timing.py -- --out DIR/background.json

The field cache is cleared first, so the build is a real one. In the window, Compute
Field runs as its button does (INVOKE_DEFAULT: a background build the window polls) and
the render as F12 does (INVOKE_DEFAULT), --renders times (the later ones with the render
workers running); the script waits on timers for each to end and quits Blender. The
window's run starts once the window has drawn itself (``SETTLED_CPU``), as a user's
click would, and records the CPU seconds of Blender's threads by name (Mesa's
``llvmpipe`` threads are the window's drawing under Xvfb's software renderer).
Headless, both run as a script would. Writes the seconds, the CPU seconds of Blender's
process and of its worker processes during each render (what the machine's other load
does not change), the report's headline figures and the machine's load to --out.
"""

import argparse
import json
import os
import sys
import time

import bpy


def parse():
    argv = sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else []
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", required=True)
    parser.add_argument("--renders", type=int, default=2)
    # another engine for a baseline (BLENDER_WORKBENCH): the file's scene rendered by one
    # of Blender's own, no field built, to show what the window costs any engine
    parser.add_argument("--engine", default=None)
    # where F12 shows the render (Preferences > Interface > Temporary Editors): WINDOW,
    # Blender's default, opens a window; AREA shows it in the 3D view's place
    parser.add_argument(
        "--render-display", default=None, choices=("WINDOW", "AREA", "SCREEN", "NONE")
    )
    return parser.parse_args(argv)


ARGS = parse()
RESULT = {
    "blender": bpy.app.version_string,
    "mode": "background" if bpy.app.background else "window",
    "cores": os.cpu_count(),
}
STATE = {}
# The window has settled when Blender's process takes less than this share of a core
# over two half-second looks in a row.
SETTLED_CPU = 0.1


def _cpu_seconds(pid):
    """user + system CPU seconds of process ``pid`` (Linux /proc), 0 when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_now():
    """(Blender's process, its descendants): CPU seconds so far."""
    children = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(name))
    todo, workers = list(children.get(os.getpid(), [])), 0.0
    while todo:
        pid = todo.pop()
        workers += _cpu_seconds(pid)
        todo.extend(children.get(pid, []))
    return _cpu_seconds(os.getpid()), workers


def thread_cpu():
    """{thread name: CPU seconds so far} of Blender's own threads (Linux /proc): the
    window's drawing shows as Mesa's ``llvmpipe-N`` threads under Xvfb."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                text = f.read()
        except OSError:
            continue
        name = text[text.index("(") + 1 : text.rindex(")")]
        name = "llvmpipe" if name.startswith("llvmpipe") else name
        fields = text.rsplit(")", 1)[1].split()
        seconds = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        out[name] = out.get(name, 0.0) + seconds
    return out


def thread_delta(before):
    """CPU seconds per thread name since ``before`` (``thread_cpu``), those over 0.01."""
    spent = {k: v - before.get(k, 0.0) for k, v in thread_cpu().items()}
    return {k: round(v, 2) for k, v in spent.items() if v > 0.01}


def mark(name):
    """Print ``name`` with CLOCK_MONOTONIC seconds, the clock of ``perf record -k
    CLOCK_MONOTONIC`` (tools/e2e_real/perf_window.sh)."""
    print(f"E2E_MARK {name} {time.clock_gettime(time.CLOCK_MONOTONIC):.6f}", flush=True)


def render_started():
    mark(f"render_start {len(RESULT.get('renders', [])) + 1}")
    STATE["t1"] = time.perf_counter()
    STATE["cpu"] = cpu_now()
    STATE["threads"] = thread_cpu()


def render_ended(end):
    """Record the render that started at ``render_started``, ended at ``end``."""
    mark(f"render_end {len(RESULT.get('renders', [])) + 1}")
    main, workers = cpu_now()
    RESULT.setdefault("renders", []).append(
        {
            "seconds": round(end - STATE["t1"], 2),
            "blender_cpu_seconds": round(main - STATE["cpu"][0], 2),
            "workers_cpu_seconds": round(workers - STATE["cpu"][1], 2),
            "blender_threads_cpu_seconds": thread_delta(STATE["threads"]),
        }
    )
    seconds = [r["seconds"] for r in RESULT["renders"]]
    RESULT["render_seconds"] = seconds[0]
    if len(seconds) > 1:
        RESULT["second_render_seconds"] = seconds[1]
        later = sorted(seconds[1:])
        RESULT["later_render_median_seconds"] = later[len(later) // 2]


def write():
    RESULT["load_average"] = [round(x, 2) for x in os.getloadavg()]
    os.makedirs(os.path.dirname(ARGS.out) or ".", exist_ok=True)
    with open(ARGS.out, "w") as f:
        json.dump(RESULT, f, indent=1)
    print("E2E_TIMING", json.dumps(RESULT), flush=True)
    mark("end")


def report():
    rep = json.loads(bpy.context.scene.multiscale.report or "{}")
    return {k: rep.get(k) for k in ("method", "quality", "folds", "cached", "grids")}


def on_render_done(_scene, _depsgraph=None):
    STATE["render_end"] = time.perf_counter()
    mark("render_complete")


def override():
    win = bpy.context.window_manager.windows[0]
    area = max(
        (a for a in win.screen.areas if a.type in ("VIEW_3D", "IMAGE_EDITOR")),
        key=lambda a: (a.type == "VIEW_3D", a.width * a.height),
    )
    region = next(r for r in area.regions if r.type == "WINDOW")
    return bpy.context.temp_override(window=win, area=area, region=region)


def ours():
    """Whether the scene renders with this extension (no ``--engine`` baseline)."""
    return bpy.context.scene.render.engine == "MULTISCALE"


def background():
    scene = bpy.context.scene
    if ours():
        bpy.ops.multiscale.cache_clear()
        t = time.perf_counter()
        RESULT["compute_field"] = sorted(bpy.ops.multiscale.compute_field())
        RESULT["compute_seconds"] = round(time.perf_counter() - t, 2)
        RESULT["report"] = report()
    scene.render.filepath = os.path.join(os.path.dirname(ARGS.out), "timing_background.png")
    for _ in range(ARGS.renders):
        render_started()
        bpy.ops.render.render(write_still=True)
        render_ended(time.perf_counter())
    write()


def window_steps():
    """Timer callback: start the build, wait for it, start the render, wait, quit."""
    scene = bpy.context.scene
    step = STATE.get("step", "settle")
    if step == "settle":
        # start as a user would, once the window has drawn itself: its first draws
        # (shaders compiled by Mesa's software renderer under Xvfb) take seconds of CPU
        # that would otherwise be counted against the build
        now, cpu = time.perf_counter(), cpu_now()[0]
        last = STATE.get("settle")
        STATE["settle"] = (now, cpu)
        STATE.setdefault("settle_start", now)
        quiet = last is not None and (cpu - last[1]) / (now - last[0]) < SETTLED_CPU
        STATE["quiet"] = STATE.get("quiet", 0) + 1 if quiet else 0
        if STATE["quiet"] < 2 and now - STATE["settle_start"] < 60:
            return 0.5
        RESULT["settled_after_seconds"] = round(now - STATE["settle_start"], 2)
        STATE["step"] = "start" if ours() else "render ended"
        if not ours():
            bpy.app.handlers.render_complete.append(on_render_done)
            bpy.app.handlers.render_cancel.append(on_render_done)
        return 0.05
    if step == "start":
        with override():
            bpy.ops.multiscale.cache_clear()
            scene.multiscale.report = ""
            STATE["t0"] = time.perf_counter()
            mark("compute_start")
            STATE["threads"] = thread_cpu()
            bpy.ops.multiscale.compute_field("INVOKE_DEFAULT")
        STATE["step"] = "building"
        return 0.05
    if step == "building":
        if not scene.multiscale.report:
            if time.perf_counter() - STATE["t0"] > 1800:
                RESULT["error"] = "the build did not end in 30 minutes"
                write()
                bpy.ops.wm.quit_blender()
                return None
            return 0.05
        RESULT["compute_seconds"] = round(time.perf_counter() - STATE["t0"], 2)
        mark("compute_end")
        RESULT["compute_threads_cpu_seconds"] = thread_delta(STATE["threads"])
        RESULT["report"] = report()
        bpy.app.handlers.render_complete.append(on_render_done)
        bpy.app.handlers.render_cancel.append(on_render_done)
        with override():
            render_started()
            bpy.ops.render.render("INVOKE_DEFAULT")
        STATE["step"] = "rendering"
        return 0.05
    if step == "rendering":
        if "render_end" not in STATE:
            return 0.05
        render_ended(STATE.pop("render_end"))
        if len(RESULT["renders"]) >= ARGS.renders:
            write()
            bpy.ops.wm.quit_blender()
            return None
        STATE["step"] = "render ended"  # again, its workers running: what a re-render costs
        return 0.05
    if step == "render ended":
        if bpy.app.is_job_running("RENDER"):  # the job ends just after render_complete
            return 0.05
        with override():
            render_started()
            bpy.ops.render.render("INVOKE_DEFAULT")
        STATE["step"] = "rendering"
        return 0.05
    return None


if ARGS.engine:
    bpy.context.scene.render.engine = ARGS.engine
    RESULT["engine"] = ARGS.engine
if ARGS.render_display:
    bpy.context.preferences.view.render_display_type = ARGS.render_display
    RESULT["render_display"] = ARGS.render_display
if bpy.app.background:
    background()
else:
    bpy.app.timers.register(window_steps, first_interval=1.0)
