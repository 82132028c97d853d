"""Benchmark: what the Cycles hand-off's tiles cost (``cycles.cancel_tile``).

    .venv/bin/python bench/cycles_tiles.py [--width 640 --height 360 --samples 64 --repeats 1]

The two-camera test scene (fixtures/blender/scenes.py ``two_camera_scene``, AUTO's
field, shading = 'CYCLES', no adaptive sampling, no denoising) rendered with the
hand-off's tiles (at most ``cycles.TILE_PIXEL_SAMPLES`` pixel samples a tile, so that
Esc and Ctrl-C stop Cycles within a tile) and in one tile (``cancel_tile`` replaced by
Cycles' own 2048 px, larger than the image), alternately, so that both see the same
load. The field is built before the timed renders. Prints one JSON line: the seconds of
Cycles' own stage (``HandoffReport.cycles``) per render, the tile size and count, and
the load average (1 minute) at the start and the end.
"""

import argparse
import json
import os
import sys
from pathlib import Path

# this file's folder comes off the path: its cycles.py would stand for Blender's add-on
BENCH = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != BENCH]
sys.path.insert(0, str(BENCH.parent))

import bpy  # noqa: E402

import multiscale_camera  # noqa: E402
from fixtures.blender.handoff import cycles_settings, handoff_reports  # noqa: E402
from fixtures.blender.scenes import two_camera_scene  # noqa: E402
from multiscale_camera.render import cycles  # noqa: E402

ONE_TILE = 2048  # Cycles' own default tile size: one tile for an image under it


def load():
    return float(os.getloadavg()[0])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=360)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    multiscale_camera.register()
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    two_camera_scene(scene, args.width, args.height)
    scene.multiscale.method = "AUTO"
    scene.multiscale.shading = "CYCLES"
    cycles_settings(scene, args.samples)
    scene.cycles.samples = 1
    bpy.ops.render.render()  # the field, built and cached
    scene.cycles.samples = args.samples
    tiled = cycles.cancel_tile
    tile = tiled(args.samples)
    tiles = -(-args.width // tile) * -(-args.height // tile)
    seconds = {"tiled": [], "one_tile": []}
    start = load()
    for _ in range(args.repeats):
        for mode in ("tiled", "one_tile"):
            cycles.cancel_tile = tiled if mode == "tiled" else lambda *a, **k: ONE_TILE
            with handoff_reports() as reports:
                bpy.ops.render.render()
            seconds[mode].append(round(reports[0].cycles, 2))
    cycles.cancel_tile = tiled
    row = {
        "size": [args.width, args.height],
        "samples": args.samples,
        "tile_px": tile,
        "tiles": tiles,
        "cycles_seconds": seconds,
        "load": [round(start, 2), round(load(), 2)],
    }
    print(json.dumps(row))


if __name__ == "__main__":
    main()
