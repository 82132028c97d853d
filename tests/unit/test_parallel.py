"""The trace shared among worker processes: the same rays as traced in one, and worker
processes that import the core alone."""

import threading
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from fixtures.rigs import three_camera_rig, turned_rig
from multiscale_camera.core.errors import Cancelled
from multiscale_camera.core.field import tracer as field_module
from multiscale_camera.core.field.plane_step import schedule_of
from multiscale_camera.core.geometry import Rig
from multiscale_camera.core.methods import prepare, settings_for
from multiscale_camera.core.quality import bending_active, build_report, fold_map
from multiscale_camera.core.quality import report as report_module
from multiscale_camera.core.runtime import runtime
from multiscale_camera.core.runtime.wire import dump_payload
from multiscale_camera.core.runtime.worker import probe

from .fold_reference import reference_quad_folds


def assert_same_rays(one, two):
    """Two traced fields traced the same pixels with the same rays, to float32 steps (a
    millionth of the rig's size): pixel by pixel, their rays numbered as the workers'
    shares came back."""
    np.testing.assert_array_equal(one.index >= 0, two.index >= 0)
    a, b = one.index[one.index >= 0], two.index[two.index >= 0]
    np.testing.assert_allclose(one.traced.vertices[a], two.traced.vertices[b], rtol=0, atol=1e-5)
    np.testing.assert_array_equal(one.traced.counts[a], two.traced.counts[b])


@pytest.mark.slow
def test_rays_traced_in_two_processes_equal_those_traced_in_one(monkeypatch):
    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    # shares smaller than the rounds: each worker traces several, as at 1920x1080
    monkeypatch.setattr(field_module, "MAX_RAYS_PER_SHARE", 40)
    monkeypatch.setattr(field_module, "BLOCK_VERTICES", 1000)
    cams, masks = three_camera_rig(96, 54)
    rig = Rig(cams, masks)
    base = settings_for("PREVIEW")
    with runtime().journal() as alone_runs:
        one = prepare(rig, "SCALAR_FIELD", replace(base, processes=1))
    assert alone_runs == []
    with runtime().journal() as runs:
        two = prepare(rig, "SCALAR_FIELD", replace(base, processes=2))
    # every share of every round ran in a worker
    assert runs and all(r.in_workers == len(r.where) for r in runs)
    assert max(len(r.where) for r in runs) > 2
    # numpy's vector loops may round the last bit of a float64 differently with the
    # length of the arrays a ray shares its steps with, and the trace carries that on:
    # equal to a millionth of the rig's size (14 units), a few float32 steps
    assert_same_rays(one, two)
    assert one.stats["newton_lost"] == two.stats["newton_lost"]
    # the rays of the field built for workers lie in shared memory: the fold count and
    # the render's tables map them rather than a copy
    assert runtime().shared.handle(two.traced.vertices) is not None
    assert runtime().shared.handle(two.traced.membership) is not None
    assert runtime().shared.handle(one.traced.vertices) is None
    copies = []
    dump_payload(two, runtime().shared, copies)
    try:
        copied = {seg.size for seg in copies}
        assert two.traced.vertices.nbytes not in copied
        assert two.traced.membership.nbytes not in copied
    finally:
        for seg in copies:
            seg.unlink()


@pytest.mark.slow
def test_the_workers_shares_come_back_apart_when_asked_and_merge_to_the_same_rays(monkeypatch):
    """The lattice takes a round's shares apart (``parts=True``): merging them there
    held the round twice, and the build's last merge held that copy beside the
    result."""
    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    monkeypatch.setattr(field_module, "MAX_RAYS_PER_SHARE", 40)
    cams, masks = three_camera_rig(96, 54)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", replace(settings_for("PREVIEW"), processes=1))
    tracer = fld.tracer()
    tracer.processes = 2
    iy, ix = np.nonzero(np.ones((54, 96), dtype=bool))
    ix, iy = ix[::37], iy[::37]  # 141 pixels: 4 shares
    merged = tracer.trace_pixels(ix, iy, fld.step, 4000)
    shares = tracer.trace_pixels(ix, iy, fld.step, 4000, parts=True)
    assert len(shares) == 4
    rows = np.concatenate([r for _t, r in shares])
    np.testing.assert_array_equal(np.sort(rows), np.arange(len(ix)))
    again = field_module.merge(
        [t for t, _r in shares], [r for _t, r in shares], len(ix), schedule_of(fld.step)
    )
    np.testing.assert_array_equal(again.vertices, merged.vertices)
    np.testing.assert_array_equal(again.membership, merged.membership)
    np.testing.assert_array_equal(again.counts, merged.counts)
    np.testing.assert_array_equal(again.bands, merged.bands)
    # in one process, one part of every ray
    tracer.processes = 1
    ((alone, rows),) = tracer.trace_pixels(ix, iy, fld.step, 4000, parts=True)
    np.testing.assert_array_equal(rows, np.arange(len(ix)))
    assert alone.vertices.shape[0] == len(ix)


