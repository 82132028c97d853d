"""Benchmark: the renderer on a 100k-triangle scene at 1920x1080, one sample.

    .venv/bin/python bench/render.py [--width 1920 --height 1080] [--triangles 100000]

Reports, in one run: the raw ``BVHTree.ray_cast`` rate on the scene, in a bare loop
over prepared lists on the same tree: over the very segments the engine casts (recorded
from a render of the middle tiles: same rays, same tree), also in slices between the
tiles of the timed render (so that both rates see the same machine), and over camera
1's straight rays; the engine's segment-cast rate (segment casts over the time of the
whole tile loop: ray sampling, culling, casting, shading with its shadow rays, and
passes), in-process per CPU second, over the time of the march alone (culling,
conversion, casting, hit bookkeeping), and per second of the tile loop in the engine's
worker processes (one per core by default) against one bare loop timed just before and
after it, and the share one process could reach were the casts its only cost (its
segment casts over its segment and shadow casts, both at the raw rate); the time of
the render with the field built cold (tiles in the engine's processes) and with it
cached (the engine keeps built fields in memory), each as field + frame preparation +
tiles; the cancel latency (from the first ``should_stop`` that
says stop to the tile loop ending). CPU seconds (of this process, and of its reaped
workers where they run) are reported next to wall seconds: the machine may be shared.
Writes bench/render.json.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = Path(__file__).with_suffix(".json")
# Segment casts replayed in a bare loop after every tile of the timed render.
INTERLEAVED_CASTS = 4000


def raw_rate(frame, seconds=3.0):
    """(per wall second, per CPU second) of a bare BVHTree.ray_cast loop over camera 1's
    straight rays through the pixel centres of the image's middle rows."""
    import numpy as np

    cam = frame.rig.cameras[0]
    w, h = frame.size
    # pixel centres in row order, as the tiles go (coherent rays: the same cache luck)
    rows = max(1, min(h, 250_000 // max(w, 1)))
    py, px = np.mgrid[0:rows, 0:w] + 0.5
    py = py + (h - rows) // 2
    d = cam.directions(px.ravel(), py.ravel())
    o = cam.near_points(d)
    far = [float(cam.clip_end)] * len(d)
    return bare_rate(frame.tree.ray_cast, o.tolist(), d.tolist(), far, seconds)


class RecordingTree:
    """A BVHTree stand-in that records the arguments of every ``ray_cast``."""

    def __init__(self, tree):
        self.tree, self.calls = tree, []

    def ray_cast(self, origin, direction, distance):
        self.calls.append((origin, direction, distance))
        return self.tree.ray_cast(origin, direction, distance)


def engine_casts(frame, tiles=8):
    """([origin], [direction], [distance]): the segment casts (not the shadow rays) the
    engine makes for ``tiles`` tiles in the middle of the image, as it passes them."""
    from multiscale_camera.render import pipeline

    recorder = RecordingTree(frame.tree)
    all_tiles = pipeline.tiles(frame)
    middle = len(all_tiles) // 2
    saved = frame.tree, frame.lights, frame.casts, frame.shadow_casts, frame.rays
    frame.tree, frame.lights = recorder, []  # no lights: only segment casts are recorded
    try:
        for row0, row1 in all_tiles[max(0, middle - tiles // 2) : middle + tiles - tiles // 2]:
            pipeline.render_rows(frame, row0, row1)
    finally:
        frame.tree, frame.lights, frame.casts, frame.shadow_casts, frame.rays = saved
    origins, dirs, lengths = zip(*recorder.calls, strict=True)
    return list(origins), list(dirs), list(lengths)


def bare_rate(cast, origins, dirs, lengths, seconds=3.0):
    """(per wall second, per CPU second, CPU seconds) of ``cast`` in a bare loop over
    prepared lists (at least once through, then again until ``seconds`` of CPU time),
    results dropped, the cyclic collector paused: the best case."""
    from multiscale_camera.render.raycast import gc_paused

    done, start, cpu = 0, time.perf_counter(), time.process_time()
    with gc_paused():
        while not done or time.process_time() - cpu < seconds:
            for a, b, c in zip(origins, dirs, lengths, strict=True):
                cast(a, b, c)
            done += len(origins)
    spent = time.process_time() - cpu
    return done / (time.perf_counter() - start), done / spent, spent


def cpu_with_children():
    """CPU seconds of this process, its reaped children and the worker runtime's live
    workers (they stay across renders: Linux's /proc tells their times)."""
    from multiscale_camera.core.runtime import runtime

    t = os.times()
    seconds = t[0] + t[1] + t[2] + t[3]
    for pid in runtime().pids():
        try:
            with open(f"/proc/{pid}/stat") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        seconds += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return seconds


def render_tiles(frame, should_stop=None, processes=1):
    """The engine's tile loop (without writing a Render Result)."""
    from multiscale_camera.render import pipeline, workers

    for _rows, _passes in workers.render_tiles(
        frame, pipeline.tiles(frame), processes, should_stop
    ):
        pass


def cancel_latency(frame, after, processes=1):
    """Seconds from the first stop request (made ``after`` seconds into the tile loop)
    until the loop has ended."""
    from multiscale_camera.core.errors import Cancelled

    asked = []
    start = time.perf_counter()

    def should_stop():
        now = time.perf_counter()
        if now - start >= after:
            asked.append(now)
            return True
        return False

    try:
        render_tiles(frame, should_stop, processes)
    except Cancelled:
        pass
    if not asked:  # the render ended before the request
        return None
    return time.perf_counter() - asked[0]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--triangles", type=int, default=100_000)
    parser.add_argument("--samples", type=int, default=1)
    args = parser.parse_args()

    import bpy

    import multiscale_camera
    from fixtures.blender.scenes import dense_scene
    from multiscale_camera.adapters.scene import processes_of
    from multiscale_camera.render import pipeline, workers

    multiscale_camera.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = dense_scene(args.width, args.height, args.triangles)
    scene.multiscale.samples = args.samples
    settings = scene.multiscale
    depsgraph = bpy.context.evaluated_depsgraph_get()
    # a cold render: the field built now (the disk cache too is emptied)
    pipeline.clear_fields()
    # the engine's own worker count (one per core unless the threads are fixed)
    processes = workers.worker_count(processes_of(scene))
    t0, c0 = time.perf_counter(), cpu_with_children()
    frame = pipeline.prepare_frame(depsgraph)
    t1, c1 = time.perf_counter(), cpu_with_children()
    render_tiles(frame, processes=processes)
    t2, c2 = time.perf_counter(), cpu_with_children()
    cold_stages = dict(frame.seconds)
    # the same render again, the field cached in memory as the engine keeps it; the
    # march is timed on its own
    march_time = [0.0, 0.0]
    march = pipeline.march

    def timed_march(*a, **k):
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            return march(*a, **k)
        finally:
            march_time[0] += time.perf_counter() - wall
            march_time[1] += time.process_time() - cpu

    t3, c3 = time.perf_counter(), time.process_time()
    frame = pipeline.prepare_frame(depsgraph)
    t4, c4 = time.perf_counter(), time.process_time()
    cached_stages = dict(frame.seconds)
    # the raw rate is also sampled between the tiles (a slice of the engine's own segment
    # casts after every tile, timed apart from it), so that both see the same machine:
    # on a shared machine the speed of a core drifts by up to 2x within a minute
    same = engine_casts(frame)
    frame.casts = frame.shadow_casts = frame.rays = 0
    pipeline.march = timed_march
    tile_time = [0.0, 0.0]
    interleaved = [0, 0.0]
    try:
        loop = workers.render_tiles(frame, pipeline.tiles(frame), 1, None)
        while True:
            wall, cpu = time.perf_counter(), time.process_time()
            done = next(loop, None)
            tile_time[0] += time.perf_counter() - wall
            tile_time[1] += time.process_time() - cpu
            if done is None:
                break
            a = interleaved[0] % len(same[0])
            piece = [x[a : a + INTERLEAVED_CASTS] for x in same]
            interleaved[1] += bare_rate(frame.tree.ray_cast, *piece, seconds=0.0)[2]
            interleaved[0] += len(piece[0])
    finally:
        pipeline.march = march
    t5, c5 = time.perf_counter(), time.process_time()
    warm, warm_cpu = tile_time
    raw_between = interleaved[0] / interleaved[1]
    seg_rate, seg_rate_cpu = frame.casts / warm, frame.casts / warm_cpu
    counts = frame.rays, frame.casts, frame.shadow_casts
    # raw ray_cast, same tree: the engine's own segment casts, and camera 1's straight rays
    raw, raw_cpu = bare_rate(frame.tree.ray_cast, *same)[:2]
    cam_raw, cam_raw_cpu = raw_rate(frame)[:2]
    latencies = []
    for after in (0.5, 1.5, 3.0):
        frame.casts = frame.shadow_casts = frame.rays = 0
        latencies.append(cancel_latency(frame, after))
    # as the engine runs them, in its worker processes (CPU: this process and its reaped
    # children), with the bare loop timed just before and just after, on one core
    raw_before = bare_rate(frame.tree.ray_cast, *same, seconds=1.5)[0]
    frame.casts = frame.shadow_casts = frame.rays = 0
    before = cpu_with_children()
    t6 = time.perf_counter()
    render_tiles(frame, processes=processes)
    pooled = time.perf_counter() - t6
    pooled_cpu = cpu_with_children() - before
    pooled_casts = frame.casts
    raw_after = bare_rate(frame.tree.ray_cast, *same, seconds=1.5)[0]
    raw_around = 0.5 * (raw_before + raw_after)
    pooled_latency = cancel_latency(frame, 1.5, processes)
    frame.rays, frame.casts, frame.shadow_casts = counts
    result = {
        "size": [args.width, args.height],
        "samples": args.samples,
        "triangles": int(len(frame.geometry)),
        "field_settings": {
            "method": settings.method,
            "quality": settings.quality,
            "simplify_px": round(settings.simplify_px, 3),
            "note": "the add-on's defaults (the bench sets none of them)",
        },
        "cpu_count": os.cpu_count(),
        "raw_ray_cast_per_s": round(raw),
        "raw_ray_cast_per_cpu_s": round(raw_cpu),
        "raw_rays_measured_on": f"the engine's own {len(same[0])} segment casts of 8 middle "
        "tiles, replayed in a bare loop on the same tree",
        "raw_camera1_rays_per_s": round(cam_raw),
        "raw_camera1_rays_per_cpu_s": round(cam_raw_cpu),
        "engine_segment_casts_per_s": round(seg_rate),
        "engine_segment_casts_per_cpu_s": round(seg_rate_cpu),
        "engine_share_of_raw": round(seg_rate / raw, 3),
        "engine_share_of_raw_cpu": round(seg_rate_cpu / raw_cpu, 3),
        "raw_ray_cast_per_cpu_s_between_tiles": round(raw_between),
        "engine_share_of_raw_cpu_between_tiles": round(seg_rate_cpu / raw_between, 3),
        "march_segment_casts_per_cpu_s": round(frame.casts / march_time[1]),
        "march_share_of_raw_cpu": round(frame.casts / march_time[1] / raw_cpu, 3),
        "engine_rays_per_cpu_s": round(frame.rays / warm_cpu),
        "engine_all_casts_per_s": round((frame.casts + frame.shadow_casts) / warm),
        # another view, not the target's: segment and shadow casts together per CPU second
        "engine_all_casts_per_cpu_s": round((frame.casts + frame.shadow_casts) / warm_cpu),
        "engine_all_casts_share_of_raw_cpu": round(
            (frame.casts + frame.shadow_casts) / warm_cpu / raw_cpu, 3
        ),
        # the share of raw one process could reach if everything but the casts (ray
        # sampling, culling, shading, passes) took no time at all: its shadow casts run
        # on the same tree at the same rate, and the target counts segment casts only
        "engine_share_of_raw_ceiling_in_process": round(
            frame.casts / (frame.casts + frame.shadow_casts), 3
        ),
        "rays": frame.rays,
        "segment_casts": frame.casts,
        "shadow_casts": frame.shadow_casts,
        "segment_casts_per_ray": round(frame.casts / max(frame.rays, 1), 3),
        # the tile loop as the engine runs it: one worker process per core by default
        "engine_processes": processes,
        "engine_segment_casts_per_s_in_its_processes": round(pooled_casts / pooled),
        "raw_ray_cast_per_s_one_loop_around_that_run": round(raw_around),
        "engine_in_its_processes_share_of_one_raw_loop": round(
            pooled_casts / pooled / raw_around, 3
        ),
        "seconds": {
            "cold_field": {
                "prepare_frame": round(t1 - t0, 2),
                "stages": {k: round(v, 2) for k, v in cold_stages.items()},
                "tiles": round(t2 - t1, 2),
                "render_total": round(t2 - t0, 2),
            },
            "cached_field": {
                "prepare_frame": round(t4 - t3, 2),
                "stages": {k: round(v, 2) for k, v in cached_stages.items()},
                "tiles": round(warm, 2),
                "march": round(march_time[0], 2),
                "render_total": round(t5 - t3, 2),
            },
            f"tiles_{processes}_processes": round(pooled, 2),
            f"cached_field_render_total_{processes}_processes": round(t4 - t3 + pooled, 2),
        },
        # CPU seconds of this process: less sensitive than wall time to other work
        "cpu_seconds": {
            "cold_field": {
                "prepare_frame": round(c1 - c0, 2),
                "tiles": round(c2 - c1, 2),
                "render_total": round(c2 - c0, 2),
            },
            "cached_field": {
                "prepare_frame": round(c4 - c3, 2),
                "tiles": round(warm_cpu, 2),
                "march": round(march_time[1], 2),
                "render_total": round(c5 - c3, 2),
            },
            f"tiles_{processes}_processes_with_children": round(pooled_cpu, 2),
        },
        "load_average_1min": round(os.getloadavg()[0], 2),
        "cancel_latency_s": [None if x is None else round(x, 3) for x in latencies],
        f"cancel_latency_{processes}_processes_s": None
        if pooled_latency is None
        else round(pooled_latency, 3),
        "note": "2 cores shared with other work while measured: wall times are noisy",
    }
    print(json.dumps(result, indent=1))
    print(
        f"raw ray_cast {raw_cpu / 1e6:.2f} M/CPU s (engine's segments; camera 1's rays "
        f"{cam_raw_cpu / 1e6:.2f}) | engine {seg_rate_cpu / 1e6:.2f} M segment casts/CPU s "
        f"({seg_rate_cpu / raw_cpu:.0%} of raw; {seg_rate_cpu / raw_between:.0%} of the raw "
        f"rate sampled between the tiles; wall-clock {seg_rate / raw:.0%}); in the engine's "
        f"{processes} processes {pooled_casts / pooled / 1e6:.2f} M segment casts/s, "
        f"{pooled_casts / pooled / raw_around:.0%} of one bare loop; march alone "
        f"{frame.casts / march_time[1] / raw_cpu:.0%}, segment and shadow casts together "
        f"{(frame.casts + frame.shadow_casts) / warm_cpu / raw_cpu:.0%}; one process "
        f"could reach {frame.casts / (frame.casts + frame.shadow_casts):.0%} if only its "
        f"casts took time, "
        f"{frame.casts / frame.rays:.2f} casts/ray "
        f"| {args.width}x{args.height} {len(frame.geometry)} tris: cold field {t2 - t0:.1f} s "
        f"(CPU {c2 - c0:.1f} s), cached field {t5 - t3:.1f} s (CPU {c5 - c3:.1f} s); tiles in "
        f"{processes} processes {pooled:.1f} s | cancel latency max "
        f"{max(x or 0.0 for x in latencies):.3f} s ({pooled_latency or 0.0:.3f} s in "
        f"{processes} processes) | load {os.getloadavg()[0]:.2f}"
    )
    OUT.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
