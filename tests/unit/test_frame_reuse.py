"""A rig in motion: steady grid layouts (``core.field.layout``), what one frame's build
takes from the one before (``core.methods.reuse``) and the frame-to-frame jump
(``render.sequence``, numpy only).

The reference for reuse is the same frame built cold: its rays agree within 0.01 px
(in the pixels of the multiscale image, measured across neighbouring rays), whatever
the process built before."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from fixtures.rigs import look_at, orbit, three_camera_rig
from multiscale_camera.core.field import (
    BAND_CELLS,
    SNAP_CELLS,
    Grid,
    choose_grid,
    choose_levels,
    fill_membership,
    ladder_cell,
    steady_grid,
    steady_levels,
)
from multiscale_camera.core.field.nested import MARGIN_CELLS
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.methods import (
    FrameReuse,
    Settings,
    frame_levels,
    plan_shot,
    prepare,
    registry,
)
from multiscale_camera.render.sequence import Sequence, jump_px, pixel_size

WIDTH, HEIGHT = 64, 36
SETTINGS = Settings(accuracy_px=2.0, max_voxels=48**3, processes=1, steady=True)


def rig_at(t, nested=None):
    """The three-camera rig with camera 3 moved ``t`` metres toward the subject (camera 3
    alone moves: cameras 1 and 2 and the masks hold still)."""
    cams, masks = three_camera_rig(WIDTH, HEIGHT)
    target = np.array((0.0, 0.0, 0.5))
    eye = orbit(target, 4.0 - t, 20, 25)
    cams = (*cams[:2], replace(cams[2], matrix_world=look_at(eye, target)))
    return Rig(cams, masks)


def holds(grid, lo, hi):
    """Whether ``grid``'s centres span the box [lo, hi]."""
    g_lo, g_hi = grid.bounds
    return bool((g_lo <= lo + 1e-9).all() and (g_hi >= hi - 1e-9).all())


def test_ladder_cell_rounds_down_to_a_rung():
    for cell in (0.013, 0.1, 0.25, 1.0, 3.7):
        rung = ladder_cell(cell)
        k = np.log2(rung) * 16
        assert k == pytest.approx(round(k), abs=1e-9)
        assert cell / 2 ** (1 / 16) < rung <= cell


def test_steady_grid_holds_the_box_on_the_world_lattice():
    grid = Grid.from_bounds((0.11, -0.3, 0.02), (0.52, 0.4, 0.3), 0.05)
    steady = steady_grid(grid)
    assert holds(steady, *grid.bounds)
    quantum = SNAP_CELLS * steady.cell
    lo, hi = steady.bounds
    np.testing.assert_allclose(lo / quantum, np.round(lo / quantum), atol=1e-9)
    np.testing.assert_allclose(hi / quantum, np.round(hi / quantum), atol=1e-9)


def test_steady_grid_stays_put_until_the_box_leaves_it():
    cell = ladder_cell(0.05)
    quantum = SNAP_CELLS * cell
    shape = (11, 11, 11)  # 10 cells: 1.25 quanta
    lo = np.full(3, 0.3 * quantum)
    first = steady_grid(Grid(lo, cell, shape))
    for shift in (0.05, 0.2, 0.4):  # of a quantum: the box stays inside [0, 2] quanta
        assert steady_grid(Grid(lo + shift * quantum, cell, shape)) == first, shift
    moved = lo + 0.5 * quantum
    left = steady_grid(Grid(moved, cell, shape))
    assert left != first
    assert holds(left, moved, moved + 10 * cell)


def test_steady_levels_nest_on_their_parents_lattices():
    rig = rig_at(0.0)
    outer = choose_grid(rig, 0.5, 1 << 62).grid
    levels = choose_levels(rig, 0.5, 200_000, 16, outer.bounds).grids
    assert len(levels) >= 2
    steady = steady_levels(levels)
    assert len(steady) == len(levels)
    for lev, (before, after) in enumerate(zip(levels, steady, strict=True)):
        assert holds(after, *before.bounds)
        assert after.cell == pytest.approx(ladder_cell(levels[0].cell) / 2**lev)
        if lev:
            parent = steady[lev - 1]
            offset = (after.origin - parent.origin) / parent.cell
            np.testing.assert_allclose(offset, np.round(offset), atol=1e-9)
            keep = (MARGIN_CELLS + BAND_CELLS) * parent.cell
            p_lo, p_hi = parent.bounds
            a_lo, a_hi = after.bounds
            assert (a_lo >= p_lo + keep - 1e-9).all() and (a_hi <= p_hi - keep + 1e-9).all()


