"""Voxel grid sampling and Runge-Kutta streamlines against analytic answers."""

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from multiscale_camera.core.field import (
    MIDPOINT,
    RK4,
    FieldSampler,
    Grid,
    StopReason,
    Streamlines,
    rk4_streamlines,
    sample,
)


def _axes(grid):
    return [grid.origin[a] + grid.cell * np.arange(n) for a, n in enumerate(grid.shape)]


# --- Grid -------------------------------------------------------------------------


def test_grid_geometry():
    grid = Grid((1.0, -2.0, 0.5), 0.25, (5, 3, 1))
    lo, hi = grid.bounds
    np.testing.assert_allclose(lo, [1.0, -2.0, 0.5])
    np.testing.assert_allclose(hi, [2.0, -1.5, 0.5])
    centres = grid.centres()
    assert centres.shape == (5, 3, 1, 3) and centres.dtype == np.float64
    np.testing.assert_allclose(centres[2, 1, 0], [1.5, -1.75, 0.5])
    np.testing.assert_array_equal(grid.centres(flat=True), centres.reshape(-1, 3))
    np.testing.assert_allclose(
        grid.to_index(centres.reshape(-1, 3)).reshape(centres.shape),
        np.moveaxis(np.indices(grid.shape), 0, -1),
    )
    inside = grid.contains(
        [
            [1.0, -2.0, 0.5],
            [2.0, -1.5, 0.5],
            [2.01, -1.6, 0.5],
            [1.5, -1.6, 0.6],
            [np.nan, -1.6, 0.5],
        ]
    )
    np.testing.assert_array_equal(inside, [True, True, False, False, False])
    assert grid == Grid([1, -2, 0.5], 0.25, (5, 3, 1)) and hash(grid) == hash(
        Grid([1, -2, 0.5], 0.25, (5, 3, 1))
    )
    with pytest.raises(ValueError):
        Grid((0, 0, 0), 0.0, (2, 2, 2))


def test_from_bounds_covers_the_box_with_a_cell_to_spare():
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 0.3, 2.0])
    grid = Grid.from_bounds(lo, hi, 0.1)
    glo, ghi = grid.bounds
    np.testing.assert_allclose(glo, lo - 0.1)
    assert (ghi >= hi + 0.1 - 1e-12).all() and (ghi < hi + 0.2 - 1e-12).all()
    assert grid.shape == (23, 6, 3)


# --- sample -----------------------------------------------------------------------


def test_sample_reproduces_affine_fields():
    rng = np.random.default_rng(1)
    grid = Grid((0.3, -1.0, 2.0), 0.2, (9, 7, 5))
    lo, hi = grid.bounds
    matrix, offset = rng.normal(size=(3, 4)), rng.normal(size=4)
    field = grid.centres() @ matrix + offset  # (nx, ny, nz, 4) float64
    points = lo + rng.random((5000, 3)) * (hi - lo)
    exact = points @ matrix + offset
    for values in (
        sample(grid, field, points),
        sample(grid, field.astype(np.float32), points),
        FieldSampler(grid, field[..., :3])(points),
    ):
        assert values.dtype == np.float32
        np.testing.assert_allclose(values, exact[:, : values.shape[1]], atol=2e-6)
    scalar = sample(grid, field[..., 0], points)
    assert scalar.shape == (5000,)
    np.testing.assert_allclose(scalar, exact[:, 0], atol=2e-6)


def test_sample_matches_scipy_and_clamps_outside():
    rng = np.random.default_rng(2)
    grid = Grid((-1.0, 0.0, 0.5), 0.1, (12, 9, 7))
    lo, hi = grid.bounds
    field = rng.random((*grid.shape, 3), dtype=np.float32)
    reference = RegularGridInterpolator(_axes(grid), field)
    points = lo + rng.random((20000, 3)) * (hi - lo)
    for sampler in (
        lambda p: sample(grid, field, p),
        FieldSampler(grid, field),
        FieldSampler(grid, field, pad=False),
    ):
        np.testing.assert_allclose(sampler(points), reference(points), atol=1e-6)
    # Outside the box a point reads the nearest point of the box.
    outside = lo + (rng.random((1000, 3)) * 3 - 1) * (hi - lo)
    np.testing.assert_allclose(
        sample(grid, field, outside), reference(np.clip(outside, lo, hi)), atol=1e-6
    )
    scalar = sample(grid, field[..., 1], points)
    np.testing.assert_allclose(scalar, reference(points)[:, 1], atol=1e-6)


