"""Render farms: a scene's cache folder beside its .blend, and several `blender -b -a`
processes sharing it with Blender's placeholders and no-overwrite, as Flamenco's and
Blender's own farm set-ups run them."""

import json
import os
import subprocess
import time

import bpy
import numpy as np
import pytest
from mathutils import Vector

from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.adapters.scene import UNSAVED_CACHE
from multiscale_camera.io import cache
from multiscale_camera.render import fields, pipeline
from tests.conftest import REPO, blender_command
from tests.exr import read_passes

WIDTH, HEIGHT = 40, 30
FRAMES = (1, 2, 3, 4)
REGISTER = (
    f"import sys; sys.path.insert(0, {str(REPO)!r}); import multiscale_camera; "
    "multiscale_camera.register()"
)


@pytest.fixture()
def fresh_service(monkeypatch):
    """A field service with nothing in memory and the default folder unused."""
    service = fields.FieldService(cache.FieldCache(lazy_folder=True))
    monkeypatch.setattr(fields, "SERVICE", service)
    monkeypatch.setattr(pipeline, "SERVICE", service)
    return service


def held_rig(scene):
    """The two-camera scene, camera 2 still over frames 1-2 and moved over frames 3-4
    (a key on each frame): two rigs, two fields, each needed by two frames."""
    _c1, c2 = two_camera_scene(scene, WIDTH, HEIGHT)
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    for frame in FRAMES:
        if frame == 3:
            c2.location += Vector((0.5, 0.3, -0.2))
        c2.keyframe_insert("location", frame=frame)
    scene.render.threads_mode, scene.render.threads = "FIXED", 1  # three at once: 2 cores
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.frame_set(1)


def test_scene_cache_folder_beside_the_blend(empty_scene, tmp_path, fresh_service):
    scene = empty_scene
    two_camera_scene(scene, 24, 18)
    scene.multiscale.cache_folder = "//field cache"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend"))
    frame = pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())
    folder = tmp_path / "field cache"
    # a set: the entry's name is a digest, which sorts before or after the log's
    stored = {p.name for p in folder.iterdir()}
    entry = f"{fresh_service.request(scene).key}.npz"
    assert stored == {entry, cache.BUILDS_LOG}, stored
    (built,) = fresh_service.cache.builds()
    assert built["pid"] == os.getpid() and built["key"] in entry
    assert frame.field is not None


def test_relative_cache_folder_of_an_unsaved_file_says_so(empty_scene, fresh_service):
    scene = empty_scene
    two_camera_scene(scene, 24, 18)
    scene.multiscale.cache_folder = "//cache"
    request = fresh_service.request(scene)
    assert request.folder is None
    assert UNSAVED_CACHE.format(folder="//cache") in request.notices


def render_range(blend, first, last):
    """A `blender -b blend -s first -e last -a` process, started (not waited for)."""
    cmd = [blender_command(), "-b", str(blend), "--python-exit-code", "1"]
    cmd += ["--python-expr", REGISTER, "-s", str(first), "-e", str(last), "-a"]
    return subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.parametrize("method", ["SCALAR_FIELD", "AUTO"])
