"""A rig in motion: steady grid layouts (``core.field.layout``), what one frame's build
takes from the one before (``core.methods.reuse``) and the frame-to-frame jump
(``render.sequence``, numpy only).

The reference for reuse is the same frame built cold: its rays agree within 0.01 px
(in the pixels of the multiscale image, measured across neighbouring rays), whatever
the process built before."""

from dataclasses import replace

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
from multiscale_camera.core.methods import FrameReuse, Settings, prepare
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
    assert first.grids != second.grids
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
