"""Benchmark: the Cycles hand-off against a plain Cycles render of camera 1.

    .venv/bin/python bench/cycles.py [--width 480 --height 270 --samples 64 --repeats 2]

Two scenes, each measured on its own and reported with its own ratio:

- "light": the three-camera test scene (fixtures/blender/scenes.py
  ``three_camera_scene``: five objects, 1160 triangles, a sun); the scene issue 4's
  first measurements used.
- "dense": the renderer benchmark's scene (fixtures/blender/scenes.py ``dense_scene``:
  the two-camera rig over a bumpy ground of about 100k triangles), the scene of the
  other speed lines of ``make bench``.

Per scene, these renders alternate (so that all see the same load on a shared machine):
a plain Cycles render from camera 1 ("plain"); the Multiscale engine with shading =
'CYCLES' on the scene's rig ("hand-off": our march, the tables, the shader compile and
Cycles through the custom camera; the target's figure); the hand-off on a rig of
camera 1 alone with every pixel preserved ("one camera"), whose picture is the plain
render's, so that its ratio is the hand-off's overhead alone; and plain Cycles renders
from the rig's other cameras. The multiscale picture shows those cameras' close-ups,
which cost Cycles more per pixel than camera 1's view: "content_ratio_estimate" weighs
each camera's plain render time by the share of the picture it shows (the mean over the
pixels of the tent weights max(0, 1 - |membership - i|)), an estimate of what a plain
render of the multiscale picture would cost against camera 1's, and "overhead_ratio"
is the hand-off's time over that estimate. Cycles charges for an OSL custom camera as
such: "custom_camera_floor" is a plain render from a copy of camera 1 made a custom
camera whose shader computes camera 1's own pinhole rays and nothing else (the hand-off
shader's pinhole branch, one block), so "custom_camera_floor_ratio" is what any OSL
custom camera costs here, and "lowest_ratio_estimate" (that floor times the picture's
own cost) is the ratio a hand-off that cost nothing of its own (no march, no tables, no
texture lookups) would show. The ray field is built before the timed renders (it
is cached across renders while the rig is unchanged); the first hand-off render, which
also builds it, is reported on its own. Times are wall-clock seconds of
``bpy.ops.render.render()`` and the process's CPU seconds over all threads (less
sensitive to other load); ratios use the best of ``--repeats``. The load average
(1 minute) at the start and the end of each scene says how busy the machine was.
Writes bench/cycles.json.
"""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# this file's folder comes off the path: Blender's own add-on is the module "cycles"
BENCH = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != BENCH]
sys.path.insert(0, str(ROOT))
OUT = Path(__file__).with_suffix(".json")
TARGET_RATIO = 1.2
# Triangles of the dense scene's ground (bench/render.py's scene size).
DENSE_TRIANGLES = 100_000


def timed_render(engine):
    """Render with ``engine``: (wall seconds, CPU seconds of this process, all threads)."""
    import bpy

    bpy.context.scene.render.engine = engine
    wall, cpu = time.perf_counter(), time.process_time()
    bpy.ops.render.render()
    return time.perf_counter() - wall, time.process_time() - cpu


def block_figures(report):
    """The pinhole blocks of a hand-off, for the JSON: pixels per side, share of blocks."""
    return {"block": report.block, "share": report.share}


def light_scene(args):
    """The three-camera test rig (optionally with a dense icosphere)."""
    import bpy

    from fixtures.blender.scenes import three_camera_scene

    scene = bpy.context.scene
    three_camera_scene(scene, args.width, args.height)
    if args.dense_sphere:
        bpy.ops.mesh.primitive_ico_sphere_add(
            subdivisions=args.dense_sphere, radius=0.7, location=(-2.5, -1.0, 0.7)
        )
        bpy.context.object.pass_index = 6
        bpy.context.view_layer.update()
    return scene


def dense_scene(args):
    """bench/render.py's 100k-triangle scene."""
    from fixtures.blender.scenes import dense_scene

    return dense_scene(args.width, args.height, DENSE_TRIANGLES)


