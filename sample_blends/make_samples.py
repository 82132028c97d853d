"""Build the sample .blend files.

    tools/blender -b --factory-startup --python-exit-code 1 --python sample_blends/make_samples.py
    tools/blender -b --factory-startup --python-exit-code 1 \
        --python sample_blends/make_samples.py -- --out DIR --only two_camera

Writes demo.blend, dolly.blend (the demo animated), two_camera.blend, galleon.blend and
volume_demo.blend (compressed, masks packed; the volume demo's voxels in
volume_demo_phantom.nrrd beside it) next to this script, or into --out. The scenes are
those of fixtures/blender/samples.py.
"""

import argparse
import os
import sys

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
# Blender runs this file as a script: the repository root holds the package and fixtures/
sys.path.insert(0, REPO)
from fixtures.blender import samples  # noqa: E402

# name -> builder(scene, out_dir): the folder the .blend (and any data file) goes to
BUILDERS = {
    "demo": lambda scene, _out: samples.build_demo(scene),
    "dolly": lambda scene, _out: samples.build_dolly(scene),
    "two_camera": lambda scene, _out: samples.build_two_camera(scene),
    "galleon": lambda scene, _out: samples.build_galleon(scene),
    "volume_demo": samples.build_volume_demo,
}


def enable_multiscale():
    """Register the package from this checkout (--factory-startup enables no extension)."""
    if hasattr(bpy.types.Scene, "multiscale"):
        return
    import multiscale_camera

    multiscale_camera.register()


def make(name, out_dir):
    bpy.ops.wm.read_homefile(use_empty=True)
    BUILDERS[name](bpy.context.scene, out_dir)
    path = os.path.join(out_dir, f"{name}.blend")
    if os.path.exists(path):
        os.remove(path)  # a fresh file, not a .blend1 backup of the old one
    bpy.ops.wm.save_as_mainfile(filepath=path, compress=True, relative_remap=True)
    print(f"wrote {path}")
    return path


def main(argv):
    parser = argparse.ArgumentParser(prog="make_samples.py")
    parser.add_argument("--out", default=HERE, help="output folder (default: sample_blends/)")
    parser.add_argument("--only", nargs="+", choices=sorted(BUILDERS), default=sorted(BUILDERS))
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    enable_multiscale()
    for name in args.only:
        make(name, args.out)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else [])
