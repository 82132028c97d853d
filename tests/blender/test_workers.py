"""Tiles in render worker processes give the same image as in-process, and Esc stops them."""

import os
import time
from functools import partial

import bpy
import numpy as np
import pytest

from fixtures.blender.scenes import two_camera_scene
from multiscale_camera.core.errors import Cancelled
from multiscale_camera.core.runtime import Launcher, cores, pool, runtime
from multiscale_camera.render import pipeline, processes, workers

from ..unit.runtime_tasks import InWorkers


def frame_of(scene):
    return pipeline.prepare_frame(bpy.context.evaluated_depsgraph_get())


def collect(frame, processes, should_stop=None):
    out = {}
    for rows, passes in workers.render_tiles(frame, pipeline.tiles(frame), processes, should_stop):
        out[rows] = passes
    return out


@pytest.mark.slow
def test_worker_processes_render_the_same_image(empty_scene, monkeypatch):
    two_camera_scene(empty_scene, 64, 48)
    empty_scene.multiscale.samples = 2
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 5)
    frame = frame_of(empty_scene)
    alone = collect(frame, 1)
    casts = frame.casts, frame.shadow_casts, frame.rays
    frame.casts = frame.shadow_casts = frame.rays = 0
    pooled = collect(frame, 2)
    assert list(pooled) == list(alone) and len(alone) == 10
    for rows in alone:
        for name in pipeline.PASSES:
            np.testing.assert_array_equal(pooled[rows][name[0]], alone[rows][name[0]])
    assert (frame.casts, frame.shadow_casts, frame.rays) == casts


def test_stop_request_ends_the_workers(empty_scene, monkeypatch):
    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 4)
    frame = frame_of(empty_scene)
    got = []

    def stop_after_two_tiles():
        return len(got) >= 2

    with pytest.raises(Cancelled):
        for rows, _passes in workers.render_tiles(
            frame, pipeline.tiles(frame), 2, stop_after_two_tiles
        ):
            got.append(rows)
    assert len(got) == 2
    # the workers stopped their tiles and stayed: the next render starts none
    with runtime().journal() as runs:
        assert len(collect(frame, 2)) == len(pipeline.tiles(frame))
    assert runs[0].started == 0 and runs[0].in_workers == len(pipeline.tiles(frame))


def test_stuck_workers_do_not_stop_esc(empty_scene, monkeypatch):
    """The tile loop used to wait on its workers without asking whether to stop: a
    worker stuck on a lock (a forked copy of a threaded host can be) froze the render,
    Esc or not. The loop now asks while it waits."""
    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 8)
    monkeypatch.setattr(workers, "_render_tile", _hang)
    frame = frame_of(empty_scene)
    start = time.perf_counter()
    with pytest.raises(Cancelled):
        collect(frame, 2, lambda: time.perf_counter() - start > 0.5)
    assert time.perf_counter() - start < 3.0


def test_without_worker_processes_tiles_render_in_process(empty_scene, monkeypatch):
    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 8)
    missing = Launcher("missing blender", ("/nonexistent/blender", "-b", "--python-expr"))
    monkeypatch.setattr(workers, "blender_launcher", lambda: missing)
    frame = frame_of(empty_scene)
    out = collect(frame, 4)
    assert sorted(out) == pipeline.tiles(frame)
    assert frame.rays == 64 * 48
    assert any(n.startswith(workers.WORKERS_UNUSED) for n in frame.notices)


def test_without_shared_memory_tiles_render_in_process(empty_scene, monkeypatch):
    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)

    def no_memory(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(workers, "shared_passes", no_memory)
    monkeypatch.setattr(pool, "Worker", lambda *a: pytest.fail("no worker without passes"))
    frame = frame_of(empty_scene)
    out = collect(frame, 2)
    assert sorted(out) == pipeline.tiles(frame)
    assert frame.rays == 64 * 48


def test_a_dead_worker_does_not_hang_the_render(empty_scene, monkeypatch):
    """A worker that dies (here: every one, at its first tile) used to leave the pool
    waiting forever; the tiles now finish in Blender's process, with a notice."""
    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 8)
    frame = frame_of(empty_scene)
    alone = collect(frame, 1)
    monkeypatch.setattr(workers, "_render_tile", _die)
    rescued = collect(frame, 2)
    assert list(rescued) == list(alone)
    for rows in alone:
        np.testing.assert_array_equal(rescued[rows]["Combined"], alone[rows]["Combined"])
    assert workers.WORKER_DIED in frame.notices


def test_tiles_take_one_worker_per_core_unless_the_threads_are_fixed():
    assert workers.worker_count(0) == cores() and workers.worker_count(3) == 3


def test_render_workers_have_mathutils_and_keep_the_frames_tree(empty_scene):
    """Render workers are background Blenders (here: Pythons that import bpy); a frame's
    tree, sent as its triangles, is built there once and kept for the next run."""
    from multiscale_camera.core.runtime.worker import probe

    launcher = processes.blender_launcher()
    probes = runtime().map(probe, [0, 1], 2, launcher=launcher).results
    assert all(bpy_there for *_rest, bpy_there in probes)
    two_camera_scene(empty_scene, 64, 48)
    frame = frame_of(empty_scene)
    task = partial(_tree_id, processes.portable(frame))
    first = runtime().map(task, range(4), 2, launcher=launcher).results
    again = runtime().map(task, range(4), 2, launcher=launcher).results
    assert all(pid != os.getpid() for pid, _tree in first)
    assert dict(first) == dict(again)  # the same tree objects, in the same workers


