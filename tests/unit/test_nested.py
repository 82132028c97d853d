"""Nested grids: layout, continuity across levels, tracing, and the 1000x rig."""

from dataclasses import replace

import numpy as np
import pytest

from fixtures.rigs import three_camera_rig, zoom1000_rig
from multiscale_camera.core.field import (
    BAND_CELLS,
    NestedDomain,
    ScaleField,
    choose_grid,
    choose_levels,
    fill_membership,
    sample,
    scheduled_rays,
    solve_levels,
)
from multiscale_camera.core.geometry import Family, Rig
from multiscale_camera.core.methods import prepare, settings_for
from multiscale_camera.core.quality import build_report


@pytest.fixture(scope="module")
def levels_of_three_cameras():
    cams, masks = three_camera_rig(96, 54)
    rig = Rig(cams, masks)
    outer = choose_grid(rig, 0.5, 1 << 62).grid
    levels = choose_levels(rig, 0.5, 160**3, 16.0, outer.bounds)
    families = [Family(rig.cameras, i, rig.beta) for i in range(len(cams))]
    solved = solve_levels(rig, levels.grids, families, fill_membership)
    return rig, levels, solved


def test_each_level_lies_inside_its_parent_on_its_parents_lattice(levels_of_three_cameras):
    _rig, levels, _solved = levels_of_three_cameras
    assert len(levels.grids) >= 2
    for parent, child in zip(levels.grids, levels.grids[1:]):
        assert child.cell == pytest.approx(parent.cell / 2)
        # every parent centre in the child's box is a child centre
        offset = (child.origin - parent.origin) / parent.cell
        np.testing.assert_allclose(offset, np.round(offset), atol=1e-9)
        p_lo, p_hi = parent.bounds
        c_lo, c_hi = child.bounds
        assert (c_lo >= p_lo + BAND_CELLS * parent.cell - 1e-9).all()
        assert (c_hi <= p_hi - BAND_CELLS * parent.cell + 1e-9).all()


def test_a_level_agrees_with_its_parent_on_its_boundary(levels_of_three_cameras):
    _rig, levels, solved = levels_of_three_cameras
    domain = NestedDomain(levels.grids, solved.fields)
    for lev in range(1, len(levels.grids)):
        grid, field = levels.grids[lev], solved.fields[lev]
        shell = np.ones(grid.shape, dtype=bool)
        shell[1:-1, 1:-1, 1:-1] = False
        parent = NestedDomain(levels.grids[lev - 1 : lev], solved.fields[lev - 1 : lev])
        got = field[shell]
        want = parent.sample(grid.centres()[shell])
        np.testing.assert_allclose(got, want, atol=1e-6)
    assert domain.sample(levels.grids[-1].centres(flat=True)[:10]).dtype == np.float32


def test_membership_reads_two_levels_as_the_full_blend_over_all_levels(
    levels_of_three_cameras,
):
    """N read from the finest level holding a point (and its parent in that level's
    band) equals blending every level into its parent, coarsest first."""
    _rig, levels, solved = levels_of_three_cameras
    domain = NestedDomain(levels.grids, solved.fields)
    rng = np.random.default_rng(3)
    pts = []
    for grid in levels.grids:
        lo, hi = grid.bounds
        pad = 4 * grid.cell
        pts.append(lo - pad + rng.random((4000, 3)) * (hi - lo + 2 * pad))
    pts = np.concatenate(pts)
    want = sample(levels.grids[0], solved.fields[0], pts).astype(np.float64)
    for grid, field in zip(levels.grids[1:], solved.fields[1:]):
        lo, hi = grid.bounds
        inside = np.minimum(pts - lo, hi - pts).min(axis=1)
        s = np.clip(inside / (BAND_CELLS * grid.cell), 0.0, 1.0)
        ramp = s * s * (3.0 - 2.0 * s)
        want += ramp * (sample(grid, field, pts) - want)
    got = domain.sample(pts)
    assert (domain._depth(pts)[1] < 1).any() and (domain._depth(pts)[0] > 1).any()
    np.testing.assert_allclose(got, want, atol=2e-6)


def test_membership_has_no_seam_where_levels_meet(levels_of_three_cameras):
    """Walk N along lines through every level's faces in steps far below a cell: it
    changes by no more than its steepest slope allows (a seam would jump)."""
    _rig, levels, solved = levels_of_three_cameras
    domain = NestedDomain(levels.grids, solved.fields)
    # the steepest slope: voxel-to-voxel differences on each level, and the hand-over
    # ramp (smoothstep, slope 1.5 / band) times the largest gap between the levels
    slope = 0.0
    for lev, (grid, field) in enumerate(zip(levels.grids, solved.fields)):
        for axis in range(3):
            slope = max(slope, np.abs(np.diff(field, axis=axis)).max() / grid.cell)
        if lev:
            parent = NestedDomain(levels.grids[lev - 1 : lev], solved.fields[lev - 1 : lev])
            gap = np.abs(field.ravel() - parent.sample(grid.centres(flat=True))).max()
            slope += gap * 1.5 / (BAND_CELLS * grid.cell)
    rng = np.random.default_rng(7)
    worst = 0.0
    for grid in levels.grids[1:]:
        lo, hi = grid.bounds
        for _ in range(40):
            axis = rng.integers(3)
            a = lo + rng.random(3) * (hi - lo)
            b = a.copy()
            a[axis], b[axis] = lo[axis] - 4 * grid.cell, lo[axis] + 6 * grid.cell
            t = np.linspace(0, 1, 2001)[:, None]
            pts = a + t * (b - a)
            n = domain.sample(pts).astype(np.float64)
            step = np.linalg.norm(b - a) / 2000
            worst = max(worst, np.abs(np.diff(n)).max() / step)
    assert worst <= slope * 1.01 + 1e-6, (worst, slope)


