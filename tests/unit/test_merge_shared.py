"""``merge`` lays a field's traced rays out in shared memory, taken as it is written, so
that the workers handed the field map its rays rather than a copy of them; where
/dev/shm cannot hold them, the rays stay in this process's memory, the same."""

import gc
import os

import numpy as np
import pytest

from multiscale_camera.core.field.trace import StopReason, Traced, merge
from multiscale_camera.core.runtime import runtime


def parts_and_order(sizes=((5, 6), (7, 9), (4, 3))):
    """Parts of n rays with k vertices for each (n, k) of ``sizes`` (the longest sets the
    result's; by default 5, 7 and 4 rays of 6, 9 and 3 vertices), placed at contiguous
    rows as the adaptive lattice places its rounds."""
    rng = np.random.default_rng(3)
    parts, order, start = [], [], 0
    for n, k in sizes:
        # rays along +z with a little sideways wander, one unit a step
        verts = np.cumsum(np.broadcast_to([0.0, 0.0, 1.0], (n, k, 3)), axis=1)
        verts = (verts + rng.normal(0, 0.01, (n, k, 3))).astype(np.float32)
        mem = rng.random((n, k), dtype=np.float32)
        counts = np.full(n, k, dtype=np.int32)
        reason = np.full(n, StopReason.LEFT_GRID, dtype=np.int8)
        parts.append(Traced(verts, mem, counts, reason, 1.0))
        order.append(np.arange(start, start + n))
        start += n
    return parts, order, start


def test_rays_merged_into_shared_memory_equal_those_merged_here():
    parts, order, total = parts_and_order()
    longest = parts[1].vertices.copy()
    here = merge(list(parts), order, total)
    shared = merge(list(parts), order, total, shared=True)
    assert runtime().shared.handle(here.vertices) is None
    assert runtime().shared.handle(shared.vertices) is not None
    assert runtime().shared.handle(shared.membership) is not None
    np.testing.assert_array_equal(shared.vertices, here.vertices)
    np.testing.assert_array_equal(shared.membership, here.membership)
    np.testing.assert_array_equal(shared.counts, here.counts)
    assert shared.vertices.shape == (16, 9, 3)
    # the part with the most vertices is laid out as it came
    np.testing.assert_array_equal(shared.vertices[5:12], longest)


def test_rays_stay_here_when_dev_shm_fills_during_the_merge(monkeypatch):
    parts, order, total = parts_and_order()
    here = merge(list(parts), order, total)
    pool = runtime()
    asked = []
    reserve = pool.shared.reserve

    def full_on_the_third(array):
        asked.append(array.shape)
        if len(asked) == 3:  # the second part's vertices
            raise OSError(28, "No space left on device")
        reserve(array)

    monkeypatch.setattr(pool.shared, "reserve", full_on_the_third)
    gc.collect()  # arrays of earlier tests
    before = set(pool.shared.names())
    moved = merge(list(parts), order, total, shared=True)
    assert len(asked) == 3  # no more asked once the rays moved here
    assert pool.shared.handle(moved.vertices) is None
    np.testing.assert_array_equal(moved.vertices, here.vertices)
    np.testing.assert_array_equal(moved.membership, here.membership)
    gc.collect()
    assert not set(pool.shared.names()) - before  # the segments went with their arrays


def test_rays_stay_here_when_no_shared_memory_can_be_had(monkeypatch):
    parts, order, total = parts_and_order()
    here = merge(list(parts), order, total)

    def none(*args, **kwargs):
        raise OSError(24, "Too many open files")

    monkeypatch.setattr(runtime(), "shared_array", none)
    moved = merge(list(parts), order, total, shared=True)
    assert runtime().shared.handle(moved.vertices) is None
    np.testing.assert_array_equal(moved.vertices, here.vertices)


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="Linux's /dev/shm shows the pages")
def test_a_merge_takes_shared_pages_only_for_the_rows_it_has_written(monkeypatch):
    """The merge's peak is its result and the part being copied, as in this process's
    memory, not the whole result on top of every part from the start."""
    parts, order, total = parts_and_order(((4000, 9),) * 4)  # 432 kB of vertices each
    pool = runtime()
    taken = []
    reserve = pool.shared.reserve

    def measured(array):
        reserve(array)
        name = pool.shared.handle(array).segment
        taken.append(os.stat(f"/dev/shm/{name}").st_blocks * 512)

    monkeypatch.setattr(pool.shared, "reserve", measured)
    out = merge(list(parts), order, total, shared=True)
    verts_taken = np.array(taken[0::2])  # vertices, memberships in turn
    whole = out.vertices.nbytes
    # a quarter more with each part (to a page)
    np.testing.assert_allclose(verts_taken / whole, [0.25, 0.5, 0.75, 1.0], atol=0.01)