def test_tangent_seconds_of_a_shared_trace_count_every_share(monkeypatch):
    """A round of n shares over w workers took about n / w shares' time, and their
    tangent seconds were counted as the mean of one share's: on the 1000x rig at
    1920x1080 the build said 61.5 s of tangents in a 357 s build whose tangents, traced
    in one process at 320x180, take 31.8 of the trace's 46 CPU s. Shares here report
    known seconds; the tracer adds their sum over the workers."""

    class FakeRuntime:
        def map(self, task, items, workers, should_stop):
            return SimpleNamespace(results=[(None, 0, 1.5 + k, []) for k, _n in items])

    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    monkeypatch.setattr(field_module, "MAX_RAYS_PER_SHARE", 40)
    monkeypatch.setattr(field_module, "worker_count", lambda processes: 2)
    monkeypatch.setattr(field_module, "runtime", FakeRuntime)
    cams, masks = three_camera_rig(32, 18)
    no_grid = SimpleNamespace(sample=None, contains=None)  # the shares never read it
    tracer = field_module.FieldTracer(Rig(cams, masks), None, None, domain=no_grid, processes=2)
    ix = np.arange(200)  # 5 shares of 40 rays over 2 workers
    parts = tracer._shared("pixels", ix, ix, 1.0, 10, None, parts=True)
    assert len(parts) == 5
    assert tracer.tangent_seconds == pytest.approx((1.5 + 2.5 + 3.5 + 4.5 + 5.5) / 2)


def test_processes_are_not_part_of_the_fields_identity():
    from multiscale_camera.core.methods import field_key

    cams, masks = three_camera_rig(32, 18)
    rig = Rig(cams, masks)
    base = settings_for("STANDARD")
    assert field_key(rig, "SCALAR_FIELD", base) == field_key(
        rig, "SCALAR_FIELD", replace(base, processes=3)
    )


@pytest.mark.slow
def test_nested_levels_filled_and_rays_laid_out_in_workers_equal_those_done_in_process(
    monkeypatch,
):
    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    cams, masks = three_camera_rig(96, 54)
    rig = Rig(cams, masks)
    base = replace(settings_for("PREVIEW"), nested=True)
    with runtime().journal() as alone_runs:
        one = prepare(rig, "SCALAR_FIELD", replace(base, processes=1))
    assert alone_runs == []
    with runtime().journal() as runs:
        two = prepare(rig, "SCALAR_FIELD", replace(base, processes=2))
    levels = len(two.domain.grids)
    # the levels' fills went to the workers, and so did every lattice round's pixels
    assert levels >= 2 and len(runs[0].where) == levels
    assert all(r.in_workers == len(r.where) for r in runs)
    np.testing.assert_array_equal(one.domain.values, two.domain.values)
    assert one.stats["conflicts"] == two.stats["conflicts"]
    assert_same_rays(one, two)


def test_field_workers_import_the_core_and_no_bpy(monkeypatch):
    """The trace's workers are fresh Pythons: after a build, the same workers have
    imported the package's core, and neither bpy nor any other layer of the package."""
    monkeypatch.setattr(field_module, "MIN_RAYS_PER_PROCESS", 16)
    cams, masks = three_camera_rig(64, 36)
    with runtime().journal() as runs:
        prepare(Rig(cams, masks), "SCALAR_FIELD", replace(settings_for("PREVIEW"), processes=2))
    workers = {pid for r in runs for pid in r.workers}
    probes = runtime().map(probe, [0, 1], 2).results
    assert workers and {pid for _i, pid, _w, _m, _b in probes} <= workers | set(runtime().pids())
    for _i, pid, in_worker, loaded, bpy in probes:
        assert in_worker and not bpy
        assert "multiscale_camera.core.field.tracer" in loaded or pid not in workers
        layers = {name.split(".")[1] for name in loaded}
        assert layers == {"core"}, layers


