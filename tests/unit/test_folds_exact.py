"""The fast fold counter (``quad_folds``, every quad at every size) against the slow
reference it replaced (``fold_reference``, written out there as it was): the same map,
quad for quad, on rigs that fold, rigs that do not and randomly perturbed lattices."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fixtures.rigs import three_camera_rig, turned_rig, zoom1000_rig
from multiscale_camera.core.field import mask_weights
from multiscale_camera.core.geometry import Rig, dot3
from multiscale_camera.core.methods import prepare, prepare_image_blend, settings_for
from multiscale_camera.core.quality import bending_active, fold_map, quad_folds
from multiscale_camera.core.quality import folds as folds_module

from .fold_reference import reference_quad_folds


def lattice(fld, xs, ys):
    """The rays of pixels ``ys`` x ``xs`` of a field and their bending stretch, as
    ``fold_map`` hands them to ``quad_folds``: (Hy, Wx, K, 3) and (Hy, Wx, K)."""
    iy, ix = np.meshgrid(ys, xs, indexing="ij")
    verts = fld.rays(ix.ravel(), iy.ravel()).vertices.reshape(len(ys), len(xs), -1, 3)
    exit_index = fld.exit_index(ix.ravel(), iy.ravel())
    counts = None if exit_index is None else (exit_index + 1).reshape(len(ys), len(xs))
    cams = fld.rig.cameras
    return verts, bending_active(verts, cams[-1], counts, cams[:-1])


def walked(monkeypatch):
    """A list that grows by the number of sections each ``_walk`` call walks."""
    seen, walk = [], folds_module._walk

    def spy(rays, q, plane, where, point, alive):
        seen.append(len(where[0]))
        return walk(rays, q, plane, where, point, alive)

    monkeypatch.setattr(folds_module, "_walk", spy)
    return seen


def test_dot_planes_gives_the_bits_of_dot3():
    rng = np.random.default_rng(7)
    for n in (1, 5, 33, 10_000):
        a = rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-8, 8, size=(n, 1))
        b = rng.normal(size=(n, 3))
        planes = folds_module.dot_planes(a.T.copy(), b.T.copy())
        np.testing.assert_array_equal(planes, dot3(a, b))


def test_segment_search_counts_the_vertices_at_or_before_each_length():
    """The walk's start: a binary search over each polyline's arc lengths, against the
    count written out, on polylines with zero-length segments (ties), lengths before
    the first vertex and past the last, and K from 2 to 40."""
    rng = np.random.default_rng(11)
    for k in (2, 3, 7, 40):
        steps = rng.uniform(0.0, 1.0, size=(300, k - 1)) * (rng.random((300, k - 1)) > 0.3)
        cum = np.concatenate([np.zeros((300, 1)), np.cumsum(steps, axis=1)], axis=1)
        length = rng.uniform(-1.0, 1.2, size=(300, 5)) * cum[:, -1:]
        length[:, 0] = cum[np.arange(300), rng.integers(0, k, 300)]  # on a vertex
        expected = np.empty(length.shape, dtype=int)
        for p in range(300):
            for m in range(5):
                want = min(max(length[p, m], 0.0), cum[p, -1])
                at_or_before = sum(1 for c in cum[p] if c <= want)
                expected[p, m] = min(max(at_or_before - 1, 0), k - 2)
        np.testing.assert_array_equal(folds_module._segment_at(cum, length), expected)


def test_linear_rays_fold_where_the_reference_says():
    cams, masks = three_camera_rig(96, 54)
    fld = prepare(Rig(cams, masks), "LINEAR", settings_for("STANDARD"))
    verts, active = lattice(fld, np.arange(96), np.arange(54))
    fast = quad_folds(verts, active)
    expected = reference_quad_folds(verts, active)
    assert expected.sum() > 20, expected.sum()  # LINEAR folds where the nearest pixel jumps
    np.testing.assert_array_equal(fast, expected)
    np.testing.assert_array_equal(fold_map(fld)[0], expected)


def test_turned_rig_folds_where_the_reference_says():
    cams, masks = turned_rig(96, 54)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    verts, active = lattice(fld, np.arange(96), np.arange(54))
    expected = reference_quad_folds(verts, active)
    assert expected.sum() > 20, expected.sum()  # true folds (docs/performance.md)
    np.testing.assert_array_equal(quad_folds(verts, active), expected)


def test_image_blend_on_the_1000x_rig_folds_nowhere_as_in_the_reference():
    cams, masks = zoom1000_rig(120, 68)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    verts, active = lattice(fld, np.arange(120), np.arange(68))
    fast = quad_folds(verts, active)
    np.testing.assert_array_equal(fast, reference_quad_folds(verts, active))
    assert not fast.any()


def test_quad_folds_takes_lattices_in_any_memory_layout():
    """The windows are read as rays one after the other in memory: vertices and
    activity handed over as views (a transposed stack, every other column) give the map
    that contiguous copies give, and the reference's."""
    cams, masks = turned_rig(96, 54)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    verts, active = lattice(fld, np.arange(0, 96, 2), np.arange(54))
    expected = reference_quad_folds(verts, active)
    assert expected.any()
    held = np.moveaxis(np.ascontiguousarray(np.moveaxis(verts, -1, 0)), 0, -1)  # (3, ...) below
    wide = np.repeat(active, 2, axis=1)[:, ::2]  # every other column of a wider array
    assert not held.flags.c_contiguous and not wide.flags.c_contiguous
    np.testing.assert_array_equal(quad_folds(held, wide), expected)