def _tree_id(frame, item, context):
    """(pid, id of the frame's tree) in the process that runs it."""
    return os.getpid(), id(processes.frame_here(frame, context).tree)


def _die(*args):
    """A worker's tile that kills its process (found by name, as tasks must be)."""
    import os

    os._exit(3)


def _hang(*args):
    """A worker's tile that does not end for half a minute, nor beats (ended by the
    runtime)."""
    time.sleep(30)


def test_ray_tables_marched_in_workers_are_the_same(empty_scene, monkeypatch):
    """The Cycles hand-off's tables, marched in render workers into shared memory, equal
    the tables marched in-process."""
    from multiscale_camera.render import tables

    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 5)
    frame = frame_of(empty_scene)
    frame.processes = 1
    with runtime().journal() as runs:
        alone = tables.ray_tables(frame)
    assert runs == []
    frame.processes = 2
    with runtime().journal() as runs:
        pooled = tables.ray_tables(frame)
    assert len(runs) == 1 and runs[0].in_workers == len(runs[0].where) == 10
    assert pooled.casts == alone.casts > 0
    for name in ("origin", "direction", "distance", "depth", "hit", "membership"):
        np.testing.assert_array_equal(getattr(pooled, name), getattr(alone, name))
    np.testing.assert_array_equal(pooled.object_index, alone.object_index)


def test_stalled_workers_give_way_to_the_render_in_process(empty_scene, monkeypatch):
    """Workers that do no tile for STALL_SECONDS (as forked copies of Blender's window
    did, spinning for good in its memory allocator) are ended and the tiles render in
    Blender's process, with a notice; the image is the one rendered in-process."""
    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 8)
    monkeypatch.setattr(pool, "STALL_SECONDS", 0.5)
    frame = frame_of(empty_scene)
    alone = collect(frame, 1)
    monkeypatch.setattr(workers, "_render_tile", _hang)
    start = time.perf_counter()
    rescued = collect(frame, 2)
    assert time.perf_counter() - start < 10.0
    assert list(rescued) == list(alone) and workers.WORKER_STALLED in frame.notices
    for rows in alone:
        np.testing.assert_array_equal(rescued[rows]["Combined"], alone[rows]["Combined"])


def test_render_workers_are_one_per_core_headless_and_with_a_window(empty_scene, monkeypatch):
    """Workers start as fresh processes, not forked copies of Blender: with its window
    open too, a render takes one per core unless Threads are Fixed."""
    from types import SimpleNamespace

    from multiscale_camera.adapters.scene import processes_of

    empty_scene.render.threads_mode = "AUTO"
    assert bpy.app.background and processes_of(empty_scene) == 0
    monkeypatch.setattr(bpy, "app", SimpleNamespace(background=False))
    assert processes_of(empty_scene) == 0
    empty_scene.render.threads_mode = "FIXED"
    empty_scene.render.threads = 3
    assert processes_of(empty_scene) == 3
    empty_scene.render.threads = 1
    assert processes_of(empty_scene) == 1


def test_render_says_when_its_workers_were_given_up(empty_scene, monkeypatch, tmp_path, capfd):
    """The engine reported its notices before the tile loop only, so a worker that died
    (or stalled) during it went unsaid; the warning now reaches the user."""
    two_camera_scene(empty_scene, 64, 48)
    monkeypatch.setattr(workers, "MIN_RAYS", 0)
    monkeypatch.setattr(pipeline, "rows_per_tile", lambda width, rays=0, samples=1: 8)
    monkeypatch.setattr(workers, "_render_tile", _die)
    empty_scene.render.threads_mode = "FIXED"
    empty_scene.render.threads = 2
    empty_scene.render.filepath = str(tmp_path / "out.png")
    bpy.ops.render.render(write_still=True)
    assert f"Multiscale: {workers.WORKER_DIED}" in capfd.readouterr().out
    assert (tmp_path / "out.png").exists()


def test_frame_says_when_the_simplification_workers_were_given_up(empty_scene, monkeypatch):
    """Workers of the ray simplification that stalled gave way to the parent without a
    word: the frame was only slower, and nobody said why. Now its notices say so; the
    simplified rays are those made in-process."""
    from multiscale_camera.core.sampling import simplification as sampling

    two_camera_scene(empty_scene, 64, 48)
    empty_scene.render.threads_mode = "FIXED"
    empty_scene.render.threads = 1
    alone = frame_of(empty_scene)
    assert pipeline.WORKERS_GIVEN_UP not in alone.notices
    alone.field.__dict__.pop("_samplers")
    empty_scene.render.threads = 2
    monkeypatch.setattr(sampling, "CHUNK", 64)
    monkeypatch.setattr(pool, "STALL_SECONDS", 0.5)
    # the measures hang in the workers, without a beat (in Blender's process they run)
    monkeypatch.setattr(sampling, "_measure", InWorkers(sampling._measure, "hang"))
    start = time.perf_counter()
    rescued = frame_of(empty_scene)
    assert time.perf_counter() - start < 20.0
    assert rescued.field is alone.field and pipeline.WORKERS_GIVEN_UP in rescued.notices
    iy, ix = (a.ravel() for a in np.mgrid[0:48, 0:64])
    a = alone.sampler.segments(ix + 0.5, iy + 0.5, ix, iy)
    b = rescued.sampler.segments(ix + 0.5, iy + 0.5, ix, iy)
    np.testing.assert_array_equal(a.offsets, b.offsets)
    np.testing.assert_array_equal(a.origin, b.origin)
