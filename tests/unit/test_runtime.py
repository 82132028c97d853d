"""The worker runtime: spawned workers that stay, stream results, write into shared
memory, and give way to this process (saying so) when they die, stall or fail."""

import gc
import os
import sys
import threading
import time
from functools import partial

import numpy as np
import pytest

from multiscale_camera.core.errors import Cancelled
from multiscale_camera.core.runtime import Launcher, Reason, Runtime, pool, python_launcher
from multiscale_camera.core.runtime.shared import PREFIX
from multiscale_camera.core.runtime.worker import probe

from . import runtime_tasks as tasks


def segments():
    """Names of this process's shared-memory segments (Linux: /dev/shm)."""
    if not os.path.isdir("/dev/shm"):
        return set()
    mine = f"{PREFIX}{os.getpid()}_"
    return {name for name in os.listdir("/dev/shm") if name.startswith(mine)}


@pytest.fixture(scope="module")
def rt():
    """A runtime of the module's own: its workers stay across the tests."""
    runtime = Runtime()
    yield runtime
    runtime.shutdown()


def test_results_equal_in_process_results_in_the_items_order(rt):
    items = list(range(11))
    pooled = rt.map(tasks.square, items, 3)
    alone = rt.map(tasks.square, items, 1)
    assert pooled.results == alone.results == [x * x for x in items]
    assert pooled.outcome.in_workers == len(items) and not pooled.outcome.given_up
    assert alone.outcome.where == (0,) * len(items) and alone.outcome.started == 0


def test_results_stream_as_each_item_finishes(rt):
    rt.map(tasks.square, [1, 2], 2)  # started
    # item 0 takes longer than items 1 and 2, given out after it to the other worker
    run = rt.run(tasks.nap, [(0, 0.8), (1, 0.05), (2, 0.05)], 2)
    order = [index for index, _result in run]
    assert order == [1, 2, 0] and run.outcome.in_workers == 3


def test_workers_stay_for_the_next_run(rt):
    first = rt.map(tasks.where, range(4), 2)
    second = rt.map(tasks.where, range(4), 2)
    assert second.outcome.started == 0
    assert set(second.outcome.workers) <= set(rt.pids())
    assert all(in_worker for _i, _pid, in_worker in second.results)
    assert {pid for _i, pid, _w in first.results} | {pid for _i, pid, _w in second.results} <= set(
        rt.pids()
    )


def test_a_worker_that_dies_is_given_up_and_its_work_done_here(rt):
    mapped = rt.map(tasks.die_in_workers, [1, 2, 3], 2)
    assert mapped.results == [1, 4, 9]
    outcome = mapped.outcome
    assert outcome.in_process == 3 and outcome.given_up
    assert {g.reason for g in outcome.given_up} == {Reason.DIED}
    assert all("exit status 3" in g.detail for g in outcome.given_up)
    # the pool starts others for the next run
    assert rt.map(tasks.square, [1, 2], 2).outcome.in_workers == 2


def test_a_worker_that_stalls_is_ended_and_its_work_done_here(rt):
    start = time.perf_counter()
    mapped = rt.map(tasks.hang_in_workers, [1, 2, 3], 2, stall_seconds=0.5)
    assert time.perf_counter() - start < 5
    assert mapped.results == [1, 4, 9]
    stalled = [g for g in mapped.outcome.given_up if g.reason is Reason.STALLED]
    assert len(stalled) == 2 and all("0.5 s" in g.detail for g in stalled)
    for g in stalled:  # ended, not left hanging
        with pytest.raises(ProcessLookupError):
            os.kill(g.pid, 0)


def test_workers_that_beat_are_not_taken_for_stalled(rt):
    mapped = rt.map(partial(tasks.beating, 1.5), [1, 2], 2, stall_seconds=0.5)
    assert mapped.results == [1, 2] and mapped.outcome.in_workers == 2
    assert not mapped.outcome.given_up


def test_a_task_that_fails_in_a_worker_runs_here(rt):
    mapped = rt.map(tasks.fail_in_workers, [1, 2, 3], 2)
    assert mapped.results == [1, 4, 9] and mapped.outcome.in_process == 3
    assert all(g.reason is Reason.FAILED for g in mapped.outcome.given_up)
    assert "MemoryError: no room in the worker" in mapped.outcome.given_up[0].detail
    # the worker itself is fine and stays
    assert {g.pid for g in mapped.outcome.given_up} <= set(rt.pids())