def test_fold_map_counts_the_folds_only_odd_offset_quads_show():
    """Above a megapixel the count checked every other pixel: a quad on odd rows or
    columns was never looked at. With IMAGE_BLEND's weights un-eased, the three-camera
    rig at 480x270 folds 11 quads in strips one pixel wide; the lattice of every other
    pixel sees 2 coarse quads fold, which hold 2 of the 11: 9 were missed."""
    w, h = 480, 270
    cams, masks = three_camera_rig(w, h)
    fld = prepare_image_blend(Rig(cams, masks))
    fld.weights = mask_weights(masks).x.astype(np.float32)  # the weights that fold
    full, stride = fold_map(fld, processes=1)
    assert stride == 1
    verts, active = lattice(fld, np.arange(w), np.arange(h))
    np.testing.assert_array_equal(full, reference_quad_folds(verts, active))
    assert full.shape == (h - 1, w - 1) and full.sum() == 11
    xs, ys = np.arange(0, w, 2), np.arange(0, h, 2)
    coarse = reference_quad_folds(*lattice(fld, xs, ys))
    fy, fx = np.nonzero(full)
    seen = coarse[np.minimum(fy // 2, len(ys) - 2), np.minimum(fx // 2, len(xs) - 2)]
    assert coarse.sum() == 2 and seen.sum() == 2


@pytest.mark.slow
def test_fold_map_checks_every_quad_above_a_megapixel():
    w, h = 1280, 820
    cams, masks = turned_rig(w, h)
    fld = prepare(Rig(cams, masks), "IMAGE_BLEND", settings_for("STANDARD"))
    full, stride = fold_map(fld, processes=1)
    assert stride == 1 and full.shape == (h - 1, w - 1)
    rows = np.arange(400, 412)
    expected = reference_quad_folds(*lattice(fld, np.arange(w), rows))
    assert expected.any()
    np.testing.assert_array_equal(full[rows[:-1]], expected)


def perturbed(seed, k, noise, back, single):
    """Pinhole rays through a small lattice with vertices at uneven, sometimes repeated
    or receding depths, bent sideways and jittered, with stretches that end early:
    (Hy, Wx, K, 3) vertices, (Hy, Wx, K) active."""
    rng = np.random.default_rng(seed)
    hy, wx = rng.integers(2, 7, size=2)
    ys, xs = np.meshgrid(np.arange(hy) - hy / 2, np.arange(wx) - wx / 2, indexing="ij")
    direction = np.stack([0.1 * xs, 0.1 * ys, np.ones_like(xs)], axis=-1)
    steps = rng.uniform(-back, 1.0, size=(hy, wx, k)) * (rng.random((hy, wx, k)) > 0.1)
    depth = 1.0 + np.cumsum(steps, axis=-1)
    verts = direction[:, :, None, :] * depth[..., None]
    verts[..., 0] += 0.05 * np.sin(depth * rng.uniform(0.0, 3.0))
    verts += rng.normal(scale=noise, size=verts.shape)
    if single:
        verts = verts.astype(np.float32)
    return verts, np.arange(k) < rng.integers(1, k + 1, size=(hy, wx, 1))


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    k=st.integers(2, 12),
    noise=st.sampled_from([0.0, 1e-3, 0.05, 0.4]),
    back=st.sampled_from([0.0, 0.3]),
    single=st.booleans(),
)
def test_fast_counter_equals_the_reference_on_perturbed_lattices(seed, k, noise, back, single):
    verts, active = perturbed(seed, k, noise, back, single)
    np.testing.assert_array_equal(quad_folds(verts, active), reference_quad_folds(verts, active))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(2, 12), share=st.sampled_from([0.3, 0.8]))
