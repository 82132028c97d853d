"""Run inside a real Blender window on the demo scene: the mask tools step by step on
timers, a screenshot of the whole screen after each (ImageMagick's ``import``).

1. Paint Mask on camera 2's own (ring) mask: its view is drawn over it, the other
   masks and the transition bands over that (mask_guide.png).
2. Camera 3's mask made from the teapot's silhouette (New Mask, then Mask from
   Selected), painted over its view with the overlay (mask_from_selected.png).
3. A soft ellipse dragged onto camera 2's mask (mask_drag.png while dragging), reaching
   into camera 1's: the overlap and the missing gap are drawn where they are
   (mask_shape.png).
4. Camera 2 turned: its guide is made again within about a second (and again when it
   turns back).
5. New Mask on camera 3's painted mask asks first (mask_confirm.png), then the
   3D viewport's panel offers to put the replaced mask back (mask_restore.png).
6. Camera 3's mask put back, then a brush stroke (the mouse dragged with its button
   down) on camera 2's mask in Paint mode: the live picture is remade in the
   background and drawn in the editor's corner (mask_live.png); the log gives the
   seconds from the stroke's end to it.

    SHOT_DIR=docs/images E2E_LOG=out/mask-log.json \\
      ../shared/tools/realblender/run.sh sample_blends/demo.blend \\
      --python tools/e2e_real/mask_steps.py

Quits Blender when done; a step that fails is logged and ends the run.
"""

import json
import os
import subprocess
import time
import traceback

import bpy

OUT = os.environ.get("SHOT_DIR", ".")
LOG = os.environ.get("E2E_LOG", os.path.join(OUT, "mask_log.json"))
log = {"version": bpy.app.version_string, "steps": []}
T0 = time.time()


def note(step, **info):
    log["steps"].append({"step": step, "time": round(time.time() - T0, 1), **info})
    with open(LOG, "w") as f:
        json.dump(log, f, indent=1)
    print("E2E", step, info, flush=True)


def shot(name):
    subprocess.run(["import", "-window", "root", os.path.join(OUT, name)], check=True)
    note("screenshot", file=name)


def window():
    return bpy.context.window_manager.windows[0]


def area_of(kind):
    areas = [a for a in window().screen.areas if a.type == kind]
    return max(areas, key=lambda a: a.width * a.height) if areas else None


def override(kind="VIEW_3D"):
    """A context of the biggest area of ``kind``, else (the Image Editor maximised) of
    the Image Editor."""
    area = area_of(kind) or area_of("IMAGE_EDITOR")
    region = next(r for r in area.regions if r.type == "WINDOW")
    return bpy.context.temp_override(window=window(), area=area, region=region)


def sidebar(kind):
    """Show the area's sidebar on its Multiscale tab."""
    area = area_of(kind)
    area.spaces.active.show_region_ui = True
    for region in area.regions:
        if region.type == "UI":
            try:
                region.active_panel_category = "Multiscale"
            except (AttributeError, TypeError):
                pass
    area.tag_redraw()


def fit_image():
    with override("IMAGE_EDITOR"):
        bpy.ops.image.view_all(fit_view=True)
    sidebar("IMAGE_EDITOR")


def maximise():
    """The Image Editor over the whole window (back_to_previous undoes it)."""
    with override("IMAGE_EDITOR"):
        bpy.ops.screen.screen_full_area()


def restore_screen():
    with override("IMAGE_EDITOR"):
        bpy.ops.screen.back_to_previous()


# Distance of the 3D viewport's Multiscale tab's middle from the top of its sidebar,
# pixels (the fourth tab at Blender's default UI scale), as tools/e2e_real/gui_steps.py.
TAB_OFFSET = int(os.environ.get("E2E_TAB_OFFSET", "215"))


def click_tab():
    """Show the 3D viewport's sidebar on its Multiscale tab: set it, else click it."""
    sidebar("VIEW_3D")
    area = area_of("VIEW_3D")
    ui = next(r for r in area.regions if r.type == "UI")
    if getattr(ui, "active_panel_category", "") != "Multiscale":
        x = ui.x + ui.width - 8
        y = window().height - (ui.y + ui.height) + TAB_OFFSET
        subprocess.run(["xdotool", "mousemove", str(x), str(y), "click", "1"], check=False)


def overlay_note():
    from bl_ext.user_default.multiscale_camera.ui import mask_overlay

    return mask_overlay.OVERLAY.messages if mask_overlay.OVERLAY else None


def paint(index):
    settings = bpy.context.scene.multiscale
    settings.active_index = index
    with override():
        bpy.ops.multiscale.mask_paint()
    item = settings.cameras[index]
    note("paint", camera=item.camera.name, mask=item.mask.name, guide=item.guide.name)


def setup():
    bpy.context.scene.multiscale.live_picture = False  # on for step 6 only
    sidebar("VIEW_3D")
    paint(1)