def test_sample_handles_single_voxel_axes_nan_and_chunks():
    grid = Grid((0, 0, 0), 1.0, (4, 1, 3))
    field = np.arange(12, dtype=np.float32).reshape(4, 1, 3)
    points = np.array([[1.5, 5.0, 0.5], [np.nan, 0.0, 0.0]])
    values = sample(grid, field, points)
    np.testing.assert_allclose(values[0], 1.5 * 3 + 0.5)
    assert np.isnan(values[1])
    many = np.random.default_rng(3).random((70000, 3)) * [3, 0, 2]
    np.testing.assert_allclose(sample(grid, field, many), many[:, 0] * 3 + many[:, 2], atol=1e-5)


# --- rk4_streamlines --------------------------------------------------------------


def _rotation(points):
    """v = (-y, x + 1, 0): circles about (-1, 0, 0); the unit circle passes the origin,
    where float32 vertices resolve tiny closure errors."""
    return np.stack([-points[:, 1], points[:, 0] + 1.0, np.zeros(len(points))], axis=1)


def test_constant_field_gives_straight_rays():
    rng = np.random.default_rng(4)
    direction = np.array([1.0, 2.0, -0.5])
    unit = direction / np.linalg.norm(direction)
    seeds = rng.random((500, 3)) - 0.5
    lines = rk4_streamlines(lambda p: np.broadcast_to(direction, p.shape), seeds, 0.05, 30)
    assert isinstance(lines, Streamlines)
    assert lines.points.shape == (500, 31, 3) and lines.points.dtype == np.float32
    assert (lines.reason == StopReason.REACHED_LIMIT).all() and (lines.counts == 31).all()
    expected = seeds[:, None] + 0.05 * np.arange(31)[None, :, None] * unit
    np.testing.assert_allclose(lines.points, expected, atol=1e-6)
    np.testing.assert_allclose(lines.length, 1.5)


def _closure_errors(tableau, turns):
    errors = []
    for n in turns:
        lines = rk4_streamlines(_rotation, [[0.0, 0.0, 0.0]], 2 * np.pi / n, n, tableau=tableau)
        assert lines.counts[0] == n + 1
        np.testing.assert_allclose(lines.length, 2 * np.pi)
        errors.append(np.linalg.norm(lines.ends[0].astype(np.float64)))
    errors = np.array(errors)
    return errors, np.log2(errors[:-1] / errors[1:])


def test_rk4_closes_the_circle_at_fourth_order():
    errors, orders = _closure_errors(RK4, (128, 256, 512))
    assert errors[0] < 1e-6
    assert ((orders > 3.5) & (orders < 4.5)).all(), orders


def test_midpoint_closes_the_circle_at_second_order():
    errors, orders = _closure_errors(MIDPOINT, (256, 512, 1024))
    assert ((orders > 1.5) & (orders < 2.5)).all(), orders


def test_sampled_linear_field_traces_like_the_analytic_one():
    grid = Grid.from_bounds([-2.5, -1.5, -0.5], [0.5, 1.5, 0.5], 0.1)
    field = FieldSampler(grid, _rotation(grid.centres(flat=True)).reshape(*grid.shape, 3))
    n = 256
    sampled = rk4_streamlines(field, [[0.0, 0.0, 0.0]], 2 * np.pi / n, n, inside=grid.contains)
    analytic = rk4_streamlines(_rotation, [[0.0, 0.0, 0.0]], 2 * np.pi / n, n)
    assert sampled.reason[0] == StopReason.REACHED_LIMIT
    np.testing.assert_allclose(sampled.points, analytic.points, atol=2e-5)


def test_stop_reasons_counts_and_lengths():
    grid = Grid((0, 0, 0), 0.1, (11, 11, 11))  # the unit cube

    def velocity(points):  # +x, zero beyond x = 0.52 where y > 0.5
        v = np.zeros_like(points)
        v[:, 0] = np.where((points[:, 1] > 0.5) & (points[:, 0] > 0.52), 0.0, 1.0)
        return v

    seeds = np.array(
        [
            [0.25, 0.2, 0.5],  # leaves through x = 1
            [0.25, 0.8, 0.5],  # stalls past x = 0.52
            [1.5, 0.5, 0.5],  # starts outside
        ]
    )
    lines = rk4_streamlines(velocity, seeds, 0.1, 100, inside=grid.contains)
    assert list(lines.reason) == [StopReason.LEFT_GRID, StopReason.STALLED, StopReason.LEFT_GRID]
    np.testing.assert_array_equal(lines.counts, [9, 4, 1])
    np.testing.assert_allclose(lines.length, [0.8, 0.3, 0.0], atol=1e-12)
    last_in, out = lines.points[0, 7], lines.points[0, 8]
    assert grid.contains(last_in[None])[0] and not grid.contains(out[None])[0]
    np.testing.assert_allclose(out, [1.05, 0.2, 0.5], atol=1e-6)
    # From x = 0.45 the last stage (at 0.55) sees no field: 0.45 + 0.1 * 5/6.
    np.testing.assert_allclose(lines.ends[1], [0.45 + 0.5 / 6, 0.8, 0.5], atol=1e-6)
    # Padding repeats the last vertex.
    assert (lines.points[1, 4:] == lines.points[1, 3]).all()
    assert (lines.points[2] == seeds[2].astype(np.float32)).all()
    # The polyline length matches the integrated arc length on straight rays.
    segments = np.linalg.norm(np.diff(lines.points.astype(np.float64), axis=1), axis=2)
    np.testing.assert_allclose(segments.sum(axis=1)[[0, 2]], lines.length[[0, 2]], atol=1e-6)