def test_an_error_here_is_raised(rt):
    with pytest.raises(ZeroDivisionError):
        rt.map(partial(tasks.sleep, 0.0), [1], 1, local=lambda item, context: 1 / 0)


def test_cancel_stops_within_a_second_and_the_pool_survives(rt):
    rt.map(tasks.square, [1, 2], 2)
    before = set(rt.pids())
    start = time.perf_counter()
    with pytest.raises(Cancelled):
        rt.map(
            tasks.until_stopped, [1, 2], 2, should_stop=lambda: time.perf_counter() - start > 0.3
        )
    assert time.perf_counter() - start < 1.3
    after = rt.map(tasks.where, [1, 2], 2)
    assert after.outcome.started == 0 and set(rt.pids()) == before
    assert set(after.outcome.workers) <= before


def test_cancel_ends_workers_that_do_not_stop(rt):
    start = time.perf_counter()
    run = rt.run(partial(tasks.sleep, 60), [1, 2], 2, should_stop=lambda: True)
    with pytest.raises(Cancelled):
        list(run)
    assert time.perf_counter() - start < 1.5 and run.outcome.cancelled
    assert rt.map(tasks.square, [3, 4], 2).results == [9, 16]


def test_closing_a_run_stops_its_workers(rt):
    rt.map(tasks.square, [1, 2], 2)
    before = set(rt.pids())
    run = rt.run(tasks.until_stopped, [0, 1, 2], 2)
    assert next(run) == (0, 0)
    start = time.perf_counter()
    run.close()
    assert time.perf_counter() - start < 1.0 and run.outcome.cancelled
    assert run.outcome.where[1:] == (-1, -1) and set(rt.pids()) == before
    never = rt.run(tasks.square, [1], 2)
    never.close()
    assert never.outcome.cancelled and never.outcome.where == (-1,)


def test_workers_write_into_shared_arrays(rt):
    out = rt.shared_array((12, 3), np.int64)
    mapped = rt.map(partial(tasks.fill, out), [(0, 4), (4, 8), (8, 12)], 2)
    assert mapped.outcome.in_workers == 3
    np.testing.assert_array_equal(out, np.arange(12)[:, None] * 10 + np.arange(3))
    # a view travels as a view of the same memory
    view = out[2:10:2, 1:]
    seen = rt.map(partial(tasks.total, view), [0, 1], 2).results
    assert seen == [(float(view.sum()), "mmap")] * 2


def test_large_arrays_travel_through_shared_memory_small_ones_in_the_message(rt):
    grid = np.random.default_rng(0).random((64, 64, 64), dtype=np.float32)
    small = np.arange(10.0)
    assert (
        rt.map(partial(tasks.total, grid), [0, 1], 2).results
        == [(float(grid.sum(dtype=np.float64)), "mmap")] * 2
    )
    assert rt.map(partial(tasks.total, small), [0, 1], 2).results[0][1] != "mmap"
    # a strided view travels as its elements, in C order
    view = grid[:, ::2].T
    sent = rt.map(partial(tasks.total, view), [0, 1], 2).results
    assert sent == [(float(view.sum(dtype=np.float64)), "mmap")] * 2


def test_no_segments_are_left_behind(rt):
    gc.collect()  # arrays of earlier tests
    rt.warm(len(rt.pids()))  # a worker's control segment is named until it is ready
    before = segments()
    runtime = Runtime()
    out = runtime.shared_array((100, 100), np.float32)
    big = np.ones((256, 256), np.float64)
    runtime.map(partial(tasks.total, big), [0, 1], 2)
    runtime.map(partial(tasks.fill, out), [(0, 50), (50, 100)], 2)
    runtime.map(tasks.die_in_workers, [1, 2], 2)
    assert segments() - before == set(runtime.shared.names())  # `out` only
    del out
    assert segments() == before
    runtime.map(tasks.square, [1, 2], 2)
    runtime.shutdown()
    assert segments() == before