def live_on():
    """Camera 3's painted mask put back (New Mask left it empty), then the live picture
    on, camera 2's mask painted."""
    settings = bpy.context.scene.multiscale
    settings.active_index = 2
    with override():
        result = bpy.ops.multiscale.mask_restore()
    note("mask put back", result=sorted(result), mask=settings.cameras[2].mask.name)
    settings.live_picture = True
    paint(1)


def guide_shot():
    fit_image()
    note("overlay", warnings=overlay_note())


def turn_camera(angle):
    """Turn camera 2 about its up axis; remember its guide's state and key."""
    from bl_ext.user_default.multiscale_camera.ui.mask_ops import guide_state

    scene = bpy.context.scene
    item = scene.multiscale.cameras[1]
    state["key"] = item.guide_key
    item.camera.rotation_euler.z += angle
    bpy.context.view_layer.update()
    note("camera turned", angle=angle, guide=guide_state(item, scene))


def guide_remade():
    """The timer has made camera 2's guide again for its new direction."""
    from bl_ext.user_default.multiscale_camera.ui.mask_ops import guide_state

    scene = bpy.context.scene
    item = scene.multiscale.cameras[1]
    remade = guide_state(item, scene) == "ok" and item.guide_key != state["key"]
    note("guide after the turn", state=guide_state(item, scene), remade=remade)
    if not remade:
        raise RuntimeError("the guide was not remade after the camera turned")


def from_teapot():
    settings = bpy.context.scene.multiscale
    settings.active_index = 2
    with override():
        bpy.ops.object.select_all(action="DESELECT")
        for obj in bpy.data.objects:
            if obj.name.startswith("Teapot"):
                obj.select_set(True)
        bpy.ops.multiscale.mask_new(guide=False)
        result = bpy.ops.multiscale.mask_from_selected(margin=4)
    paint(2)
    note("from selected", result=sorted(result))


def screen_point(u, v):
    """Screen pixel (x from the left, y from the top) of image point (u, v) in the
    Image Editor."""
    area = area_of("IMAGE_EDITOR")
    region = next(r for r in area.regions if r.type == "WINDOW")
    x, y = region.view2d.view_to_region(u, v, clip=False)
    return region.x + x, window().height - (region.y + y)


def claimed(index):
    import numpy as np

    image = bpy.context.scene.multiscale.cameras[index].mask
    px = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(px)
    return int((px.reshape(-1, 4)[:, 0] >= 0.5).sum())


def drag_start():
    """Drag a Shape (an ellipse) on camera 2's mask: the mouse to the first corner."""
    settings = bpy.context.scene.multiscale
    settings.active_index = 1
    state["claimed"] = claimed(1)
    with override("IMAGE_EDITOR"):
        result = bpy.ops.multiscale.mask_shape_drag("INVOKE_DEFAULT", shape="ELLIPSE", feather=12.0)
    state["from"], state["to"] = screen_point(0.14, 0.80), screen_point(0.36, 0.64)
    x, y = state["from"]
    subprocess.run(["xdotool", "mousemove", str(int(x)), str(int(y))], check=False)
    note("drag started", result=sorted(result))


def press():
    subprocess.run(["xdotool", "mousedown", "1"], check=False)


def move(k, steps=4):
    """The k-th of ``steps`` moves towards the second corner (Blender takes each event
    between timer steps, as from a hand)."""
    (x0, y0), (x1, y1) = state["from"], state["to"]
    x, y = x0 + (x1 - x0) * k / steps, y0 + (y1 - y0) * k / steps
    subprocess.run(["xdotool", "mousemove", str(int(x)), str(int(y))], check=False)


def drag_end():
    subprocess.run(["xdotool", "mouseup", "1"], check=False)


def dragged():
    now = claimed(1)
    note("dragged", claimed_before=state["claimed"], claimed_after=now)
    if now <= state["claimed"]:
        raise RuntimeError("the dragged ellipse added nothing to the mask")