def brute_force_fold_map(fld):
    """Every quad of the lattice counted on its own by the slow reference counter
    (``fold_reference``): the map no banding or sharing can change."""
    w, h = fld.rig.size
    out = np.zeros((h - 1, w - 1), dtype=bool)
    cams = fld.rig.cameras
    for y in range(h - 1):
        iy, ix = np.meshgrid([y, y + 1], np.arange(w), indexing="ij")
        bundle = fld.rays(ix.ravel(), iy.ravel())
        verts = bundle.vertices.reshape(2, w, -1, 3)
        out[y] = reference_quad_folds(verts, bending_active(verts, cams[-1], None, cams[:-1]))[0]
    return out


def vertices_per_ray(fld):
    """K: the vertices of each of the field's rays (fold_map's bands hold
    ``FOLD_CHUNK_VERTICES`` of them)."""
    return fld.rays(np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64)).vertices.shape[1]


@pytest.mark.slow
def test_folds_counted_in_two_processes_equal_those_counted_in_one(monkeypatch):
    cams, masks = turned_rig(64, 48)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    # bands of 4 lattice rows: 16 of them at 64x48, shared between two workers
    monkeypatch.setattr(report_module, "FOLD_CHUNK_VERTICES", 64 * vertices_per_ray(fld) * 4)
    monkeypatch.setattr(report_module, "FOLD_SHARED_MIN_PIXELS", 64 * 48)
    with runtime().journal() as alone_runs:
        one, stride = fold_map(fld, processes=1)
    assert alone_runs == [] and stride == 1
    with runtime().journal() as runs:
        two, _ = fold_map(fld, processes=2)
    # 16 bands in runs of two, a few a process, shared by a worker and this process
    # (which takes the runs no worker has yet): every run counted once
    shares = 2 * report_module.SHARES_PER_WORKER
    assert len(runs) == 1 and len(runs[0].where) == shares
    assert runs[0].in_workers + runs[0].in_process == shares and len(runs[0].workers) <= 1
    expected = brute_force_fold_map(fld)
    assert expected.any()  # the turned rig's IMAGE_BLEND folds: the maps say where
    np.testing.assert_array_equal(one, expected)
    np.testing.assert_array_equal(two, expected)


@pytest.mark.slow
def test_build_report_keeps_the_fold_count_in_one_process_when_threads_say_one(monkeypatch):
    """The report's fold count ignored the build's worker count (Blender's Threads):
    ``build_report`` called ``fold_map`` with its default, one worker per core, even
    where the build was asked to stay in one process (a farm node at Fixed 1)."""
    cams, masks = turned_rig(64, 48)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    monkeypatch.setattr(report_module, "FOLD_CHUNK_VERTICES", 64 * vertices_per_ray(fld) * 4)
    monkeypatch.setattr(report_module, "FOLD_SHARED_MIN_PIXELS", 64 * 48)
    with runtime().journal() as runs:
        alone = build_report(fld, "STANDARD", processes=1)
    assert runs == []
    with runtime().journal() as runs:
        shared = build_report(fld, "STANDARD", processes=2)
    shares = 2 * report_module.SHARES_PER_WORKER
    assert len(runs) == 1 and runs[0].in_workers + runs[0].in_process == shares
    assert alone["folds"] == shared["folds"] > 0


def test_folds_of_an_image_with_few_bands_are_shared_on_smaller_bands(monkeypatch):
    """Too few full bands for two workers (a 480x270 image has 5): the count was kept
    in two threads of this process, which gained nothing (its many small array
    operations hold the interpreter between them). The bands are cut smaller and the
    processes share them (a worker and this one); the map is every quad's."""
    cams, masks = turned_rig(64, 48)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    k = vertices_per_ray(fld)
    monkeypatch.setattr(report_module, "FOLD_CHUNK_VERTICES", 64 * k * 16)  # 4 full bands
    monkeypatch.setattr(report_module, "FOLD_SHARED_MIN_PIXELS", 64 * 48)
    workers, rows = report_module.fold_plan(64, 48, k, 2)
    assert workers == 1 and rows == 47 // (2 * report_module.SMALL_BANDS) + 2 == 7
    with runtime().journal() as runs:
        two, _ = fold_map(fld, processes=2)
    assert len(runs) == 1 and runs[0].in_workers + runs[0].in_process == len(runs[0].where) == 8
    assert not [t for t in threading.enumerate() if t.name == "fold count"]  # it ended
    expected = brute_force_fold_map(fld)
    assert expected.any()
    np.testing.assert_array_equal(two, expected)


