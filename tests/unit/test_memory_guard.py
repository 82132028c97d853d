"""The memory guard's estimate (core.quality.memory): bytes from shapes, each part
against the arrays it models, the whole against a measured peak on a small rig, and the
refusal of an 8000x8000 build before it starts (docs/failures.md, "Memory")."""

import json
import subprocess
import sys
import time
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fixtures.rigs import zoom_rig
from multiscale_camera.core.diagnostics import Diagnostics
from multiscale_camera.core.errors import RigError
from multiscale_camera.core.field import tracer
from multiscale_camera.core.field.plane_step import MAX_GAIN, extra_steps
from multiscale_camera.core.geometry import DEFAULT_SEGMENTS, Rig
from multiscale_camera.core.methods import prepare, registry, settings_for, traced
from multiscale_camera.core.quality import (
    MAX_MEASURED,
    budget_message,
    build_memory,
    estimate_memory,
    render_memory,
    report,
    size_text,
)
from multiscale_camera.core.quality import measure_memory as mm
from multiscale_camera.core.quality import memory as mem

ROOT = Path(__file__).resolve().parents[2]
MB = 1 << 20
GB = 1 << 30


def test_constants_are_the_ones_the_code_uses():
    assert mem.MAX_STRIDE == traced.MAX_STRIDE
    assert mem.MAX_RAYS_PER_SHARE == tracer.MAX_RAYS_PER_SHARE
    assert mem.MIN_RAYS_PER_PROCESS == tracer.MIN_RAYS_PER_PROCESS
    assert mem.DEVIATION_BLOCK_VERTICES == traced.DEVIATION_BLOCK_VERTICES
    assert mem.WORKER_BLOCK_VERTICES == tracer.BLOCK_VERTICES


@pytest.mark.parametrize("nested", [False, True])
def test_copied_stride_and_step_limit_are_those_the_trace_uses(monkeypatch, nested):
    """The estimate reads the lattice's stride and the trace's step limit off the rig
    with its own copy of their arithmetic (core.quality cannot import the methods): on a
    rig, the stride equals what a build's ``traced.lattice_stride`` uses, and the step
    limit ``trace_field``'s but for the steps its bands at near planes add, which the
    estimate takes at their most (``field.NearPlaneStep``, MAX_GAIN)."""
    limits = []
    lattice = traced._AdaptiveLattice

    def recording(tracer_, rig_, step, max_steps, tol_px, diag):
        limits.append(max_steps)
        return lattice(tracer_, rig_, step, max_steps, tol_px, diag)

    monkeypatch.setattr(traced, "_AdaptiveLattice", recording)
    cams, masks = zoom_rig(96, 54)
    rig = Rig(cams, masks)
    settings = replace(settings_for("PREVIEW"), nested=nested, processes=1)
    est = estimate_memory(rig, "SCALAR_FIELD", settings)
    fld = prepare(rig, "SCALAR_FIELD", settings)
    assert fld.stats["levels"] > 1 if nested else fld.stats["levels"] == 1
    assert est.shapes["stride"] == fld.stats["stride"]
    (limit,) = limits
    (gain,) = fld.stats["plane_gains"]
    banded = extra_steps([gain]) if gain > 1 else 0  # no band: the step as it was
    assert limit == est.shapes["step_limit"] - extra_steps([MAX_GAIN]) + banded


def test_image_blend_grows_with_pixels_and_cameras_only():
    one = build_memory("IMAGE_BLEND", 100, 50, 2)
    assert one.main == 100 * 50 * (2 * mem.WEIGHT_BYTES_PER_CAMERA_PIXEL + mem.SOLVE_BYTES_PER_CELL)
    assert one.workers == 0 and one.worker == 0
    assert build_memory("IMAGE_BLEND", 200, 100, 2).main == 4 * one.main
    assert build_memory("IMAGE_BLEND", 100, 50, 2, voxels=10**9).main == one.main