def _taken_bytes(array, rt):
    """Bytes of /dev/shm the segment under ``array`` holds (Linux)."""
    name = rt.shared.handle(array).segment
    return os.stat(f"/dev/shm/{name}").st_blocks * 512


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="Linux's /dev/shm shows the pages")
def test_a_shared_array_made_without_reserving_takes_its_pages_as_asked(rt):
    out = rt.shared_array((64, 1024), np.float32, reserve=False)  # 256 kB
    assert _taken_bytes(out, rt) == 0
    rt.shared.reserve(out[16:32])  # 64 kB
    assert 64 * 1024 <= _taken_bytes(out, rt) < 128 * 1024
    out[16:32] = 1.0
    assert float(out.sum()) == 16 * 1024
    # workers see what was written, and what was not reads as zeros
    assert rt.map(partial(tasks.total, out), [0, 1], 2).results == [(16384.0, "mmap")] * 2
    whole = rt.shared_array((64, 1024), np.float32)
    assert _taken_bytes(whole, rt) >= 256 * 1024


def test_only_a_contiguous_piece_of_a_shared_array_can_be_reserved(rt):
    out = rt.shared_array((8, 8), np.float32, reserve=False)
    with pytest.raises(ValueError, match="not a contiguous piece of a shared array"):
        rt.shared.reserve(out[:, :4])
    with pytest.raises(ValueError, match="not a contiguous piece of a shared array"):
        rt.shared.reserve(np.zeros((8, 8), np.float32))


def test_too_few_processes_run_here_without_workers():
    runtime = Runtime()
    mapped = runtime.map(tasks.where, [1, 2, 3], 1)
    assert mapped.outcome.started == 0 and runtime.pids() == []
    assert all(not in_worker and pid == os.getpid() for _i, pid, in_worker in mapped.results)


def test_workers_that_cannot_start_leave_the_work_here():
    runtime = Runtime()
    missing = Launcher("missing", ("/nonexistent/python", "-c"))
    mapped = runtime.map(tasks.square, [1, 2], 2, launcher=missing)
    assert mapped.results == [1, 4] and mapped.outcome.in_process == 2
    assert mapped.outcome.given_up[0].reason is Reason.NO_START
    # a worker that exits before it is ready: no more are started for that kind
    broken = Launcher("broken", (sys.executable, "-c"), preamble="raise SystemExit(7)")
    mapped = runtime.map(tasks.square, [1, 2], 2, launcher=broken)
    assert mapped.results == [1, 4]
    assert {g.reason for g in mapped.outcome.given_up} == {Reason.NO_START}
    again = runtime.map(tasks.square, [1, 2], 2, launcher=broken)
    assert again.outcome.started == 0 and again.outcome.given_up[0].reason is Reason.NO_START
    runtime.shutdown()


def test_a_task_that_cannot_travel_runs_here(rt):
    mapped = rt.map(lambda item, context: item + 1, [1, 2], 2)
    assert mapped.results == [2, 3] and mapped.outcome.in_process == 2
    assert "cannot travel" in mapped.outcome.given_up[0].detail


def test_a_journal_collects_the_outcomes_of_its_block(rt):
    with rt.journal() as runs:
        rt.map(tasks.square, [1, 2], 2)
        with rt.journal() as inner:
            rt.map(tasks.die_in_workers, [1, 2], 2)
    rt.map(tasks.square, [1, 2], 2)
    assert len(runs) == 2 and len(inner) == 1 and inner[0] is runs[1]
    assert not runs[0].given_up and runs[1].given_up


def test_the_default_stall_limit_is_read_when_a_run_starts(rt, monkeypatch):
    monkeypatch.setattr(pool, "STALL_SECONDS", 0.5)
    start = time.perf_counter()
    assert rt.map(tasks.hang_in_workers, [2], 2).results == [4]
    assert time.perf_counter() - start < 5


def test_workers_import_the_package_under_its_own_name_and_no_bpy(rt):
    names = rt.map(tasks.modules, [0, 1], 2).results
    for loaded in names:
        assert "multiscale_camera" in loaded and "numpy" in loaded
        assert not {"bpy", "mathutils", "bmesh", "gpu"} & set(loaded)