def test_a_small_move_keeps_the_steady_levels():
    """Camera 3 moves 2 mm of its 4 m: the layout of the frame before still covers it."""
    grids = []
    for t in (0.0, 0.002):
        rig = rig_at(t)
        outer = choose_grid(rig, 0.5, 1 << 62).grid
        grids.append(steady_levels(choose_levels(rig, 0.5, 200_000, 16, outer.bounds).grids))
    assert grids[0] == grids[1]


def test_known_claims_fill_as_splatting_does():
    rig = rig_at(0.0)
    grid = steady_grid(choose_grid(rig, 2.0, 40**3).grid)
    families = [Family(rig.cameras, i, rig.beta) for i in range(3)]
    cold = fill_membership(rig, grid, families)
    known = [(cold.cores[0], cold.halos[0]), None, (cold.cores[2], cold.halos[2])]
    warm = fill_membership(rig, grid, families, known=known)
    np.testing.assert_array_equal(warm.values, cold.values)
    np.testing.assert_array_equal(warm.constrained, cold.constrained)
    assert warm.conflicts == cold.conflicts


def used_grids(fld):
    """The Grids a SCALAR_FIELD build used, coarsest first."""
    return tuple(fld.domain.grids) if fld.domain is not None else (fld.grid,)


def ray_gap_px(a, b):
    """(worst, p99) distance between the rays of fields ``a`` and ``b`` for every pixel,
    vertex by vertex, over the spacing of ``b``'s neighbouring rays there (pixels of the
    multiscale image)."""
    w, h = a.rig.size
    iy, ix = np.mgrid[0:h, 0:w]
    ra, rb = a.rays(ix.ravel(), iy.ravel()), b.rays(ix.ravel(), iy.ravel())
    k = min(ra.vertices.shape[1], rb.vertices.shape[1])
    va = ra.vertices[:, :k].astype(np.float64)
    vb = rb.vertices[:, :k].astype(np.float64)
    grid = vb.reshape(h, w, k, 3)
    spacing = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
    spacing = np.concatenate([spacing, spacing[:, -1:]], axis=1).reshape(-1, k)
    gap = np.linalg.norm(va - vb, axis=-1) / np.maximum(spacing, 1e-12)
    return float(gap.max()), float(np.percentile(gap.max(axis=1), 99))


@pytest.mark.slow
@pytest.mark.parametrize("nested", [False, True])
def test_a_frame_after_another_matches_it_built_cold(nested):
    """Frame 2 built after frame 1 (camera 1 and 2's claims taken, the solve started
    from frame 1's membership) against frame 2 built in a fresh process state."""
    settings = replace(SETTINGS, nested=nested)
    reuse = FrameReuse()
    prepare(rig_at(0.0), "SCALAR_FIELD", settings, reuse=reuse)
    warm = prepare(rig_at(0.002), "SCALAR_FIELD", settings, reuse=reuse)
    cold = prepare(rig_at(0.002), "SCALAR_FIELD", settings)
    took = warm.stats["reuse"]
    assert took["claims_reused"] == ["C1", "C2"]
    assert took["claims_built"] == ["C3"]
    assert took["solve"] == "warm"
    assert warm.grids == cold.grids
    worst, p99 = ray_gap_px(warm, cold)
    print(f"nested={nested}: worst {worst:.2e} px, p99 {p99:.2e} px")
    assert worst <= 0.01


