"""Acceptance: a two-camera scene rendered headless through $BLENDER shows, in each
camera's eroded mask, the object that camera's own straight pinhole ray hits."""

import json

import numpy as np
import pytest

from multiscale_camera.core.quality import erode
from tests.conftest import REPO
from tests.exr import read_passes

REGISTER = (
    "import sys; sys.path.insert(0, {repo!r}); import bpy, multiscale_camera; "
    "multiscale_camera.register(); "
)

# The reference: for every camera, Blender's own view frame and scene.ray_cast along
# straight pinhole rays from the near plane, written to a JSON file of pass indices.
REFERENCE = """
import json, sys, bpy, numpy as np
from mathutils import Vector
out = sys.argv[sys.argv.index("--") + 1]
scene = bpy.context.scene
depsgraph = bpy.context.evaluated_depsgraph_get()
w = scene.render.resolution_x * scene.render.resolution_percentage // 100
h = scene.render.resolution_y * scene.render.resolution_percentage // 100
result = {}
for item in scene.multiscale.cameras:
    cam = item.camera
    frame = [cam.matrix_world @ v for v in cam.data.view_frame(scene=scene)]
    # view_frame: top-right, bottom-right, bottom-left, top-left
    tr, br, bl, tl = frame
    eye = cam.matrix_world.translation
    axis = (cam.matrix_world.to_quaternion() @ Vector((0, 0, -1))).normalized()
    index = np.zeros((h, w), dtype=int)
    for y in range(h):
        fy = (y + 0.5) / h
        left, right = tl.lerp(bl, fy), tr.lerp(br, fy)
        for x in range(w):
            point = left.lerp(right, (x + 0.5) / w)
            d = (point - eye).normalized()
            origin = eye + d * (cam.data.clip_start / d.dot(axis))
            hit, _loc, _nor, _i, obj, _m = scene.ray_cast(depsgraph, origin, d)
            index[y, x] = obj.pass_index if hit else 0
    result[cam.name] = index.tolist()
json.dump(result, open(out, "w"))
"""


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.parametrize("method", ["SCALAR_FIELD", "IMAGE_BLEND"])
def test_indexob_matches_each_cameras_own_pinhole_ray(run_blender, tmp_path, method):
    run_blender(
        [
            "-b",
            "--factory-startup",
            "--python-exit-code",
            "1",
            "--python",
            "sample_blends/make_samples.py",
            "--",
            "--out",
            tmp_path,
            "--only",
            "two_camera",
        ]
    )
    blend = tmp_path / "two_camera.blend"
    exr = tmp_path / "render.exr"
    ref = tmp_path / "reference.json"
    register = REGISTER.format(repo=str(REPO))
    run_blender(
        ["-b", blend, "--python-exit-code", "1", "--python-expr", register + REFERENCE, "--", ref]
    )
    render = register + (
        "scene = bpy.context.scene; scene.render.engine = 'MULTISCALE'; "
        f"scene.multiscale.method = {method!r}; "
        "scene.render.image_settings.media_type = 'MULTI_LAYER_IMAGE'; "
        f"scene.render.filepath = {str(exr)!r}; bpy.ops.render.render(write_still=True)"
    )
    run_blender(["-b", blend, "--python-exit-code", "1", "--python-expr", render])
    index = read_passes(exr)["IndexOB"][..., 0]
    reference = json.loads(ref.read_text())
    masks = json.loads(
        run_blender(
            [
                "-b",
                blend,
                "--python-exit-code",
                "1",
                "--python-expr",
                register
                + (
                    "import json, numpy as np; "
                    "from multiscale_camera.adapters.masks import mask_from_image; "
                    "s = bpy.context.scene; w, h = s.render.resolution_x, s.render.resolution_y; "
                    "print('MASKS', json.dumps([mask_from_image(i.mask, w, h)[0].tolist() "
                    "for i in s.multiscale.cameras]))"
                ),
            ]
        )
        .stdout.split("MASKS ", 1)[1]
        .splitlines()[0]
    )
    for (name, ref_index), mask in zip(reference.items(), masks):
        kept = erode(np.array(mask, dtype=bool))
        assert kept.sum() >= 200, f"{name}: only {kept.sum()} pixels to compare"
        agree = (index[kept] == np.array(ref_index)[kept]).mean()
        print(f"{method} {name}: {agree:.4f} of {kept.sum()} pixels agree")
        assert agree >= 0.99, f"{name}: only {agree:.2%} of preserved pixels show the right object"
