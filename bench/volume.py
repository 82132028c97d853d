"""Benchmark: volume ray casting of a 256^3 volume at 1920x1080.

    .venv/bin/python bench/volume.py [--width 1920 --height 1080 --voxels 256]
        [--configs single multiscale] [--threads 2]

The volume is the sample phantom (fixtures/phantom.py: skin, organ, vessel tree)
in a 2 m cube, seen by the volume demo's rig:

- single: camera 1 alone with a full mask (straight rays), the body's transfer function;
- multiscale: the three cameras and masks of the demo (SCALAR_FIELD, STANDARD), a
  transfer function each, blended by membership along the bent rays.

Each configuration runs in a fresh process (so its peak memory is its own): the phantom
is loaded (made once into .cache/), the ray field prepared (timed apart), then every
image row is rendered tile
by tile as the renderer does (bundle, march, composite), with gradient shading and the
default step of one voxel (--step to change it). Prints a table and writes bench/volume.json,
with the CPU seconds of the render and the machine's 1-minute load average before and
after it (other work may share the cores).
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = Path(__file__).with_suffix(".json")
CONFIGS = ("single", "multiscale")
TARGET_SECONDS = 60.0


def rig_for(config, width, height):
    import numpy as np

    from fixtures import phantom, rigs
    from fixtures.masks import radius, ring_masks
    from multiscale_camera.core.geometry import Rig

    cams = tuple(
        rigs.camera(
            name,
            rigs.orbit(target, distance, az, el),
            target,
            width,
            height,
            clip_start=clip,
            clip_end=100.0,
        )
        for name, target, distance, az, el, clip in phantom.DEMO_CAMERAS
    )
    if config == "single":
        return Rig(cams[:1], np.ones((1, height, width), bool)), "IMAGE_BLEND"
    # the radii are pixels of a 640-pixel-wide image
    masks = ring_masks(radius(width, height) * (640 / width), phantom.DEMO_RADII)
    return Rig(cams, masks), "SCALAR_FIELD"


def phantom_file(voxels):
    """The phantom's voxels, made once in a process of their own (its temporaries would
    otherwise count in the renderer's peak memory) and kept in .cache/."""
    path = ROOT / ".cache" / f"phantom-{voxels}.npy"
    if not path.is_file():
        path.parent.mkdir(exist_ok=True)
        code = (
            f"import sys, numpy as np; sys.path.insert(0, {str(ROOT)!r}); "
            f"from fixtures import phantom; np.save({str(path)!r}, phantom.phantom({voxels}))"
        )
        subprocess.run([sys.executable, "-c", code], check=True)
    return path


def run_one(config, width, height, voxels, threads, step):
    import numpy as np

    from fixtures import phantom
    from multiscale_camera.core import volume as V
    from multiscale_camera.core.methods import prepare, settings_for

    start = time.perf_counter()
    values = np.load(phantom_file(voxels))
    world = np.eye(4)
    world[:3, 3] = phantom.BODY_CENTRE
    vol = V.ScalarVolume(values, V.box_to_index(values.shape, (-1,) * 3, (1,) * 3, world))
    t_phantom = time.perf_counter() - start

    rig, method = rig_for(config, width, height)
    start = time.perf_counter()
    fld = prepare(rig, method, settings_for("STANDARD"))
    t_field = time.perf_counter() - start

    tables = np.stack([V.table_from_points(p) for p in phantom.DEMO_TFS.values()])
    tables = tables[: len(rig.cameras)]
    start = time.perf_counter()
    scene = V.VolumeScene.build(vol, tables, step=step, shading=True)
    t_setup = time.perf_counter() - start

    load_before = os.getloadavg()[0]
    rows = max(1, 16384 // width)  # render/pipeline.rows_per_tile
    image = np.zeros((height, width, 4), np.float32)
    samples = skipped = 0
    t_rays = t_march = 0.0
    cpu = time.process_time()
    for row0 in range(0, height, rows):
        row1 = min(row0 + rows, height)
        t0 = time.perf_counter()
        iy, ix = np.mgrid[row0:row1, 0:width]
        bundle = fld.rays(ix.ravel(), iy.ravel())
        t1 = time.perf_counter()
        res = V.march_volume(
            scene, bundle.vertices, bundle.membership, bundle.reach, threads=threads
        )
        t_rays += t1 - t0
        t_march += time.perf_counter() - t1
        image[row0:row1, :, :3] = res.colour.reshape(row1 - row0, width, 3)
        image[row0:row1, :, 3] = res.alpha.reshape(row1 - row0, width)
        samples += res.samples
        skipped += res.skipped
    cpu = time.process_time() - cpu
    seen = float((image[..., 3] > 0.01).mean())
    return {
        "config": config,
        "method": method,
        "size": [width, height],
        "voxels": [voxels] * 3,
        "step_voxels": step,
        "threads": threads,
        "seconds": {
            "load_volume": round(t_phantom, 2),
            "field": round(t_field, 2),
            "volume_setup": round(t_setup, 2),
            "rays": round(t_rays, 2),
            "march": round(t_march, 2),
            "render": round(t_setup + t_rays + t_march, 2),
        },
        "cpu_seconds_render": round(cpu, 2),
        # other work shares the cores: the 1-minute load average before and after
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "samples_M": round(samples / 1e6, 2),
        "skipped_samples_M": round(skipped / 1e6, 2),
        "ns_per_sample": round(t_march / max(samples, 1) * 1e9, 1),
        "covered_pixels": round(seen, 3),
        "peak_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--voxels", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--step", type=float, default=1.0, help="samples apart, voxels")
    parser.add_argument("--configs", nargs="+", choices=CONFIGS, default=list(CONFIGS))
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        row = run_one(args.one, args.width, args.height, args.voxels, args.threads, args.step)
        print(json.dumps(row))
        return
    rows = []
    for config in args.configs:
        cmd = [
            sys.executable,
            __file__,
            "--one",
            config,
            "--width",
            str(args.width),
            "--height",
            str(args.height),
            "--voxels",
            str(args.voxels),
            "--threads",
            str(args.threads),
            "--step",
            str(args.step),
        ]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        row = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(row)
        s = row["seconds"]
        print(
            f"{config:10s} {row['size'][0]}x{row['size'][1]} {args.voxels}^3: render "
            f"{s['render']:.1f} s (march {s['march']:.1f}, rays {s['rays']:.1f}; field "
            f"{s['field']:.1f}), {row['samples_M']:.0f} M samples, "
            f"{row['ns_per_sample']:.0f} ns/sample, peak {row['peak_mb']:.0f} MB "
            f"(CPU {row['cpu_seconds_render']:.1f} s; load {row['load_average_1min']})",
            flush=True,
        )
    result = {
        "target_render_seconds": TARGET_SECONDS,
        "machine_note": "2 cores shared with other work: timings are noisy",
        "results": rows,
    }
    OUT.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