@pytest.mark.slow
def test_a_moved_layout_builds_cold():
    """A rig that left the layout (camera 3 half a metre on) takes nothing: its grids
    are new, so neither claims nor a warm start apply."""
    reuse = FrameReuse()
    first = prepare(rig_at(0.0), "SCALAR_FIELD", SETTINGS, reuse=reuse)
    second = prepare(rig_at(0.5), "SCALAR_FIELD", SETTINGS, reuse=reuse)
    assert used_grids(first) != used_grids(second)
    assert second.stats["reuse"]["solve"] == "cold"
    assert second.stats["reuse"]["claims_reused"] == []


def slow_jump(index0, hits0, index1, hits1):
    """The jump of ``jump_px``, pixel by pixel."""
    h, w = index1.shape
    moves = []
    for y in range(h):
        for x in range(w):
            if index1[y, x] <= 0 or index0[y, x] != index1[y, x]:
                continue
            sizes = []
            for ny, nx in ((y, x + 1), (y + 1, x)):
                if ny < h and nx < w and index1[ny, nx] == index1[y, x]:
                    d = float(np.linalg.norm(hits1[ny, nx] - hits1[y, x]))
                    if d > 0:
                        sizes.append(d)
            if sizes:
                moves.append(float(np.linalg.norm(hits1[y, x] - hits0[y, x])) / min(sizes))
    return float(np.percentile(moves, 95))


def test_jump_is_the_p95_move_in_pixels():
    rng = np.random.default_rng(3)
    h, w = 12, 16
    yy, xx = np.mgrid[0:h, 0:w]
    spacing = np.where(xx < 8, 0.01, 0.002)[..., None]  # two scales side by side
    hits1 = np.stack([xx, yy, np.zeros_like(xx)], -1) * spacing
    index1 = np.where(xx < 8, 1, 2).astype(np.float32)
    index1[0, :3] = 0  # misses
    hits0 = hits1 + rng.normal(0, 0.003, hits1.shape)
    index0 = index1.copy()
    index0[5, 5] = 3  # another object there before
    got = jump_px(index0, hits0, index1, hits1)
    assert got == pytest.approx(slow_jump(index0, hits0, index1, hits1), rel=1e-9)
    assert np.isnan(pixel_size(index1, hits1)[0, 0])


def test_a_sequence_reports_its_worst_jump():
    h, w = 6, 8
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([xx, yy, np.zeros_like(xx)], -1).astype(np.float64)
    index = np.ones((h, w), dtype=np.float32)
    seq = Sequence()
    assert seq.add("S", 1, 1, index, base).px is None  # starts the sequence
    assert seq.add("S", 2, 1, index, base + [0.5, 0, 0]).px == pytest.approx(0.5)
    third = seq.add("S", 3, 1, index, base + [2.5, 0, 0])
    assert third.px == pytest.approx(2.0)
    assert (third.worst_px, third.worst_frame) == (pytest.approx(2.0), 3)
    fourth = seq.add("S", 4, 1, index, base + [2.6, 0, 0])
    assert (fourth.worst_px, fourth.worst_frame) == (pytest.approx(2.0), 3)
    # a frame that does not follow starts a new sequence
    assert seq.add("S", 9, 1, index, base).worst_px is None


def claims_on(grid, cameras=3):
    """A fill's worth of (empty) claims on ``grid``: what ``FrameReuse.keep`` stores."""
    empty = tuple(np.zeros(grid.shape, dtype=bool) for _ in range(cameras))
    return SimpleNamespace(cores=empty, halos=empty)


def test_reuse_store_holds_one_build_while_the_layout_holds():
    """The store once gained a claims entry per moving camera per frame on a layout that
    held (7, 12, 17, 22 entries after frames 5 to 20): it holds this build's alone."""
    reuse = FrameReuse()
    grid = Grid(np.zeros(3), 0.1, (4, 4, 4))
    membership = np.zeros(grid.shape, dtype=np.float32)
    for frame in range(20):
        rig = rig_at(0.001 * frame)  # camera 3 moves, cameras 1 and 2 hold still
        reuse.keep(rig, (grid,), (claims_on(grid),), (membership,), "tag")
        assert len(reuse.claims) == 3, frame
        assert len(reuse.solved) == 1, frame
    taken = reuse.known(rig_at(0.019), (grid,))[0]
    assert all(claims is not None for claims in taken)
    earlier = reuse.known(rig_at(0.0), (grid,))[0]
    assert earlier[0] is not None and earlier[2] is None  # camera 3's old claims are gone