def test_three_farm_workers_share_frames_and_fields(empty_scene, tmp_path, fresh_service, method):
    """Three processes render overlapping ranges of one .blend with placeholders and
    no overwrite, and one cache folder beside the file: every frame is written once,
    each of the two fields is built once (builds.jsonl says by whom), and every frame
    equals the same frame rendered cold in one process. With AUTO each worker chooses
    the shot's method on its own: they agree, or the fields' keys would differ."""
    scene = empty_scene
    held_rig(scene)
    scene.multiscale.method = method
    scene.multiscale.cache_folder = "//cache"
    scene.render.use_placeholder, scene.render.use_overwrite = True, False
    scene.render.filepath = "//frames/f_####"
    blend = tmp_path / "farm.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    start = time.perf_counter()
    workers = [render_range(blend, a, b) for a, b in ((1, 3), (2, 4), (1, 4))]
    logs = [w.communicate(timeout=600)[0].decode() for w in workers]
    print(f"three workers: {time.perf_counter() - start:.1f} s")
    for worker, log in zip(workers, logs, strict=True):
        assert worker.returncode == 0, log

    names = sorted(os.listdir(tmp_path / "frames"))
    assert names == [f"f_{f:04d}.exr" for f in FRAMES]
    builds = cache.FieldCache(str(tmp_path / "cache")).builds()
    keys = [b["key"] for b in builds]
    print("builds:", [(b["key"][:8], b["pid"], b["seconds"]) for b in builds])
    assert len(keys) == 2 and len(set(keys)) == 2, builds

    # the cold reference: the same frames, one process, its own empty cache folder
    scene.multiscale.cache_folder = "//cold"
    scene.render.use_placeholder, scene.render.use_overwrite = False, True
    scene.render.filepath = str(tmp_path / "cold" / "f_####")
    bpy.ops.render.render(animation=True)
    assert len(fresh_service.cache.builds()) == 2
    for f in FRAMES:
        farm = read_passes(tmp_path / "frames" / f"f_{f:04d}.exr")
        cold = read_passes(tmp_path / "cold" / f"f_{f:04d}.exr")
        np.testing.assert_array_equal(farm["IndexOB"], cold["IndexOB"])
        np.testing.assert_allclose(farm["Combined"], cold["Combined"], atol=1e-3)
    one, three = (read_passes(tmp_path / "cold" / f"f_{f:04d}.exr") for f in (1, 3))
    assert not np.array_equal(one["Combined"], three["Combined"])  # two rigs indeed
    print(json.dumps(builds))
    if method == "AUTO":
        report = json.loads(scene.multiscale.report)
        print(report["auto"])
        assert report["method"] == "IMAGE_BLEND"
        assert report["auto"].endswith("at frames 1, 2, 4 of the shot"), report["auto"]


@pytest.mark.slow
@pytest.mark.e2e
def test_a_worker_killed_mid_build_does_not_block_the_next(empty_scene, tmp_path):
    """A worker killed (SIGKILL) while it builds a field leaves its lock file behind; the
    next worker that needs the field breaks it at once (its holder's process is gone:
    same host) and builds, so its time beyond the build is Blender's start-up, well
    under 10 s (a lock judged by its heartbeat alone would hold it 20 s; from another
    host that is the most, see tests/unit/test_build_lock.py), and the field is built
    once."""
    scene = empty_scene
    held_rig(scene)
    scene.multiscale.cache_folder = "//cache"
    scene.render.filepath = "//frames/f_####"
    blend = tmp_path / "farm.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    folder = tmp_path / "cache"

    killed = subprocess.Popen(
        [blender_command(), "-b", str(blend), "--python-expr", REGISTER, "-f", "1"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + 120
    while not (folder.is_dir() and any(p.suffix == ".lock" for p in folder.iterdir())):
        assert killed.poll() is None and time.monotonic() < deadline, "no build started"
        time.sleep(0.05)
    os.killpg(killed.pid, 9)
    killed.wait()
    assert [p.suffix for p in folder.iterdir()] == [".lock"]  # left behind, no field

    start = time.perf_counter()
    worker = render_range(blend, 2, 2)
    log = worker.communicate(timeout=600)[0].decode()
    seconds = time.perf_counter() - start
    assert worker.returncode == 0, log
    (built,) = cache.FieldCache(str(folder)).builds()
    print(f"next worker: {seconds:.1f} s in all, its build {built['seconds']:.1f} s")
    assert built["pid"] != killed.pid
    assert seconds - built["seconds"] < 10.0
    assert sorted(p.suffix for p in folder.iterdir()) == [".jsonl", ".npz"]
    assert os.path.getsize(tmp_path / "frames" / "f_0002.exr") > 0
