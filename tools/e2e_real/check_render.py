"""Run in a real Blender with the extension installed (tools/e2e_real/run.sh):
check that it is enabled and registered, run the workflow's operators headless, render
the open file and write a summary JSON.

    blender -b demo.blend --python check_render.py -- --out DIR [--percentage 50]
"""

import argparse
import json
import os
import sys
import time

import bpy


def main(argv):
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", required=True)
    parser.add_argument("--percentage", type=int, default=50)
    parser.add_argument("--quality", default="PREVIEW")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    summary = {"blender": bpy.app.version_string, "python": sys.version.split()[0]}
    import numpy

    summary["numpy"] = numpy.__version__
    summary["enabled"] = [m for m in bpy.context.preferences.addons.keys() if "multiscale" in m]
    module = sys.modules[summary["enabled"][0]] if summary["enabled"] else None
    summary["registered"] = {
        "engine": "MULTISCALE"
        in {getattr(e, "bl_idname", None) for e in bpy.types.RenderEngine.__subclasses__()},
        "panel": hasattr(bpy.types, "MULTISCALE_PT_main"),
        "operators": sorted(n for n in dir(bpy.ops.multiscale) if not n.startswith("_")),
    }
    if module is not None:
        panels = sys.modules[module.__name__ + ".ui.panels"]
        summary["shading_option_shown"] = panels.shading_option_shown()
    scene = bpy.context.scene
    settings = scene.multiscale
    settings.quality = args.quality
    scene.render.resolution_percentage = args.percentage
    summary["cameras"] = [i.camera.name for i in settings.cameras]
    summary["validate"] = sorted(bpy.ops.multiscale.validate())
    summary["validation"] = json.loads(settings.validation or "[]")
    t = time.perf_counter()
    summary["compute_field"] = sorted(bpy.ops.multiscale.compute_field())
    summary["compute_seconds"] = round(time.perf_counter() - t, 2)
    report = json.loads(settings.report)
    summary["report"] = {k: report[k] for k in ("method", "quality", "folds", "cached")}
    scene.render.filepath = os.path.join(args.out, "render.png")
    scene.render.image_settings.file_format = "PNG"
    t = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    summary["render_seconds"] = round(time.perf_counter() - t, 2)
    summary["render"] = scene.render.filepath
    img = bpy.data.images.load(scene.render.filepath)
    px = numpy.empty(img.size[0] * img.size[1] * 4, numpy.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(-1, 4)
    summary["render_size"] = list(img.size)
    summary["render_mean_rgb"] = [round(float(v), 4) for v in px[:, :3].mean(0)]
    summary["render_std"] = round(float(px[:, :3].std()), 4)
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print("E2E_SUMMARY", json.dumps(summary))
    ok = (
        summary["enabled"]
        and all(summary["registered"][k] for k in ("engine", "panel"))
        and summary["render_std"] > 0.02
        and summary["compute_field"] == ["FINISHED"]
    )
    if not ok:
        sys.exit(1)


main(sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else [])