def test_length_limit_lands_exactly():
    lines = rk4_streamlines(_rotation, [[0.0, 0.0, 0.0]], 0.03, 1000, max_length=1.0)
    assert lines.reason[0] == StopReason.REACHED_LIMIT
    assert lines.counts[0] == 35  # 33 steps of 0.03, then one of 0.01
    np.testing.assert_allclose(lines.length, 1.0)
    angle = 1.0  # radians along the unit circle about (-1, 0, 0)
    np.testing.assert_allclose(lines.ends[0], [np.cos(angle) - 1, np.sin(angle), 0], atol=1e-6)


def test_record_every_keeps_seed_every_nth_and_last_vertices():
    lines = rk4_streamlines(_rotation, [[0.0, 0.0, 0.0]], 0.01, 10, record_every=3)
    full = rk4_streamlines(_rotation, [[0.0, 0.0, 0.0]], 0.01, 10)
    assert lines.counts[0] == 5
    np.testing.assert_array_equal(lines.points[0], full.points[0, [0, 3, 6, 9, 10]])
    # Leaving: the last inside point and the outside point are both kept.
    inside = lambda p: p[:, 0] < 0.105  # noqa: E731
    straight = lambda p: np.tile([1.0, 0.0, 0.0], (len(p), 1))  # noqa: E731
    left = rk4_streamlines(straight, [[0.0, 0.0, 0.0]], 0.01, 100, inside=inside, record_every=4)
    assert left.reason[0] == StopReason.LEFT_GRID
    np.testing.assert_allclose(
        left.points[0, : left.counts[0], 0], [0.0, 0.04, 0.08, 0.10, 0.11], atol=1e-7
    )


def test_chunking_and_cancelling():
    rng = np.random.default_rng(5)
    seeds = rng.random((50, 3)) - 0.5
    ball = lambda p: np.linalg.norm(p, axis=1) < 0.8  # noqa: E731
    whole = rk4_streamlines(_rotation, seeds, 0.05, 40, max_length=1.7, inside=ball)
    chunked = rk4_streamlines(_rotation, seeds, 0.05, 40, max_length=1.7, inside=ball, chunk=7)
    for name in ("points", "counts", "reason", "length"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(chunked, name))
    assert whole.complete and len(set(whole.counts)) > 3
    for r, count in enumerate(whole.counts):  # padding repeats the last vertex
        assert (whole.points[r, count:] == whole.points[r, count - 1]).all()
    calls = []

    def should_stop():
        calls.append(1)
        return len(calls) > 1  # let the first chunk start, then cancel

    whole = rk4_streamlines(_rotation, seeds, 0.05, 40)
    cut = rk4_streamlines(_rotation, seeds, 0.05, 40, chunk=20, should_stop=should_stop)
    assert not cut.complete
    assert (cut.reason == StopReason.RUNNING).all()
    assert (cut.counts[:20] == 16).all()  # cancelled at step 16, the point reached kept
    assert (cut.counts[20:] == 1).all() and (cut.length[20:] == 0).all()
    np.testing.assert_allclose(cut.length[:20], 15 * 0.05)
    np.testing.assert_array_equal(cut.points[:20, :16], whole.points[:20, :16])


def test_velocity_can_see_which_rays_it_serves():
    seeds = np.zeros((10, 3))
    seen = []

    def velocity(points, rays):  # ray r runs along x at speed r (ray 0 stalls)
        seen.append(rays.copy())
        return np.outer(rays, [1.0, 0.0, 0.0])

    lines = rk4_streamlines(velocity, seeds, 0.1, 5, with_rays=True, chunk=4)
    assert lines.reason[0] == StopReason.STALLED and lines.counts[0] == 1
    assert (lines.reason[1:] == StopReason.REACHED_LIMIT).all()
    np.testing.assert_allclose(lines.ends[1:, 0], 0.5, atol=1e-6)
    assert all(len(r) <= 4 for r in seen)
    np.testing.assert_array_equal(np.unique(np.concatenate(seen)), np.arange(10))
