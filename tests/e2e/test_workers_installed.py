"""The worker runtime from the installed extension: its workers load the package under
its real name (bl_ext.user_default.multiscale_camera), field workers without bpy,
render workers with it, and a render in workers equals one in Blender's process."""

import json

import numpy as np
import pytest

from tests.exr import read_passes

from .test_install_extension import SCENE

pytestmark = pytest.mark.e2e

WIDTH, HEIGHT = 64, 48

WORKERS = SCENE.replace(
    "bpy.ops.render.render(write_still=True)",
    """import json
from bl_ext.user_default.multiscale_camera.core.runtime import runtime
from bl_ext.user_default.multiscale_camera.core.runtime.worker import probe
from bl_ext.user_default.multiscale_camera.render import pipeline, processes, workers
field = runtime().map(probe, [0, 1], 2).results
render = runtime().map(probe, [0, 1], 2, launcher=processes.blender_launcher()).results
workers.MIN_RAYS = 0
pipeline.rows_per_tile = lambda width, rays=0, samples=1: 8
render_settings = scene.render
render_settings.threads_mode = "FIXED"
render_settings.threads = 1
render_settings.filepath = {exr!r}.replace(".exr", "-here.exr")
bpy.ops.render.render(write_still=True)
render_settings.threads = 2
render_settings.filepath = {exr!r}
with runtime().journal() as runs:
    bpy.ops.render.render(write_still=True)
print("WORKERS_JSON", json.dumps(dict(
    field=field, render=render,
    runs=[dict(kind=r.kind, where=r.where, given_up=len(r.given_up)) for r in runs])))
""",
)


def test_installed_workers_load_the_package_by_its_name(run_blender, linux_zip, tmp_path):
    exr = tmp_path / "workers.exr"
    code = WORKERS.format(zip=str(linux_zip), exr=str(exr), w=WIDTH, h=HEIGHT)
    proc = run_blender(
        ["-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", code],
        env={"BLENDER_USER_RESOURCES": str(tmp_path / "user")},
    )
    line = next(x for x in proc.stdout.splitlines() if x.startswith("WORKERS_JSON"))
    seen = json.loads(line.split(" ", 1)[1])
    name = "bl_ext.user_default.multiscale_camera"
    for _item, _pid, in_worker, loaded, bpy_there in seen["field"]:
        assert in_worker and not bpy_there
        assert f"{name}.core.runtime.worker" in loaded
        assert {m.split(".")[3] for m in loaded} == {"core"}
    assert all(in_worker and bpy_there for _i, _p, in_worker, _m, bpy_there in seen["render"])
    tiles = [r for r in seen["runs"] if r["kind"] == "blender"]
    assert tiles and all(min(r["where"]) > 0 and r["given_up"] == 0 for r in tiles)
    here = read_passes(tmp_path / "workers-here.exr")
    pooled = read_passes(exr)
    for name in ("Combined", "Depth", "IndexOB"):
        np.testing.assert_array_equal(pooled[name], here[name])