def trace_stage(pixels, cameras, voxels, rays, vertices, share, workers=True):
    """The trace stage's bytes in the main process, written out from the arrays: the
    kept grid and the lattice, with the rounds (the rays once, the error estimate's
    block, a share coming in) or, after them, the merge (the rays twice)."""
    largest = int(np.ceil(mem.LARGEST_ROUND * rays))
    held = voxels * mem.KEPT_BYTES_PER_VOXEL + pixels * (
        mem.LATTICE_BYTES_PER_PIXEL + cameras * mem.CELL_TABLE_BYTES_PER_PIXEL
    )
    rounds = (
        rays * vertices * mem.RAY_BYTES_PER_VERTEX
        + min(largest * vertices, mem.DEVIATION_BLOCK_VERTICES) * mem.DEVIATION_BYTES_PER_VERTEX
        + share * vertices * mem.RECEIVE_BYTES_PER_VERTEX
    )
    merge = rays * vertices * mem.RAY_BYTES_PER_VERTEX * 2
    return held + max(rounds, merge)


def share_reference(rays, limit, length, preserved, nested=False):
    """A share's peak written out stage by stage from the arrays the tracer holds:
    camera after camera its preserved rays (float32 xyz and membership to the step
    limit, one block of float64 temporaries), then the streamlines, then the pickle."""
    block = 1 << 18
    stages, trimmed = [], 0.0
    for i, f in enumerate(preserved):
        n = f * rays * limit
        per = 225 if nested else (130 if i else 48)
        stages.append(trimmed + 16 * n + per * min(n, block))
        trimmed += 16 * f * rays * length
    rest = (1 - sum(preserved)) * rays * length
    stages.append(trimmed + 52 * rest + (130 if nested else 46) * min(rest, block))
    stages.append(50 * rays * length)
    return max(stages)


