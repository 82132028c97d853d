"""Run inside a real Blender window (tools/e2e_real/run.sh): drive the Multiscale
workflow on the sample scene step by step on timers and take a screenshot of the whole
screen after each step (ImageMagick's ``import``, which works under Xvfb).

Environment: SHOT_DIR (where the PNGs go), E2E_LOG (a JSON log of what each step saw).
Quits Blender when done; a step that fails is logged and ends the run.
"""

import faulthandler
import json
import os
import subprocess
import time
import traceback

import bpy

faulthandler.enable(all_threads=True)  # a crash shows the Python line it came from
OUT = os.environ.get("SHOT_DIR", ".")
LOG = os.environ.get("E2E_LOG", os.path.join(OUT, "e2e_log.json"))
log = {"version": bpy.app.version_string, "steps": []}


def note(step, **info):
    log["steps"].append({"step": step, "time": round(time.time() - T0, 1), **info})
    with open(LOG, "w") as f:
        json.dump(log, f, indent=1)
    print("E2E", step, info, flush=True)


def shot(name):
    path = os.path.join(OUT, name)
    subprocess.run(["import", "-window", "root", path], check=True)
    note("screenshot", file=name)


def view3d():
    win = bpy.context.window_manager.windows[0]
    area = max(
        (a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height
    )
    region = next(r for r in area.regions if r.type == "WINDOW")
    return win, area, region


def override():
    win, area, region = view3d()
    return bpy.context.temp_override(window=win, area=area, region=region)


def setup():
    bpy.context.preferences.view.render_display_type = "SCREEN"
    win, area, _region = view3d()
    space = area.spaces.active
    space.show_region_ui = True
    for region in area.regions:
        if region.type == "UI":
            try:
                region.active_panel_category = "Multiscale"
            except (AttributeError, TypeError):
                pass
    scene = bpy.context.scene
    with override():
        if os.environ.get("E2E_FRESH", "1") == "1":  # a real build, not a cache hit
            bpy.ops.multiscale.cache_clear()
        bpy.ops.multiscale.validate()
        bpy.ops.multiscale.compute_field("INVOKE_DEFAULT")
    scene.multiscale.show_preview = True
    note("setup", cameras=[i.camera.name for i in scene.multiscale.cameras])


def press_n():
    """While the field builds, the viewport must still take keys: N hides the sidebar."""
    win, area, _region = view3d()
    state["ui_before"] = area.spaces.active.show_region_ui
    state["pressed"] = time.time()
    x, y = area.x + area.width // 3, win.height - (area.y + area.height // 2)
    subprocess.run(["xdotool", "mousemove", str(x), str(y), "key", "n"], check=False)


def check_toggled():
    """Condition: the sidebar changed (within 30 s; the build shares the CPU)."""
    _win, area, _region = view3d()
    now = area.spaces.active.show_region_ui
    if now == state["ui_before"]:
        if time.time() - state["pressed"] > 30:
            raise RuntimeError("the interface did not take a key while the field was building")
        return False
    note(
        "keys during the build",
        sidebar_before=state["ui_before"],
        sidebar_after=now,
        seconds=round(time.time() - state["pressed"], 1),
        building=not field_ready(),
    )
    area.spaces.active.show_region_ui = True
    return True


def _builds():
    import threading

    return [t for t in threading.enumerate() if t.name.endswith("(_run)") and t.is_alive()]


def press_esc():
    """Esc over the viewport cancels the build."""
    win, area, _region = view3d()
    state["builds"] = len(_builds())
    state["pressed"] = time.time()
    x, y = area.x + area.width // 3, win.height - (area.y + area.height // 2)
    subprocess.run(["xdotool", "mousemove", str(x), str(y), "key", "Escape"], check=False)


def build_stopped():
    """Condition: the worker thread ended without a report (within 60 s)."""
    if _builds():
        if time.time() - state["pressed"] > 60:
            raise RuntimeError("Esc did not stop the build")
        return False
    note(
        "cancelled",
        builds_before=state["builds"],
        seconds=round(time.time() - state["pressed"], 1),
        report_written=field_ready(),
    )
    return True


def build_again():
    with override():
        bpy.ops.multiscale.compute_field("INVOKE_DEFAULT")
    note("build restarted")


def sidebar_tab():
    """Show the Multiscale tab of the sidebar: set the region's category, else click it."""
    win, area, _region = view3d()
    ui = next(r for r in area.regions if r.type == "UI")
    try:
        ui.active_panel_category = "Multiscale"
    except (AttributeError, TypeError):
        pass
    area.tag_redraw()
    if getattr(ui, "active_panel_category", "") != "Multiscale":
        # the tabs run down the region's right edge: Tool, View, Animation, Multiscale
        x = ui.x + ui.width - 8
        y = win.height - (ui.y + ui.height) + TAB_OFFSET
        subprocess.run(["xdotool", "mousemove", str(x), str(y), "click", "1"], check=False)
    note("sidebar", category=getattr(ui, "active_panel_category", None))


# Distance of the Multiscale tab's middle from the top of the sidebar, pixels (the
# fourth tab at Blender's default UI scale).
TAB_OFFSET = int(os.environ.get("E2E_TAB_OFFSET", "215"))


def field_ready():
    return bool(bpy.context.scene.multiscale.report)


def tab_category():
    _win, area, _region = view3d()
    return next(r for r in area.regions if r.type == "UI").active_panel_category


def panel_shot():
    s = bpy.context.scene.multiscale
    note("report", report=json.loads(s.report).get("folds"), validation=s.validation)
    with override():
        bpy.ops.view3d.view_all(center=False)
    return "panel.png"


def render_start():
    with override():
        bpy.ops.multiscale.render("INVOKE_DEFAULT")
    note("render started")


def rendering():
    return bpy.app.is_job_running("RENDER")


def render_done():
    subprocess.run(["xdotool", "key", "Escape"], check=False)  # back from the render view


def viewport_rendered():
    win, area, region = view3d()
    space = area.spaces.active
    space.shading.type = "RENDERED"
    space.overlay.show_overlays = False
    space.region_3d.view_perspective = "CAMERA"
    bpy.context.scene.multiscale.show_preview = False
    area.tag_redraw()


def mask_new():
    win, area, region = view3d()
    area.spaces.active.shading.type = "SOLID"
    area.spaces.active.overlay.show_overlays = True
    s = bpy.context.scene.multiscale
    s.active_index = 1
    with override():
        bpy.ops.multiscale.mask_new()
        bpy.ops.multiscale.mask_paint()
    item = s.cameras[1]
    note("mask", mask=item.mask.name, size=list(item.mask.size), guide=item.guide.name)


def paint_stroke():
    win = bpy.context.window_manager.windows[0]
    area = next(a for a in win.screen.areas if a.type == "IMAGE_EDITOR")
    region = next(r for r in area.regions if r.type == "WINDOW")
    with bpy.context.temp_override(window=win, area=area, region=region):
        bpy.ops.image.view_all(fit_view=True)
    # a circle of strokes around the middle of the image, as a hand would paint it
    top = win.height - (region.y + region.height)
    cx, cy = region.x + region.width // 2, top + region.height // 2
    r = min(region.width, region.height) // 6
    import math

    pts = [
        (cx + int(r * math.cos(t / 12 * math.pi)), cy + int(r * math.sin(t / 12 * math.pi)))
        for t in range(25)
    ]
    start = ["mousemove", str(pts[0][0]), str(pts[0][1])]
    cmd = ["xdotool", *start, "sleep", "0.5", *start, "sleep", "0.3", "mousedown", "1"]
    cmd += ["sleep", "0.3"]
    for x, y in pts[1:]:
        cmd += ["mousemove", str(x), str(y), "sleep", "0.08"]
    cmd += ["sleep", "0.3", "mouseup", "1"]
    subprocess.run(cmd, check=False)
    area.tag_redraw()
    note("stroke", points=len(pts))


def mask_check():
    import numpy as np

    img = bpy.context.scene.multiscale.cameras[1].mask
    px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(px)
    note("mask painted", white_pixels=int((px.reshape(-1, 4)[:, 0] > 0.5).sum()))
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            area.tag_redraw()


def save_copy():
    """Save the painted file (run.sh reopens it to check the mask survived)."""
    path = os.environ.get("E2E_SAVE")
    if path:
        bpy.ops.wm.save_as_mainfile(filepath=path, copy=True)
        note("saved", path=path)


STEPS = [
    ("setup", setup, 3.0),
    ("building shot", lambda: shot("building.png"), 1.0),
    ("press N while building", press_n, 1.5),
    ("sidebar toggled", check_toggled, None),
    ("press Esc", press_esc, 1.0),
    ("build cancelled", build_stopped, None),
    ("build again", build_again, 3.0),
    ("wait field", field_ready, None),
    ("tab", sidebar_tab, 1.0),
    ("tab check", lambda: note("sidebar after", category=tab_category()), 1.0),
    ("panel", lambda: shot(panel_shot()), 2.0),
    ("render", render_start, 1.0),
    ("wait render", lambda: not rendering(), None),
    ("render shot", lambda: shot("render.png"), 1.0),
    ("back", render_done, 1.0),
    ("viewport", viewport_rendered, 6.0),
    ("viewport shot", lambda: shot("viewport_rendered.png"), 1.0),
    ("mask", mask_new, 3.0),
    ("mask shot", lambda: shot("mask_new.png"), 1.0),
    ("paint", paint_stroke, 2.0),
    ("mask check", mask_check, 3.0),
    ("paint shot", lambda: shot("mask_paint.png"), 1.0),
    ("save", save_copy, 1.0),
]
state = {"i": 0, "since": None}
T0 = time.time()
TIMEOUT = float(os.environ.get("E2E_STEP_TIMEOUT", "600"))


def tick():
    i = state["i"]
    if i >= len(STEPS):
        note("done")
        bpy.ops.wm.quit_blender()
        return None
    name, fn, wait = STEPS[i]
    try:
        if wait is None:  # a condition: poll it
            state["since"] = state["since"] or time.time()
            if not fn():
                if time.time() - state["since"] > TIMEOUT:
                    note("timeout", at=name)
                    bpy.ops.wm.quit_blender()
                    return None
                return 1.0
            state["since"] = None
            note(name)
            wait = 1.0
        else:
            fn()
    except Exception:
        note("failed", at=name, error=traceback.format_exc())
        bpy.ops.wm.quit_blender()
        return None
    state["i"] += 1
    return wait


bpy.app.timers.register(tick, first_interval=4.0)
