"""Benchmark: the Cycles hand-off against a plain Cycles render of camera 1.

    .venv/bin/python bench/cycles.py [--width 480 --height 270 --samples 64 --repeats 2]

The scene is the three-camera rig of tests/blender/test_cycles.py (five objects, a sun).
Times are wall-clock seconds of ``bpy.ops.render.render()`` (and the process's CPU
seconds over all threads, less sensitive to other load on the machine): a plain Cycles render from
camera 1, and the Multiscale engine with shading = 'CYCLES' (our march, the tables, the
shader compile and Cycles through the custom camera), the ray field already built (it is
cached across renders while the rig is unchanged), the two alternating; the first
hand-off render, which also builds the field, is reported on its own. The load average
(1 minute) at the start and the end says how busy the machine was. Writes
bench/cycles.json.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# this file's folder comes off the path: Blender's own add-on is the module "cycles"
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).parent]
sys.path.insert(0, str(ROOT))
OUT = Path(__file__).with_suffix(".json")
TARGET_RATIO = 1.2


def timed_render(engine):
    """Render with ``engine``: (wall seconds, CPU seconds of this process, all threads)."""
    import bpy

    bpy.context.scene.render.engine = engine
    wall, cpu = time.perf_counter(), time.process_time()
    bpy.ops.render.render()
    return time.perf_counter() - wall, time.process_time() - cpu


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=270)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--dense-sphere",
        type=int,
        default=0,
        metavar="N",
        help="add an icosphere of N subdivisions (20 * 4**(N - 1) triangles) to the scene",
    )
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()

    import bpy

    import multiscale_camera
    from multiscale_camera.render import cycles, pipeline
    from multiscale_camera.render.tables import ray_tables
    from tests.blender.test_cycles import cycles_settings, three_camera_scene

    multiscale_camera.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    cams, _masks = three_camera_scene(scene, args.width, args.height)
    cycles_settings(scene, samples=args.samples)
    scene.camera = cams[0]
    if args.dense_sphere:
        bpy.ops.mesh.primitive_ico_sphere_add(
            subdivisions=args.dense_sphere, radius=0.7, location=(-2.5, -1.0, 0.7)
        )
        bpy.context.object.pass_index = 6
        bpy.context.view_layer.update()
    for o in scene.objects:
        if o.type == "MESH":
            o.data.calc_loop_triangles()
    triangles = sum(len(o.data.loop_triangles) for o in scene.objects if o.type == "MESH")

    load_start = os.getloadavg()[0]
    timed_render("CYCLES")  # warm-up: kernels, caches
    scene.multiscale.shading = "CYCLES"
    pipeline.clear_fields()
    first, _ = timed_render("MULTISCALE")
    # alternate the two, so that both see the same load on a shared machine
    plain, handoff, plain_cpu, handoff_cpu, stages = [], [], [], [], []
    for _ in range(args.repeats):
        wall, cpu = timed_render("CYCLES")
        plain.append(wall)
        plain_cpu.append(cpu)
        wall, cpu = timed_render("MULTISCALE")
        handoff.append(wall)
        handoff_cpu.append(cpu)
        stages.append({k: round(v, 3) for k, v in cycles.LAST_SECONDS.items()})

    depsgraph = bpy.context.evaluated_depsgraph_get()
    start = time.perf_counter()
    frame = pipeline.prepare_frame(depsgraph)
    prepare = time.perf_counter() - start
    start = time.perf_counter()
    tables = ray_tables(frame)
    march = time.perf_counter() - start

    result = {
        "size": [args.width, args.height],
        "samples": args.samples,
        "triangles": triangles,
        "cpu_count": os.cpu_count(),
        "plain_cycles_seconds": [round(t, 3) for t in plain],
        "handoff_seconds": [round(t, 3) for t in handoff],
        "plain_cycles_cpu_seconds": [round(t, 3) for t in plain_cpu],
        "handoff_cpu_seconds": [round(t, 3) for t in handoff_cpu],
        "handoff_stage_seconds": stages,
        "handoff_first_render_seconds": round(first, 3),
        "prepare_frame_cached_field_seconds": round(prepare, 3),
        "march_and_tables_seconds": round(march, 3),
        "segment_casts": int(tables.casts),
        "ratio": round(min(handoff) / min(plain), 3),
        "cpu_ratio": round(min(handoff_cpu) / min(plain_cpu), 3),
        "ratio_first_render": round(first / min(plain), 3),
        "target_ratio": TARGET_RATIO,
        "load_average": [round(load_start, 2), round(os.getloadavg()[0], 2)],
    }
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    print(
        f"hand-off {min(handoff):.2f} s vs plain Cycles {min(plain):.2f} s: "
        f"{result['ratio']:.2f}x (target <= {TARGET_RATIO}x); first render with the field "
        f"build {first:.2f} s; march + tables {march:.2f} s"
    )
    multiscale_camera.unregister()


if __name__ == "__main__":
    main()