def confirm():
    settings = bpy.context.scene.multiscale
    settings.active_index = 2
    area = area_of("VIEW_3D")
    x = area.x + area.width // 3
    y = window().height - (area.y + area.height // 2)
    subprocess.run(["xdotool", "mousemove", str(x), str(y)], check=False)
    with override():
        result = bpy.ops.multiscale.mask_new("INVOKE_DEFAULT")
    note("new mask asked", result=sorted(result))


def accept():
    subprocess.run(["xdotool", "key", "Return"], check=False)


def restored():
    item = bpy.context.scene.multiscale.cameras[2]
    note(
        "replaced",
        mask=item.mask.name if item.mask else None,
        previous=item.previous_mask.name if item.previous_mask else None,
    )


def live_picture():
    from bl_ext.user_default.multiscale_camera.render.fields import SERVICE

    return SERVICE.live


def live_ready():
    """Camera 2's mask in the Image Editor, Paint mode: wait for the first live
    picture (the one of the masks as they are) before the stroke."""
    live = live_picture()
    if live.message:
        raise RuntimeError(live.message)
    if live.updates == 0 or live.job is not None:
        if time.time() - T0 > 900:
            raise RuntimeError(f"no live picture ({live.message or 'timed out'})")
        return AGAIN
    state["live"], state["claimed"] = live.updates, claimed(1)
    note("live picture", updates=live.updates, seconds=round(live.seconds, 2))
    return None


def brush_down():
    """Press the brush on camera 2's mask, in the gap between camera 3's disk and
    camera 2's ring, right of the centre; the stroke runs upwards."""
    state["from"], state["to"] = screen_point(0.633, 0.44), screen_point(0.633, 0.56)
    x, y = state["from"]
    subprocess.run(["xdotool", "mousemove", str(int(x)), str(int(y))], check=False)
    subprocess.run(["xdotool", "mousedown", "1"], check=False)


def brush_up():
    subprocess.run(["xdotool", "mouseup", "1"], check=False)
    state["stroke_end"] = time.perf_counter()
    now = claimed(1)
    note("stroke", claimed_before=state["claimed"], claimed_after=now)
    if now <= state["claimed"]:
        raise RuntimeError("the brush stroke painted nothing")


def live_updated():
    """The live picture after the stroke: wait for it (Blender stays responsive)."""
    live = live_picture()
    if live.message:
        raise RuntimeError(live.message)
    if live.updates <= state["live"] or live.job is not None:
        if time.perf_counter() - state["stroke_end"] > 600:
            raise RuntimeError(f"the stroke gave no live picture ({live.message or 'timed out'})")
        return AGAIN
    took = time.perf_counter() - state["stroke_end"]
    note("live picture after the stroke", seconds=round(took, 2), stages=live.stages)
    return None


STEPS = [
    ("setup", setup, 3.0),
    ("sidebar", lambda: sidebar("IMAGE_EDITOR"), 1.0),
    ("maximise", maximise, 2.0),
    ("fit", guide_shot, 2.0),
    ("guide shot", lambda: shot("mask_guide.png"), 1.0),
    ("from teapot", from_teapot, 3.0),
    ("fit 3", guide_shot, 2.0),
    ("teapot shot", lambda: shot("mask_from_selected.png"), 1.0),
    ("paint 2", lambda: paint(1), 2.0),
    ("fit 2", guide_shot, 2.0),
    ("drag", drag_start, 1.0),
    ("press", press, 0.5),
    ("move 1", lambda: move(1), 0.3),
    ("move 2", lambda: move(2), 0.3),
    ("move 3", lambda: move(3), 0.3),
    ("move 4", lambda: move(4), 1.0),
    ("drag shot", lambda: shot("mask_drag.png"), 0.5),
    ("release", drag_end, 1.5),
    ("dragged", dragged, 1.0),
    ("ellipse shot", lambda: shot("mask_shape.png"), 1.0),
    ("screen back", restore_screen, 2.0),
    ("turn", lambda: turn_camera(0.05), 2.5),
    ("remade", guide_remade, 0.5),
    ("turn back", lambda: turn_camera(-0.05), 2.5),
    ("remade back", guide_remade, 0.5),
    ("confirm", confirm, 1.5),
    ("confirm shot", lambda: shot("mask_confirm.png"), 1.0),
    ("accept", accept, 2.0),
    ("replaced", restored, 1.0),
    ("tab", click_tab, 2.0),
    ("restore shot", lambda: shot("mask_restore.png"), 1.0),
    ("paint for the live picture", live_on, 2.0),
    ("maximise again", maximise, 2.0),
    ("fit for the live picture", guide_shot, 2.0),
    ("live ready", live_ready, 1.0),
    ("brush down", brush_down, 0.3),
    ("brush 1", lambda: move(1), 0.2),
    ("brush 2", lambda: move(2), 0.2),
    ("brush 3", lambda: move(3), 0.2),
    ("brush 4", lambda: move(4), 0.5),
    ("brush up", brush_up, 0.5),
    ("live updated", live_updated, 1.0),
    ("live shot", lambda: shot("mask_live.png"), 1.0),
]
# A step that returns AGAIN runs again a second later.
AGAIN = "again"
state = {"i": 0}


def tick():
    i = state["i"]
    if i >= len(STEPS):
        note("done")
        bpy.ops.wm.quit_blender()
        return None
    name, fn, wait = STEPS[i]
    try:
        if fn() == AGAIN:
            return 1.0
    except Exception:
        note("failed", at=name, error=traceback.format_exc())
        bpy.ops.wm.quit_blender()
        return None
    state["i"] += 1
    return wait


bpy.app.timers.register(tick, first_interval=4.0)