def test_scalar_field_peak_is_its_largest_stage_and_the_workers_shares():
    kw = dict(traced_rays=40000, vertices=100, max_vertices=200, workers=2)
    # a large grid: the solve is the peak
    est = build_memory("SCALAR_FIELD", 480, 270, 3, voxels=10**7, **kw)
    assert est.main == 10**7 * mem.SOLVE_BYTES_PER_CELL
    # rays' share: the largest round (0.45 of the rays) over two workers, by default
    # every ray a later camera's (the most a share holds)
    share = -(-int(np.ceil(0.45 * 40000)) // 2)
    assert est.workers == 2
    assert est.worker == pytest.approx(
        mem.WORKER_BASE_BYTES
        + 10**7 * mem.WORKER_BYTES_PER_VOXEL
        + share_reference(share, 200, 100, [0.0, 1.0]),
        abs=2,
    )
    assert est.total == est.main + 2 * est.worker == sum(est.parts.values())
    assert list(est.parts.values()) == sorted(est.parts.values(), reverse=True)
    # a small grid and a large image: the trace is
    est = build_memory("SCALAR_FIELD", 1920, 1080, 3, voxels=10**5, **kw)
    assert est.main == trace_stage(1920 * 1080, 3, 10**5, 40000, 100, share)
    assert {"lattice", "traced rays", "error estimate"} <= set(est.parts)
    # a small one of both, and few rays: the fill's chunks
    est = build_memory(
        "SCALAR_FIELD", 64, 48, 2, voxels=10**5, traced_rays=600, vertices=20, workers=2
    )
    assert est.main == mem.FILL_CHUNK_BYTES + 10**5 * (
        mem.FILL_BYTES_PER_VOXEL + 2 * mem.FILL_BYTES_PER_CAMERA_VOXEL
    )


# One worker's share of the 25x zoom's largest round at STANDARD, 480x270: rays, the
# step limit plus one, the longest ray, each camera's preserved rays among them, and
# the share's peak under tracemalloc with preserved rays laid out a block at a time
# (bench/worker_memory.py zoom25_rig:SCALAR_FIELD:STANDARD:480x270), MB.
ZOOM25_SHARE = (5546, 280, 98, (919, 1207, 408), 40.6)
THREE_CAMERA_SHARE = (9994, 278, 95, (3240, 3581, 1160), 54.8)


@pytest.mark.parametrize("measured", [ZOOM25_SHARE, THREE_CAMERA_SHARE])
def test_25x_worker_lays_preserved_rays_out_camera_by_camera_not_all_at_once(measured):
    """The 25x zoom's worker was estimated at 1.50 times its peak (bench/memory.json):
    the model charged every preserved ray of a share at once (70 B a vertex to the step
    limit), where the worker lays them out one camera after the other, its peak the
    largest of its stages. The stages (``share_memory``) against the reference and
    against the share's peak measured with those rays."""
    rays, limit, length, cams, peak_mb = measured
    fractions = [c / rays for c in cams]
    stages = mem.share_memory(rays, limit, length, fractions)
    assert max(stages.values()) == pytest.approx(share_reference(rays, limit, length, fractions))
    assert max(stages.values()) / MB == pytest.approx(peak_mb, rel=0.1)
    assert max(stages, key=stages.get) == "preserved rays laid out"


def test_nested_share_weighs_the_nested_sampler_s_block():
    """On nested grids the sampler's temporaries of a block set the share's peak: the
    1000x rig's share of 7,418 rays (5,338 streamlines of 146 vertices) peaked at 78 MB,
    its streamlines' stage (bench/worker_memory.py zoom1000_rig:SCALAR_FIELD_NESTED:
    PREVIEW:480x270), where the model before said 71 MB for the whole worker's share."""
    fractions = [457 / 7418, 1213 / 7418, 410 / 7418]
    stages = mem.share_memory(7418, 530, 147, fractions, nested=True)
    assert max(stages.values()) == pytest.approx(
        share_reference(7418, 530, 147, fractions, nested=True)
    )
    assert max(stages.values()) / MB == pytest.approx(78.0, rel=0.1)
    assert max(stages, key=stages.get) == "streamlines"


def test_preserved_fractions_are_each_camera_s_share_of_the_pixels():
    rng = np.random.default_rng(3)
    masks = rng.random((3, 37, 53)) < [[[0.2]], [[0.1]], [[0.05]]]
    kept = [sum(masks[i, y, x] for y in range(37) for x in range(53)) for i in range(3)]
    assert mem.preserved_fractions(masks) == pytest.approx([k / (37 * 53) for k in kept])
    assert mem.preserved_fractions(np.zeros((2, 4, 4), bool)) == [0.0, 0.0]


def test_preserved_rays_are_laid_out_a_block_at_a_time(monkeypatch):
    """A worker laid every preserved ray of its share out at once in float64 (about
    130 bytes a vertex: 135 MB on the three-camera rig's largest share at STANDARD,
    bench/worker_memory.py): now ``BLOCK_VERTICES`` vertices at a time, kept float32.
    The same rays bit for bit as laid out at once; the peak that of a block."""
    cams, masks = zoom_rig(96, 54)
    settings = replace(settings_for("PREVIEW"), nested=False, processes=1)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", settings)
    trace = fld.tracer()
    iy, ix = np.nonzero(masks[1])
    u, v, k = ix + 0.5, iy + 0.5, 300

    def laid(block):
        monkeypatch.setattr(tracer, "BLOCK_VERTICES", block)
        tracemalloc.start()
        try:
            out = trace.preserved_rays(1, u, v, fld.step, k)[1]
            return out, tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    whole, whole_peak = laid(10**9)
    blocks, block_peak = laid(20 * k)
    for name in ("vertices", "membership", "counts", "reason"):
        assert np.array_equal(getattr(blocks, name), getattr(whole, name)), name
    held = len(u) * k * mem.HELD_BYTES_PER_VERTEX
    assert whole_peak > held + 100 * len(u) * k  # float64 temporaries of every vertex
    assert block_peak < 1.5 * held + mem.CURVED_LAYOUT_BYTES_PER_VERTEX * 20 * k + 4 * MB


def test_auto_estimates_image_blend_built_then_measured_with_its_fold_bands():
    """AUTO's default build was estimated as IMAGE_BLEND's solve and SCALAR_FIELD's
    whole build, never as what it allocates first: IMAGE_BLEND's weights solved, then
    its rays measured (the along-ray measure here, the fold count's bands in workers
    when there are enough of them, ``report.fold_map``). SCALAR_FIELD is asked of the
    guard when AUTO goes on to it (``Diagnostics.guard``)."""
    assert mm.SEGMENTS == DEFAULT_SEGMENTS and mm.blend_vertices(3) == 18
    big = build_memory("AUTO", 1920, 1080, 2, workers=2)
    rows = report.FOLD_CHUNK_VERTICES // (1920 * 10)  # rows of 10-vertex rays a band
    bands = len(range(0, 1079, rows - 1))
    # one solve, here; the bands shared by a worker and this process
    assert bands >= 2 * report.MIN_SHARED_BANDS and big.workers == 1
    assert big.worker == (
        mem.WORKER_BASE_BYTES + 1920 * 1080 * 2 * 5 + rows * 1920 * 10 * (70 + 2 * 24)
    )
    assert big.main == 1920 * 1080 * (2 * 8 + mem.SOLVE_BYTES_PER_CELL)  # the solve
    assert "traced rays" not in big.parts and big.shapes["traced_rays"] == 0
    # an image with too few full bands for its processes: smaller bands, still shared,
    # counted in a worker while this process measures, then here too
    small = build_memory("AUTO", 480, 270, 3, workers=2)
    assert small.workers == 1  # the fold count's
    rows = min(report.FOLD_CHUNK_VERTICES // (480 * 18), 269 // (2 * report.SMALL_BANDS) + 2)
    assert rows == 35
    assert small.worker == mem.WORKER_BASE_BYTES + 480 * 270 * 3 * 5 + rows * 480 * 18 * (
        70 + 3 * 24
    )
    along = min(MAX_MEASURED, 480 * 270) * 18 * 260
    band = rows * 480 * 18 * (70 + 3 * 24)
    assert small.main == max(
        480 * 270 * (3 * 8 + mem.SOLVE_BYTES_PER_CELL), 480 * 270 * 3 * 4 + max(along, band)
    )
    # below ``report.FOLD_SHARED_MIN_PIXELS`` the count stays here, after the measure
    tiny = build_memory("AUTO", 160, 90, 3, workers=2)
    band = min(report.FOLD_CHUNK_VERTICES // (160 * 18), 90) * 160 * 18 * (70 + 3 * 24)
    along = min(MAX_MEASURED, 160 * 90) * 18 * 260
    assert tiny.workers == 0
    assert tiny.main == max(
        160 * 90 * (3 * 8 + mem.SOLVE_BYTES_PER_CELL), 160 * 90 * 3 * 4 + max(along, band)
    )


def test_weight_solves_in_workers_are_estimated_there():
    """At 1920x1080 a three-camera rig's two weight solves run at once in two workers
    (``harmonic.mask_weights``): each worker holds one solve and the masks, and the
    build's process the weights alone; a worker's peak is the larger of its solve and
    its fold band. This process then eases the weights (float64 temporaries)."""
    pixels = 1920 * 1080
    three = build_memory("IMAGE_BLEND", 1920, 1080, 3, workers=2)
    solve = pixels * mem.SOLVE_BYTES_PER_CELL + pixels * 3
    assert three.workers == 2 and three.worker == mem.WORKER_BASE_BYTES + solve
    assert three.main == pixels * 3 * mem.EASE_BYTES_PER_CAMERA_PIXEL  # then eased here
    alone = build_memory("IMAGE_BLEND", 1920, 1080, 3, workers=1)  # one process: here
    assert alone.workers == 0 and alone.main == pixels * (3 * 8 + mem.SOLVE_BYTES_PER_CELL)
    # one solve: the fold count's worker starts meanwhile, on the idle core (this
    # process counts with it once it has measured)
    two = build_memory("IMAGE_BLEND", 1920, 1080, 2, workers=2)
    assert two.workers == 1 and two.worker == mem.WORKER_BASE_BYTES
    auto = build_memory("AUTO", 1920, 1080, 3, workers=2)
    rows = report.FOLD_CHUNK_VERTICES // (1920 * 18)
    band = pixels * 3 * 5 + rows * 1920 * 18 * (70 + 3 * 24)
    assert auto.workers == 2 and auto.worker == mem.WORKER_BASE_BYTES + max(solve, band)


def test_auto_asks_the_guard_before_it_builds_scalar_field(monkeypatch):
    """The guard estimates AUTO's first candidate before the build; AUTO asks it again
    before it goes on to SCALAR_FIELD, which a refusal stops before it starts."""
    built = []
    monkeypatch.setattr(registry, "accuracy_misses", lambda cameras, acc: ["camera 'C2' off"])
    monkeypatch.setitem(registry.METHODS, "SCALAR_FIELD", lambda *a: built.append(a))
    asked = []

    def refuse(method):
        asked.append(method)
        raise RigError(f"{method} would not fit")

    diag = Diagnostics()
    diag.guard = refuse
    cams, masks = zoom_rig(64, 48)
    with pytest.raises(RigError, match="^SCALAR_FIELD would not fit$"):
        prepare(Rig(cams, masks), "AUTO", replace(settings_for("PREVIEW"), processes=1), diag)
    assert asked == ["SCALAR_FIELD"] and built == []
    assert diag.child().guard is refuse


def test_uniform_grid_traced_rays_do_not_grow_with_the_scale_ratio():
    """On one uniform grid the 25x zoom traced 27,215 rays at STANDARD where the
    estimate, growing as (1 + log10 25)^2 / 4, said 61,116 (bench/memory.json): there
    the ratio is left out; on nested grids it stays."""
    args = (480, 270, 16, 4040, 0.5)
    uniform = [mem.traced_rays_of(*args, ratio=r, nested=False) for r in (3.2, 25.0, 1000.0)]
    assert uniform[0] == uniform[1] == uniform[2]
    lattice = (30 + 1) * (17 + 1)
    assert uniform[0] == int(lattice + 3.0 * 4040 + 0.048 * 480 * 270)
    nested = [mem.traced_rays_of(*args, ratio=r, nested=True) for r in (3.2, 25.0, 1000.0)]
    assert nested[0] < nested[1] < nested[2]
    coarse = mem.traced_rays_of(480, 270, 16, 4040, 2.0, nested=False)
    assert coarse == int(lattice + 3.0 * 4040 + 0.048 * 0.25**1.75 * 480 * 270)


def test_nested_levels_are_filled_in_the_workers_and_solved_one_at_a_time():
    kw = dict(traced_rays=600, vertices=20, workers=2)
    uniform = build_memory("SCALAR_FIELD", 64, 48, 2, voxels=3 * 10**6, **kw)
    nested = build_memory("SCALAR_FIELD", 64, 48, 2, voxels=3 * 10**6, level_voxels=10**6, **kw)
    assert uniform.main == 3 * 10**6 * mem.SOLVE_BYTES_PER_CELL
    assert nested.main == 10**6 * mem.SOLVE_BYTES_PER_CELL  # the largest level's solve
    fill = mem.FILL_CHUNK_BYTES + 10**6 * (
        mem.FILL_BYTES_PER_VOXEL + 2 * mem.FILL_BYTES_PER_CAMERA_VOXEL
    )
    assert nested.workers == 2
    assert nested.parts["workers: grid fill"] == 2 * fill


def test_a_small_trace_stays_in_the_main_process():
    est = build_memory(
        "SCALAR_FIELD", 64, 48, 2, voxels=1000, traced_rays=300, vertices=20, workers=2
    )
    assert est.workers == 0 and est.worker == 0
    assert est.total == est.main


def test_render_memory_counts_the_engine_arrays_and_the_shared_passes():
    """The engine's IndexOB and First Hit arrays (16 B/px) and, with workers, the shared
    passes they write (13 float32 channels) were not counted."""
    est = render_memory(1000, 1000, samples=4, traced_rays=0, workers=2)
    assert mem.ENGINE_BYTES_PER_PIXEL == 16 and mem.SHARED_PASS_BYTES_PER_PIXEL == 52
    assert est.main == 10**6 * (mem.RESULT_BYTES_PER_PIXEL + 16 + 52)
    assert est.worker == mem.RENDER_WORKER_BYTES + 10**6 * mem.RENDER_WORKER_BYTES_PER_PIXEL
    assert est.workers == 2 and est.parts["engine arrays"] == 16 * 10**6
    # a small frame renders in-process: a tile there, no shared passes, no workers
    small = render_memory(400, 300, samples=1, traced_rays=10, vertices=5, workers=2)
    assert small.workers == 0 and small.worker == 0 and "shared passes" not in small.parts
    assert (
        small.main
        == 120000 * (mem.RESULT_BYTES_PER_PIXEL + 16)
        + 10 * 5 * (mem.FIELD_BYTES_PER_VERTEX)
        + mem.TILE_RAYS * mem.TILE_BYTES_PER_RAY
    )


def test_render_estimate_was_never_measured_and_now_meets_the_measured_renders():
    """bench/render_memory.json: each measured render (main process plus workers)
    against ``render_memory`` of its shapes with today's constants (the estimate put a
    1920x1080 render with two workers at 0.30 of its peak). With workers within 30%; in
    one process never under by more than 30% (the resident size there misses memory the
    build freed and the render reused, so the estimate runs up to 2.1 times over)."""
    rows = json.loads((ROOT / "bench" / "render_memory.json").read_text())["rows"]
    assert any(row["held_out"] for row in rows) and len(rows) >= 6
    for row in rows:
        w, h = (int(x) for x in row["row"].split(":")[1].split("x"))
        workers = int(row["row"].split(":p")[1]) if ":p" in row["row"] else 2
        est = render_memory(w, h, 1, row["traced_rays"], row["vertices"], workers)
        ratio = est.total / 2**20 / row["measured_mb"]
        # in one process no worker ran; with workers, the render's (and the build's, idle)
        assert len(row["peak_workers_added_mb"]) >= est.workers, row
        assert est.workers or not row["peak_workers_added_mb"], row
        assert 0.7 <= ratio <= (1.3 if est.workers else 2.5), (ratio, row)


def test_edge_pixels_counts_both_sides_of_every_label_change():
    masks = np.zeros((2, 6, 8), bool)
    masks[1, 2:4, 3:5] = True  # a 2x2 square: itself and its 8 outer neighbours across edges
    assert mem.edge_pixels(masks) == 4 + 8


def test_edge_pixels_of_a_large_image_are_counted_on_a_sparser_lattice():
    masks = np.zeros((2, 4096, 4096), bool)  # 16 M pixels: every 2nd row and column
    masks[1, 1000:3000, 1000:3000] = True
    exact = 2 * 4 * 2000  # both sides of a 2000-pixel square's four edges
    assert abs(mem.edge_pixels(masks) - exact) <= 0.01 * exact


def test_budget_message_names_the_estimate_the_budget_and_what_to_lower():
    est = build_memory(
        "SCALAR_FIELD", 8000, 8000, 2, voxels=4 * 10**6, traced_rays=10**6, vertices=100
    )
    assert budget_message(est, est.total, "the scene's Memory Budget") is None
    text = budget_message(est, 4 * GB, "the scene's Memory Budget")
    parts = list(est.parts.items())[:3]
    assert text == (
        f"The field build would need about {size_text(est.total)} of memory ("
        + ", ".join(f"{k} {size_text(v)}" for k, v in parts)
        + "), more than the budget of 4.0 GB (the scene's Memory Budget); nothing was "
        "started: lower the resolution (Output Properties > Format > Resolution, or its %) "
        "or the Quality (a looser accuracy target traces fewer rays, with fewer steps), "
        "or raise the Memory Budget (Multiscale > Preview and Cache; 0: the free memory)"
    )


def test_budget_message_says_quality_for_the_grid_and_threads_for_workers():
    grid = build_memory("SCALAR_FIELD", 64, 48, 2, voxels=10**9, traced_rays=300, vertices=20)
    assert "lower the Quality (its voxel budget)" in budget_message(grid, MB, "x")
    workers = build_memory(
        "SCALAR_FIELD", 64, 48, 2, voxels=10**8, traced_rays=10**6, vertices=10, workers=64
    )
    assert list(workers.parts)[0].startswith("workers: ")
    assert "Render > Performance > Threads: Fixed, fewer" in budget_message(workers, MB, "x")


def test_budget_message_suggests_a_lower_quality_for_traced_rays():
    """Traced rays shrink with a looser accuracy target as well as with fewer pixels:
    the refusal says both (it said only the resolution)."""
    est = build_memory("SCALAR_FIELD", 64, 48, 2, voxels=10, traced_rays=10**6, vertices=400)
    assert list(est.parts)[0] == "traced rays"
    text = budget_message(est, MB, "x")
    assert (
        "lower the resolution (Output Properties > Format > Resolution, or its %) or the "
        "Quality (a looser accuracy target traces fewer rays, with fewer steps), or raise"
    ) in text, text


def test_8000x8000_is_refused_before_the_build_starts_with_the_estimate():
    """The estimate of an 8000x8000 build takes no more than a glance at its masks: it
    is refused (here against a 4 GB budget) before anything large is allocated."""
    cams, _masks = zoom_rig(80, 80)
    cams = tuple(replace(c, width=8000, height=8000) for c in cams)
    masks = np.zeros((2, 8000, 8000), bool)
    masks[0, :1000] = True  # camera 1 keeps a band at the top, camera 2 a square
    masks[1, 3000:5000, 3000:5000] = True
    rig = Rig(cams, masks)
    start = time.perf_counter()
    est = estimate_memory(rig, "SCALAR_FIELD", settings_for("STANDARD"), workers=2)
    seconds = time.perf_counter() - start
    text = budget_message(est, 4 * GB, "the scene's Memory Budget")
    assert est.total > 4 * GB  # 6.3 GB
    assert text.startswith(f"The field build would need about {size_text(est.total)} of memory")
    assert "more than the budget of 4.0 GB (the scene's Memory Budget)" in text
    assert "lower the resolution" in text
    assert list(est.parts)[0] == "traced rays"
    assert seconds < 20  # a glance at the masks, no build (2.7 s measured on a busy machine)


@pytest.mark.slow
@pytest.mark.parametrize(
    "spec, workers",
    [("zoom_rig:SCALAR_FIELD:STANDARD:480x270:p3", 3), ("zoom25_rig:AUTO:PREVIEW:480x270", 1)],
)
def test_estimate_is_within_30_percent_of_the_measured_peak_on_a_held_out_row(spec, workers):
    """Rows the constants were not calibrated on (bench/memory.py HELD_OUT): the zoom rig
    at 480x270, STANDARD, SCALAR_FIELD with three workers, and the default build (AUTO:
    IMAGE_BLEND built and measured, its fold count in a worker and this process) of the 25x zoom at
    PREVIEW. The peak resident size of a fresh process plus its workers' against the
    estimate made before, in all and for the largest worker. (It measured a calibration
    row: in-sample.)"""
    done = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "memory.py"), "--one", spec],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    row = json.loads(done.stdout.strip().splitlines()[-1])
    assert row["held_out"], "a row the constants were not fitted to"
    assert len(row["peak_workers_mb"]) == workers, row
    assert 0.7 <= row["estimated_mb"] / row["measured_mb"] <= 1.3, row
    if workers:
        assert 0.7 <= row["worker_ratio"] <= 1.3, row