def test_steady_grids_hold_the_voxel_budget():
    """Snapping once took steady grids to 1.29 to 1.69 times their input's voxels, past
    the budget: the rung now rises until the snapped grids fit it."""
    rig = rig_at(0.0)
    for budget in (30_000, 200_000, 885_000):
        outer = choose_grid(rig, 0.5, 1 << 62).grid
        levels = choose_levels(rig, 0.5, budget, 16, outer.bounds).grids
        steady = steady_levels(levels, budget)
        assert sum(g.size for g in steady) <= budget, budget
        for before, after in zip(levels, steady):
            assert holds(after, *before.bounds)
        uniform = choose_grid(rig, 0.25, budget).grid
        one = steady_grid(uniform, budget)
        assert one.size <= budget, budget
        assert holds(one, *uniform.bounds)
        # no coarser than it must be: one rung finer would not fit
        finer = steady_grid(replace(uniform, cell=one.cell / 2 ** (1 / 16) * 0.999))
        assert finer.size > budget or finer.cell < one.cell


def shot(frames=9, step=0.05):
    """The rigs of a shot: camera 3 dollies ``step`` metres a frame."""
    return [rig_at(step * f) for f in range(frames)]


@pytest.mark.parametrize(
    ("nested", "budget", "step"), [(False, 60_000, 0.1), (True, 200_000, 0.15)]
)
def test_a_shot_keeps_one_layout_over_its_frames(nested, budget, step):
    """Steady layouts once re-snapped inside a shot (each frame's cell from its own
    budget): the shot's layout holds every frame's grids, within the budget, while the
    frames' own steady layouts change along the dolly."""
    settings = replace(SETTINGS, nested=nested, max_voxels=budget, accuracy_px=0.5)
    rigs = shot(9, step)
    layout = plan_shot(rigs, settings)
    assert layout.nested == nested
    assert sum(g.size for g in layout.grids) <= settings.max_voxels
    own = []
    for rig in rigs:
        if nested:
            grids = frame_levels(rig, settings).grids
            own.append(steady_levels(grids, settings.max_voxels))
        else:
            grids = (choose_grid(rig, settings.accuracy_px, settings.max_voxels).grid,)
            own.append((steady_grid(grids[0], settings.max_voxels),))
        assert layout.covers(grids)
    assert len(set(own)) > 1  # each frame alone would have moved its grids
    assert plan_shot(rigs[::-1], settings) == layout  # whatever order frames come in


@pytest.mark.slow
def test_a_frame_of_a_shot_builds_on_the_shots_layout():
    settings = replace(SETTINGS, nested=True)
    rigs = shot(5)
    layout = plan_shot(rigs, settings)
    fld = prepare(rigs[2], "SCALAR_FIELD", replace(settings, layout=layout))
    assert fld.stats["layout"] == "shot"
    assert used_grids(fld) == layout.grids


def test_auto_keeps_one_method_for_a_moving_rig(monkeypatch):
    """AUTO counted IMAGE_BLEND's folds frame by frame, so it could switch method mid
    shot: a rig in motion whose shot was not measured (no ``Settings.shot``) gets
    SCALAR_FIELD at every frame, with the reuse store, and says why."""
    asked = []

    def scalar(rig, settings, diag=None, reuse=None):
        asked.append(("SCALAR_FIELD", reuse))
        return SimpleNamespace(stats={})

    def blend(rig, settings, diag=None):
        asked.append(("IMAGE_BLEND", None))
        raise AssertionError("IMAGE_BLEND built for a rig in motion")

    monkeypatch.setattr(registry, "prepare_scalar_field", scalar)
    monkeypatch.setattr(registry, "prepare_image_blend", blend)
    reuse = FrameReuse()
    for t in (0.0, 0.3, 0.6):
        out = registry.prepare_auto(rig_at(t), SETTINGS, reuse=reuse)
        assert out.stats["auto"] == registry.UNMEASURED_SHOT
    assert asked == [("SCALAR_FIELD", reuse)] * 3


