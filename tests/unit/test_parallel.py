"""The trace shared among forked worker processes: the same rays, stoppable, and done
in-process when a worker dies."""

import os
from dataclasses import replace

import numpy as np
import pytest

from fixtures.rigs import three_camera_rig
from multiscale_camera.core import parallel
from multiscale_camera.core.errors import Cancelled
from multiscale_camera.core.field import tracer as field_module
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import prepare, settings_for

needs_fork = pytest.mark.skipif(parallel.fork_context() is None, reason="no fork here")


@pytest.mark.slow
@needs_fork
def test_rays_traced_in_two_processes_equal_those_traced_in_one(monkeypatch):
    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    # shares smaller than the rounds: each worker traces several, as at 1920x1080
    monkeypatch.setattr(field_module, "MAX_RAYS_PER_SHARE", 40)
    monkeypatch.setattr(field_module, "BLOCK_VERTICES", 1000)
    calls, shares = [], []
    real = parallel.forked_map

    def counting(task, items, *args, **kwargs):
        out = real(task, items, *args, **kwargs)
        calls.append(out is not None)
        shares.append(len(items))
        return out

    monkeypatch.setattr(parallel, "forked_map", counting)
    cams, masks = three_camera_rig(96, 54)
    rig = Rig(cams, masks)
    base = settings_for("PREVIEW")
    one = prepare(rig, "SCALAR_FIELD", replace(base, processes=1))
    assert calls == []
    two = prepare(rig, "SCALAR_FIELD", replace(base, processes=2))
    assert calls and all(calls) and max(shares) > 2
    # numpy's vector loops may round the last bit of a float64 differently with the
    # length of the arrays a ray shares its steps with, and the trace carries that on:
    # equal to a millionth of the rig's size (14 units), a few float32 steps
    np.testing.assert_allclose(one.traced.vertices, two.traced.vertices, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(one.traced.counts, two.traced.counts)
    np.testing.assert_array_equal(one.index, two.index)
    assert one.stats["newton_lost"] == two.stats["newton_lost"]


def test_processes_are_not_part_of_the_fields_identity():
    from multiscale_camera.core.methods import field_key

    cams, masks = three_camera_rig(32, 18)
    rig = Rig(cams, masks)
    base = settings_for("STANDARD")
    assert field_key(rig, "SCALAR_FIELD", base) == field_key(
        rig, "SCALAR_FIELD", replace(base, processes=3)
    )


@needs_fork
def test_forked_map_keeps_the_order_of_its_items():
    assert parallel.forked_map(lambda x: x * x, list(range(7)), 3) == [x * x for x in range(7)]


@needs_fork
def test_a_worker_that_dies_leaves_the_work_to_the_caller():
    def die(x):
        os._exit(3)

    assert parallel.forked_map(die, [1, 2], 2) is None


@needs_fork
def test_a_stop_request_ends_the_workers():
    import time

    start = time.perf_counter()
    with pytest.raises(Cancelled):
        parallel.forked_map(lambda x: time.sleep(30), [1, 2], 2, should_stop=lambda: True)
    assert time.perf_counter() - start < 10


@needs_fork
def test_stalled_workers_leave_the_work_to_the_caller():
    """Workers that do nothing for stall_seconds (a forked copy of a threaded host
    spinning on a lock never ends nor dies) are ended; the caller does the work."""
    import time

    start = time.perf_counter()
    given_up = parallel.given_up()
    assert parallel.forked_map(lambda x: time.sleep(30), [1, 2], 2, stall_seconds=0.5) is None
    assert time.perf_counter() - start < 10
    # counted, so that the work's caller can say why it was slow
    assert parallel.given_up() == given_up + 1


@needs_fork
def test_workers_that_die_are_counted_as_given_up_and_done_work_is_not():
    import os

    given_up = parallel.given_up()
    assert parallel.forked_map(lambda x: x * 2, [1, 2], 2) == [2, 4]
    assert parallel.given_up() == given_up
    assert parallel.forked_map(lambda x: os._exit(3), [1, 2], 2) is None
    assert parallel.given_up() == given_up + 1


def test_without_fork_the_work_stays_in_process(monkeypatch):
    monkeypatch.setattr(parallel, "fork_context", lambda: None)
    assert parallel.forked_map(lambda x: x, [1, 2], 2) is None


@pytest.mark.slow
@needs_fork
def test_nested_levels_filled_and_rays_laid_out_in_workers_equal_those_done_in_process(
    monkeypatch,
):
    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    calls = []
    real = parallel.forked_map

    def counting(task, items, *args, **kwargs):
        out = real(task, items, *args, **kwargs)
        calls.append((len(items), out is not None))
        return out

    monkeypatch.setattr(parallel, "forked_map", counting)
    cams, masks = three_camera_rig(96, 54)
    rig = Rig(cams, masks)
    base = replace(settings_for("PREVIEW"), nested=True)
    one = prepare(rig, "SCALAR_FIELD", replace(base, processes=1))
    assert calls == []
    two = prepare(rig, "SCALAR_FIELD", replace(base, processes=2))
    levels = len(two.domain.grids)
    # the levels' fills went to the workers, and so did every lattice round's pixels
    assert levels >= 2 and calls[0] == (levels, True) and all(ok for _n, ok in calls)
    np.testing.assert_array_equal(one.domain.values, two.domain.values)
    assert one.stats["conflicts"] == two.stats["conflicts"]
    np.testing.assert_allclose(one.traced.vertices, two.traced.vertices, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(one.traced.counts, two.traced.counts)
    np.testing.assert_array_equal(one.index, two.index)


@needs_fork
def test_workers_that_beat_are_not_taken_for_stalled():
    """An item longer than stall_seconds is waited for while its worker beats."""
    import time

    def slow(x):
        for _ in range(20):
            time.sleep(0.1)
            parallel.beat()
        return x

    assert parallel.forked_map(slow, [1, 2], 2, stall_seconds=0.5) == [1, 2]