def floor_camera(scene, camera, pinhole_camera, folder):
    """A copy of ``camera`` (linked to ``scene``) made an OSL custom camera whose shader
    computes ``pinhole_camera``'s own rays (core.geometry.PinholeCamera of ``camera`` at the
    render size): the hand-off's shader with one pinhole block over the whole image."""
    import hashlib

    import numpy as np

    from multiscale_camera.render.cycles_rays import PinholeBlocks, pinhole_affine
    from multiscale_camera.render.cycles_shader import compile_shader

    width, height = pinhole_camera.width, pinhole_camera.height
    blocks = PinholeBlocks(
        max(width, height),
        np.ones((1, 1), dtype=np.int32),
        pinhole_affine(pinhole_camera, np.asarray(camera.matrix_world))[None],
    )
    bytecode = compile_shader(folder, blocks)
    copy = camera.copy()
    copy.data = camera.data.copy()
    copy.name = copy.data.name = "custom camera floor"
    scene.collection.objects.link(copy)
    data = copy.data
    data.type = "CUSTOM"
    data.custom_mode = "INTERNAL"
    data.custom_bytecode = bytecode
    data.custom_bytecode_hash = hashlib.sha1(bytecode.encode()).hexdigest()
    # the shader's rays start on camera 1's near plane
    data.clip_end = camera.data.clip_end - camera.data.clip_start
    data.clip_start = 1e-6
    return copy


def set_rig(scene, items):
    """Make the scene's rig ``items``: [(camera object, mask image)]."""
    scene.multiscale.cameras.clear()
    for cam, mask in items:
        item = scene.multiscale.cameras.add()
        item.camera, item.mask = cam, mask
    import bpy

    bpy.context.view_layer.update()


def measure(scene, args):
    """Time plain, hand-off and one-camera renders of ``scene``; a dict for the JSON."""
    import bpy
    import numpy as np

    from fixtures.blender.handoff import cycles_settings, handoff_reports
    from fixtures.blender.objects import mask_image
    from multiscale_camera.render import pipeline
    from multiscale_camera.render.tables import ray_tables

    cycles_settings(scene, samples=args.samples)
    rig = [(item.camera, item.mask) for item in scene.multiscale.cameras]
    camera1 = rig[0][0]
    scene.camera = camera1
    full = mask_image("full mask", np.ones((args.height, args.width), dtype=bool))
    one_camera = [(camera1, full)]
    for o in scene.objects:
        if o.type == "MESH":
            o.data.calc_loop_triangles()
    triangles = sum(len(o.data.loop_triangles) for o in scene.objects if o.type == "MESH")

    load_start = os.getloadavg()[0]
    timed_render("CYCLES")  # warm-up: kernels, caches
    scene.multiscale.shading = "CYCLES"
    pipeline.clear_fields()
    first, _ = timed_render("MULTISCALE")
    set_rig(scene, one_camera)
    timed_render("MULTISCALE")  # builds the one-camera field
    one_frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    with tempfile.TemporaryDirectory() as folder:
        floor = floor_camera(scene, camera1, one_frame.rig.cameras[0], folder)
    scene.camera = floor
    timed_render("CYCLES")  # warm-up: the custom camera's kernels
    scene.camera = camera1
    runs = {"plain": [], "handoff": [], "one_camera": [], "custom_camera_floor": []}
    runs.update({f"plain_camera_{i + 1}": [] for i in range(1, len(rig))})
    stages, blocks = [], {}
    for _ in range(args.repeats):
        runs["plain"].append(timed_render("CYCLES"))
        scene.camera = floor
        runs["custom_camera_floor"].append(timed_render("CYCLES"))
        for i in range(1, len(rig)):
            scene.camera = rig[i][0]
            runs[f"plain_camera_{i + 1}"].append(timed_render("CYCLES"))
        scene.camera = camera1
        set_rig(scene, rig)
        with handoff_reports() as reports:
            runs["handoff"].append(timed_render("MULTISCALE"))
        stages.append({k: round(v, 3) for k, v in reports[-1].seconds().items()})
        blocks["handoff"] = block_figures(reports[-1])
        set_rig(scene, one_camera)
        with handoff_reports() as reports:
            runs["one_camera"].append(timed_render("MULTISCALE"))
        blocks["one_camera"] = block_figures(reports[-1])
    set_rig(scene, rig)
    bpy.data.cameras.remove(floor.data)
    load_end = os.getloadavg()[0]

    depsgraph = bpy.context.evaluated_depsgraph_get()
    start = time.perf_counter()
    frame = pipeline.prepare_frame(depsgraph)
    prepare = time.perf_counter() - start
    start = time.perf_counter()
    tables = ray_tables(frame)
    march = time.perf_counter() - start

    wall = {k: min(r[0] for r in v) for k, v in runs.items()}
    cpu = {k: min(r[1] for r in v) for k, v in runs.items()}
    ratio = wall["handoff"] / wall["plain"]
    membership = tables.membership.astype(np.float64)
    shares = [
        float(np.clip(1.0 - abs(membership - i), 0.0, 1.0).mean()) for i in range(1, len(rig) + 1)
    ]
    plain_times = [wall["plain"]] + [wall[f"plain_camera_{i + 1}"] for i in range(1, len(rig))]
    content = sum(w * t for w, t in zip(shares, plain_times, strict=True)) / (
        sum(shares) * wall["plain"]
    )
    floor_ratio = wall["custom_camera_floor"] / wall["plain"]
    return {
        "triangles": triangles,
        "cameras": len(rig),
        "seconds": {k: [round(r[0], 3) for r in v] for k, v in runs.items()},
        "cpu_seconds": {k: [round(r[1], 3) for r in v] for k, v in runs.items()},
        "handoff_stage_seconds": stages,
        "pinhole_blocks": blocks,
        "handoff_first_render_seconds": round(first, 3),
        "prepare_frame_cached_field_seconds": round(prepare, 3),
        "march_and_tables_seconds": round(march, 3),
        "segment_casts": int(tables.casts),
        "ratio": round(ratio, 3),
        "cpu_ratio": round(cpu["handoff"] / cpu["plain"], 3),
        "one_camera_ratio": round(wall["one_camera"] / wall["plain"], 3),
        "one_camera_cpu_ratio": round(cpu["one_camera"] / cpu["plain"], 3),
        "ratio_first_render": round(first / wall["plain"], 3),
        "camera_shares": [round(w, 3) for w in shares],
        "content_ratio_estimate": round(content, 3),
        "overhead_ratio": round(ratio / content, 3),
        "custom_camera_floor_ratio": round(floor_ratio, 3),
        "custom_camera_floor_cpu_ratio": round(cpu["custom_camera_floor"] / cpu["plain"], 3),
        "lowest_ratio_estimate": round(floor_ratio * content, 3),
        "meets_target": bool(ratio <= TARGET_RATIO),
        "load_average": [round(load_start, 2), round(load_end, 2)],
    }