def test_warm_starts_the_workers_a_run_will_find(rt):
    pids = rt.warm(3)
    assert len(set(pids)) == 3 and set(pids) <= set(rt.pids())
    mapped = rt.map(probe, range(3), 3)
    assert mapped.outcome.started == 0
    for _i, pid, in_worker, loaded, bpy in mapped.results:
        assert pid in pids and in_worker and not bpy
        assert "multiscale_camera.core.runtime.worker" in loaded


def test_warm_without_waiting_starts_workers_the_next_run_takes_as_they_come_ready():
    """IMAGE_BLEND starts the fold count's workers as its solve starts and does not wait
    for them (``warm(wait=False)``): the run that follows takes those workers, starting
    none of its own, and hands them its items once they are ready."""
    fresh = Runtime()
    try:
        pids = fresh.warm(2, wait=False)
        assert len(set(pids)) == 2 and set(pids) == set(fresh.pids())
        mapped = fresh.map(probe, range(4), 2)
        assert mapped.outcome.started == 0 and mapped.outcome.in_workers == 4
        assert {r[1] for r in mapped.results} <= set(pids)
    finally:
        fresh.shutdown()


def test_the_python_launcher_starts_this_interpreter_isolated():
    launcher = python_launcher()
    command = launcher.command("control")
    assert command[:3] == [sys.executable, "-I", "-c"]
    assert "multiscale_camera" in command[3] and "'control'" in command[3]
    assert launcher.environment()["OPENBLAS_NUM_THREADS"] == "1"


def test_a_short_stall_limit_does_not_cut_a_slow_start_short():
    """A run's stall limit is for items that stop beating, not for starting: a worker
    that takes longer than it to start (a busy machine) is waited for, not given up
    (which would leave the whole kind unused for later runs)."""
    runtime = Runtime()
    slow = Launcher("slow start", (sys.executable, "-c"), preamble="import time; time.sleep(1.5)")
    try:
        mapped = runtime.map(tasks.where, [1, 2], 2, launcher=slow, stall_seconds=0.3)
        assert mapped.outcome.given_up == ()
        assert any(in_worker for _i, _pid, in_worker in mapped.results)
    finally:
        runtime.shutdown()


def _iterate_in_a_thread(run):
    """Iterate ``run`` in a thread, as ``quality.FoldCount`` does: (thread, results, errors)."""
    results, errors = {}, []

    def iterate():
        try:
            for index, result in run:
                results[index] = result
        except BaseException as err:
            errors.append(err)

    thread = threading.Thread(target=iterate)
    thread.start()
    return thread, results, errors


def test_a_helped_run_shares_its_items_between_one_worker_and_the_caller(rt):
    """A run the caller helps (``Run.help``) starts one worker for ``processes`` 1 and
    hands the caller the items no worker has taken: each item runs once, here or there."""
    rt.warm(1)
    items = [(i, 0.15) for i in range(8)]
    run = rt.run(tasks.nap, items, 1, helped=True)
    thread, results, errors = _iterate_in_a_thread(run)
    run.help()
    thread.join()
    assert not errors and results == {i: i for i in range(8)}
    where = run.outcome.where
    assert run.outcome.in_process >= 1 and run.outcome.in_workers >= 1
    assert run.outcome.in_process + run.outcome.in_workers == 8 and len(run.outcome.workers) == 1
    assert 0 in where and -1 not in where


def test_an_error_in_the_helping_caller_ends_the_run_with_it(rt):
    rt.warm(1)
    run = rt.run(
        partial(tasks.sleep, 0.2), [1, 2, 3, 4], 1, helped=True, local=lambda item, c: 1 / 0
    )
    thread, _results, errors = _iterate_in_a_thread(run)
    run.help()
    thread.join()
    assert len(errors) == 1 and isinstance(errors[0], ZeroDivisionError)
    assert run.outcome.cancelled
    assert rt.map(tasks.square, [3, 4], 2).results == [9, 16]


def test_help_returns_at_once_from_a_run_that_has_ended(rt):
    run = rt.run(tasks.square, [1, 2], 1, helped=True)
    assert dict(run) == {0: 1, 1: 4}
    start = time.perf_counter()
    run.help()
    closed = rt.run(tasks.square, [1], 1, helped=True)
    closed.close()
    closed.help()
    assert time.perf_counter() - start < 0.5