def test_jump_needs_no_pass_index():
    """The jump was measured on IndexOB, the objects' pass index: 0 on every object of
    an ordinary scene, read as no hit, so no jump was ever reported. Objects are now
    told apart by the sequence's ordinal of their names (hit object + 1 in the pass)."""
    h, w = 6, 8
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([xx, yy, np.zeros_like(xx)], -1).astype(np.float64)
    seq = Sequence()
    hit = np.where(xx < 4, 1, 2)  # "Floor" left, "Teapot" right, both pass index 0
    hit[0, 0] = 0  # a miss
    first = seq.object_index(["Floor", "Teapot"], hit)
    assert first[0, 0] == 0 and first[0, 1] == 1 and first[0, 5] == 2
    seq.add("S", 1, 1, first, base)
    # the next frame lists its objects in another order: the ordinals follow the names
    second = seq.object_index(["Teapot", "Floor"], np.where(xx < 4, 2, 1))
    np.testing.assert_array_equal(second[1:], first[1:])
    assert seq.add("S", 2, 1, second, base + [0.25, 0, 0]).px == pytest.approx(0.25)


def test_a_second_view_layer_keeps_the_first_ones_sequence():
    """Two view layers rendered in turn at each frame once reset each other's sequence
    (and a same-named scene of another file continued it): each render key has its own."""
    h, w = 6, 8
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([xx, yy, np.zeros_like(xx)], -1).astype(np.float64)
    index = np.ones((h, w))
    seq = Sequence()
    a, b = ("shot.blend", "Scene", "A"), ("shot.blend", "Scene", "B")
    for frame in (1, 2, 3):
        moved = base + [0.5 * frame, 0, 0]
        got_a = seq.add(a, frame, 1, index, moved)
        got_b = seq.add(b, frame, 1, index, moved + [0.0, 0.1 * frame, 0])
        if frame > 1:
            assert got_a.px == pytest.approx(0.5)
            assert got_b.px == pytest.approx(np.hypot(0.5, 0.1))
    other_file = ("other.blend", "Scene", "A")
    assert seq.add(other_file, 4, 1, index, base).px is None


def test_a_partial_warm_start_reads_as_one():
    """A frame's report once said "membership solve (warm on 2 of 4 grids start)"."""
    reuse = FrameReuse()
    cold, warm = np.zeros(3), np.ones(3)
    said = [
        reuse.record(["C1"], [[None]] * 4, starts, {})["solve_said"]
        for starts in ([None] * 4, [warm] * 4, [warm, cold, None, None])
    ]
    assert said == [
        "membership solve",
        "membership solve (warm start)",
        "membership solve (warm start on 2 of 4 grids)",
    ]


@pytest.mark.slow
def test_a_partial_warm_start_matches_a_cold_build():
    """Frame 2 (camera 3 5 cm on, on the same grids) after frame 1 with level 0's warm
    start gone (the finer levels start from
    frame 1's membership, level 0 cold): its rays agree with frame 2 built cold within
    0.01 px."""
    settings = replace(SETTINGS, nested=True)
    reuse = FrameReuse()
    first = prepare(rig_at(0.0), "SCALAR_FIELD", settings, reuse=reuse)
    assert len(used_grids(first)) >= 2
    coarsest = used_grids(first)[0]
    for key in [k for k in reuse.solved if k[0] == coarsest]:
        del reuse.solved[key]
    warm = prepare(rig_at(0.05), "SCALAR_FIELD", settings, reuse=reuse)
    cold = prepare(rig_at(0.05), "SCALAR_FIELD", settings)
    levels = len(used_grids(first))
    assert warm.stats["reuse"]["solve"] == f"warm on {levels - 1} of {levels} grids"
    assert used_grids(warm) == used_grids(cold)
    worst, p99 = ray_gap_px(warm, cold)
    print(f"partial warm start: worst {worst:.2e} px, p99 {p99:.2e} px")
    assert worst <= 0.01