def test_bands_too_wide_for_the_chunk_are_counted_in_pieces_of_columns(monkeypatch):
    """Rays of 216 vertices across a 1920-wide image (the turned rig's forced
    SCALAR_FIELD): a band of two rows held 0.83 M vertices, 1.6 chunks, whatever
    FOLD_CHUNK_VERTICES said. Such a band now goes in pieces of columns of at most a
    chunk; the map is every quad's."""
    cams, masks = turned_rig(64, 48)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    k = vertices_per_ray(fld)
    monkeypatch.setattr(report_module, "FOLD_CHUNK_VERTICES", 2 * k * 7)  # 7 columns a piece
    monkeypatch.setattr(report_module, "FOLD_SHARED_MIN_PIXELS", 64 * 48)
    assert report_module.fold_plan(64, 48, k, 2)[1] == 2
    assert report_module.fold_columns(2, k) == 7
    pieces = []
    piece = report_module._fold_piece

    def recorded(fld, band, xs, limit, need, a, b, folds):
        pieces.append((len(band), b - a))
        piece(fld, band, xs, limit, need, a, b, folds)

    monkeypatch.setattr(report_module, "_fold_piece", recorded)
    one, _ = fold_map(fld, processes=1)
    assert pieces and max(rows * cols for rows, cols in pieces) <= 2 * 7
    two, _ = fold_map(fld, processes=2)  # the workers' pieces go unrecorded here
    expected = brute_force_fold_map(fld)
    assert expected.any()
    np.testing.assert_array_equal(one, expected)
    np.testing.assert_array_equal(two, expected)


def test_the_measure_runs_while_workers_count_the_folds(monkeypatch):
    """``measure_map`` begins the shared fold count before it measures the preserved
    rays, so that the workers count while this process measures: the count's workers
    are handed their bands before the measure ends, and both results are those of the
    measure and the count made one after the other."""
    cams, masks = turned_rig(64, 48)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    monkeypatch.setattr(report_module, "FOLD_SHARED_MIN_PIXELS", 64 * 48)
    runtime().warm(1)  # ready: its first band goes out as the count begins
    alone_cameras = report_module.measure_cameras(fld)
    alone_folds, _ = fold_map(fld, processes=1)
    seen = []
    measure = report_module.measure_cameras

    def measuring(*args):
        seen.append([t.name for t in threading.enumerate() if t.name == "fold count"])
        return measure(*args)

    monkeypatch.setattr(report_module, "measure_cameras", measuring)
    with runtime().journal() as runs:
        cameras, folds, _ = report_module.measure_map(fld, processes=2)
    assert seen == [["fold count"]]  # the count was under way while it measured
    # the worker took bands from the start; this process the ones left once it measured
    assert len(runs) == 1 and runs[0].in_workers >= 1
    assert runs[0].in_workers + runs[0].in_process == len(runs[0].where)
    assert cameras == alone_cameras
    np.testing.assert_array_equal(folds, alone_folds)


def test_a_cancelled_measure_stops_the_shared_fold_count(monkeypatch):
    """Esc during the measure: the fold count its workers had begun stops too (its run
    cancelled, its thread ended), and ``Cancelled`` reaches the caller."""
    cams, masks = turned_rig(192, 108)  # bands of tens of milliseconds each
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    monkeypatch.setattr(report_module, "FOLD_SHARED_MIN_PIXELS", 192 * 108)

    def cancelled(*args):
        raise Cancelled()

    monkeypatch.setattr(report_module, "measure_cameras", cancelled)
    with runtime().journal() as runs, pytest.raises(Cancelled):
        report_module.measure_map(fld, processes=2)
    assert len(runs) == 1 and runs[0].cancelled
    assert not [t for t in threading.enumerate() if t.name == "fold count"]