@pytest.mark.slow
def test_scheduled_rays_lie_on_the_curves_at_the_steps_asked():
    cams, masks = three_camera_rig(96, 54)
    fam = Family(cams, 2, 0.2)
    scale = ScaleField(cams)

    def step(x):
        return scale(x) / 40.0

    rng = np.random.default_rng(3)
    u, v = rng.uniform(0, 96, 50), rng.uniform(0, 54, 50)
    big = choose_grid(Rig(cams, masks), 0.5, 1 << 62).grid
    verts = scheduled_rays(fam, u, v, step, 300, big.contains)
    for r in range(0, 50, 7):
        pts = verts[r]
        inside = big.contains(pts)
        k = int(np.argmin(inside)) if not inside.all() else len(pts)
        pts = pts[: max(k, 2)]
        # on the curve: each vertex is within a hair of a dense sampling of R_3 there
        taus = np.linspace(0.0, 2.0 + 8.0, 200001)
        dense, _ = fam.evaluate(np.full(len(taus), u[r]), np.full(len(taus), v[r]), taus)
        for p in pts[:: max(1, len(pts) // 40)]:
            near = np.linalg.norm(dense - p, axis=-1).min()
            spacing = np.linalg.norm(np.diff(dense, axis=0), axis=-1).max()
            assert near <= spacing, (near, spacing)
        gaps = np.linalg.norm(np.diff(pts, axis=0), axis=-1)
        want = step(pts[:-1])
        # the asked length, within what the arc-length table of 64 samples per guide stage
        # resolves (1.2% at worst here)
        np.testing.assert_allclose(gaps, want, rtol=0.02)


@pytest.mark.slow
def test_streamlines_cross_levels_without_kinks():
    cams, masks = three_camera_rig(96, 54)
    fld = prepare(Rig(cams, masks), "SCALAR_FIELD", replace(settings_for("STANDARD"), nested=True))
    assert len(fld.domain.grids) >= 2
    t = fld.traced
    v = t.vertices.astype(np.float64)
    seg = np.diff(v, axis=1)
    length = np.linalg.norm(seg, axis=-1)
    unit = seg / np.maximum(length, 1e-30)[..., None]
    turn = np.arccos(np.clip((unit[:, 1:] * unit[:, :-1]).sum(-1), -1, 1))
    live = np.arange(turn.shape[1])[None] < (t.counts[:, None] - 3)
    # turning per unit length, over the local step: a kink turns a lot in one short step
    curvature = turn / np.maximum(length[:, 1:], 1e-30)
    scale = ScaleField(cams)(v[:, 1:-1].reshape(-1, 3)).reshape(turn.shape)
    bend = np.where(live, curvature * scale, 0.0)
    # the rays bend on the scale of the bundle: a few radians per scale length at most
    assert bend.max() < 20.0, bend.max()


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="not met: the nested grids fold in sections (81 quads here, 269 at 240x135; "
    "66 and 239 before the step shortened at the near planes) among the transition rays, "
    "where camera 2's ray family, far off its image, turns hard into its near plane "
    "(docs/architecture.md, Where the 1000x rig's transition rays fold); the preserved "
    "rays hold every camera (p95 0.10, 0.20 and 0.14 px here along the whole ray, with "
    "the preserved cells interpolated where that stays within a quarter of the target)",
)
def test_1000x_rig_holds_every_camera_to_a_pixel_where_a_uniform_grid_fails():
    cams, masks = zoom1000_rig(192, 108)
    rig = Rig(cams, masks)
    nested = prepare(rig, "SCALAR_FIELD", settings_for("STANDARD"))  # chosen: budget capped
    assert len(nested.domain.grids) > 5
    report = build_report(nested, "STANDARD")
    # measured 13 folded quads of 20,000 at this size (8 with the 1.5-cell step of a
    # 1920-wide image; issue 7 asks for none: not met yet): stretches of neighbouring
    # traced rays that cross where N nears 2, on camera 2's side of its transition
    assert report["folds"] <= 14 and report["stalled"] == 0
    for cam in report["cameras"]:
        assert cam["preserved_px"]["p95"] <= 1.0, cam
    # the same voxel budget as one uniform grid: the smallest camera is lost
    uniform = prepare(rig, "SCALAR_FIELD", replace(settings_for("STANDARD"), nested=False))
    flat = build_report(uniform, "STANDARD")
    assert flat["cameras"][2]["preserved_px"]["p95"] > 10.0
    assert sum(np.prod(g) for g in report["grids"]) <= settings_for("STANDARD").max_voxels