def test_fast_counter_equals_the_reference_where_the_active_stretch_has_holes(seed, k, share):
    """Sections past ray a's last active vertex are skipped (``folds._live_sections``):
    with holes in the stretch that is its last active vertex, not its active count."""
    verts, _ = perturbed(seed, k, 0.05, 0.3, False)
    active = np.random.default_rng(seed).random(verts.shape[:3]) < share
    np.testing.assert_array_equal(quad_folds(verts, active), reference_quad_folds(verts, active))


def test_perturbed_lattices_fold_and_walk(monkeypatch):
    """The lattices above hold what the comparison must cover: folded quads, flat ones,
    and sections the fast path leaves to the walk (several steps, rays doubling back)."""
    seen = walked(monkeypatch)
    maps = [quad_folds(*perturbed(seed, 9, 0.05, 0.3, False)) for seed in range(20)]
    assert sum(m.sum() for m in maps) > 0 and sum((~m).sum() for m in maps) > 0
    assert sum(seen) > 20, seen


@pytest.mark.parametrize("rig, method", [(turned_rig, "IMAGE_BLEND"), (three_camera_rig, "LINEAR")])
def test_windows_stacked_into_rectangles_give_the_row_windows_map(monkeypatch, rig, method):
    """Rows' windows stacked into rectangles (``folds._rectangles``) give the map each
    row's windows give alone, with per-quad limits in runs of every kind (0: not
    checked, a few sections, all of them) that shift from row to row, as the kept
    quads' limits do along a mask's edge."""
    cams, masks = rig(96, 54)
    fld = prepare(Rig(cams, masks), method, settings_for("STANDARD"))
    verts, active = lattice(fld, np.arange(96), np.arange(54))
    planes = np.moveaxis(verts, -1, 0).astype(np.float64, order="C")
    k = verts.shape[2]
    rng = np.random.default_rng(5)
    limit = np.zeros((53, 95), dtype=np.int16)
    for r in range(53):
        cuts = np.sort(rng.choice(np.arange(1, 95), 4, replace=False))
        for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [95]])):
            limit[r, a:b] = rng.choice([0, 3, 10, k])
    rects = folds_module._rectangles(np.minimum(limit, k), 95, folds_module.CHUNK_SECTIONS // k)
    # rows are stacked, windows of one rectangle starting at different columns
    assert max(len(rect[3]) for rect in rects) > 1
    assert any(len({c0 for _r, c0, _c1 in rect[3]}) > 1 for rect in rects)
    stacked = folds_module.quad_folds_on_planes(planes, active, limit)

    def row_by_row(lim, cols, _budget):
        return [
            (c0, c1, kmax, [(r, c0, c1)])
            for r in range(lim.shape[0])
            for c0, c1, kmax in folds_module._row_windows(lim[r], cols)
        ]

    monkeypatch.setattr(folds_module, "_rectangles", row_by_row)
    alone = folds_module.quad_folds_on_planes(planes, active, limit)
    assert alone.any() and (limit[alone] > 0).all()
    np.testing.assert_array_equal(stacked, alone)