SCENES = {
    "light": ("three cameras, five objects", light_scene),
    "dense": ("two cameras, bumpy ground (bench/render.py)", dense_scene),
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=270)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=["light", "dense"])
    parser.add_argument(
        "--dense-sphere",
        type=int,
        default=0,
        metavar="N",
        help="add an icosphere of N subdivisions (20 * 4**(N - 1) triangles) to the light scene",
    )
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()

    import bpy

    import multiscale_camera

    multiscale_camera.register()
    result = {
        "size": [args.width, args.height],
        "samples": args.samples,
        "repeats": args.repeats,
        "cpu_count": os.cpu_count(),
        "target_ratio": TARGET_RATIO,
        "scenes": {},
    }
    for name in args.scenes:
        description, build = SCENES[name]
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = build(args)
        figures = measure(scene, args)
        result["scenes"][name] = {"description": description, **figures}
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    for name, figures in result["scenes"].items():
        runs = figures["seconds"]
        verdict = "meets" if figures["meets_target"] else "does not meet"
        print(
            f"{name} scene ({figures['description']}, {figures['triangles']} triangles): "
            f"hand-off {min(runs['handoff']):.2f} s vs plain Cycles {min(runs['plain']):.2f} s "
            f"= {figures['ratio']:.2f}x ({figures['cpu_ratio']:.2f}x in CPU seconds), "
            f"{verdict} the <= {TARGET_RATIO}x target; one-camera rig (same picture as "
            f"plain: overhead alone) {figures['one_camera_ratio']:.2f}x; the multiscale "
            f"picture's own cost, estimated from plain renders of each camera, "
            f"{figures['content_ratio_estimate']:.2f}x, the hand-off "
            f"{figures['overhead_ratio']:.2f}x that; any OSL custom camera "
            f"{figures['custom_camera_floor_ratio']:.2f}x, so a hand-off costing nothing "
            f"of its own would be {figures['lowest_ratio_estimate']:.2f}x; "
            f"march + tables {figures['march_and_tables_seconds']:.2f} s; "
            f"load {figures['load_average'][0]:.1f} to {figures['load_average'][1]:.1f}"
        )
    multiscale_camera.unregister()


if __name__ == "__main__":
    main()
