import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fixtures.masks import disk_masks
from fixtures.rigs import demo_rig
from multiscale_camera.core.errors import RigError
from multiscale_camera.core.field import harmonic, mask_weights
from multiscale_camera.core.runtime import runtime


def dense_reference(masks):
    """Harmonic interpolation by a direct sparse solve of the 4-neighbour Laplacian."""
    n, h, w = masks.shape
    size = h * w
    idx = np.arange(size).reshape(h, w)
    rows, cols = [], []
    for a, b in ((idx[:, 1:], idx[:, :-1]), (idx[1:, :], idx[:-1, :])):
        rows += [a.ravel(), b.ravel()]
        cols += [b.ravel(), a.ravel()]
    adj = sp.csr_matrix(
        (np.ones(sum(len(r) for r in rows)), (np.concatenate(rows), np.concatenate(cols))),
        (size, size),
    )
    lap = sp.diags(np.asarray(adj.sum(1)).ravel()) - adj
    fixed = masks.any(0).ravel()
    free = ~fixed
    values = masks.reshape(n, -1).astype(float)
    out = values.copy()
    a = lap[free][:, free].tocsc()
    for i in range(n):
        rhs = -lap[free][:, fixed] @ values[i, fixed]
        out[i, free] = spla.spsolve(a, rhs)
    return out.reshape(n, h, w)


@pytest.mark.parametrize("shape", [(20, 30), (45, 70), (97, 130)])
def test_mask_weights_match_direct_solve(shape):
    h, w = shape
    masks = disk_masks(w, h, 0.15 * w, 0.35 * w)
    masks = np.concatenate([masks, np.zeros((1, h, w), bool)])
    masks[2, : h // 6, : w // 6] = True
    masks[0] &= ~masks[2]
    got = mask_weights(masks, tol=1e-8)
    assert got.converged
    np.testing.assert_allclose(got.x, dense_reference(masks), atol=2e-5)
    np.testing.assert_allclose(got.x.sum(0), 1.0, atol=1e-5)


def test_mask_weights_one_hot_inside_masks():
    masks = disk_masks(80, 60, 10, 25)
    x = mask_weights(masks).x
    assert (x[0][masks[0]] == 1).all() and (x[1][masks[0]] == 0).all()
    assert (x[1][masks[1]] == 1).all()


def test_empty_masks_raise():
    with pytest.raises(RigError, match="Every mask is empty"):
        mask_weights(np.zeros((2, 5, 5), bool))


@pytest.mark.parametrize("shape", [(45, 70), (97, 130)])
def test_last_weight_is_one_minus_the_solved_ones_within_tolerance(shape):
    """Only N - 1 weights are solved; the last is 1 minus them. At the default tolerance
    every weight, the last included, stays within 1e-4 of the direct solve."""
    h, w = shape
    masks = disk_masks(w, h, 0.15 * w, 0.35 * w)
    got = mask_weights(masks)
    ref = dense_reference(masks)
    assert got.converged
    np.testing.assert_allclose(got.x, ref, atol=1e-4)
    np.testing.assert_allclose(got.x.sum(0), 1.0, atol=1e-6)
    assert (got.x[1][masks[1]] == 1).all() and (got.x[1][masks[0]] == 0).all()


def test_weights_started_from_the_coarse_solve_match_the_direct_solve():
    """The demo's three ring masks at 240x135: every solve starts from the coarse one
    (``coarse_start``), and the weights still lie within 1e-4 of the direct solve."""
    _cams, masks = demo_rig(240, 135)
    owned = masks.any(0)
    start = harmonic.coarse_start(masks[0], owned)
    assert start is not None and start.shape == (135, 240, 1)
    ref = dense_reference(masks)
    # the start alone is not the answer: the full solve moves it
    assert np.abs(start[..., 0] - ref[0]).max() > 1e-3
    got = mask_weights(masks)
    assert got.converged
    np.testing.assert_allclose(got.x, ref, atol=1e-4)


def test_weights_solved_in_workers_are_the_bits_solved_here(monkeypatch):
    """The demo's three masks at 240x135 with the size threshold lowered: the two solves
    run at once in worker processes, and the weights are those solved in this process,
    bit for bit (the fold map and the rays depend on them)."""
    _cams, masks = demo_rig(240, 135)
    here = mask_weights(masks, processes=1)
    monkeypatch.setattr(harmonic, "SHARED_MIN_PIXELS", 1)
    with runtime().journal() as runs:
        shared = mask_weights(masks, processes=2)
    assert [run.where for run in runs] and all(pid > 0 for pid in runs[0].where)
    assert shared.iterations == here.iterations
    assert np.array_equal(shared.x.view(np.uint32), here.x.view(np.uint32))


def test_weights_solved_on_the_free_pixels_box_match_the_whole_image_solve():
    """The solves run on the box around the free pixels (``free_box``): where camera 1
    keeps the frame's edges (a ring), and a free pixel touches the frame (a notch), the
    weights are the whole image's direct solve's."""
    h, w = 60, 90
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(yy - 30, xx - 45)
    masks = np.stack([r > 25, r < 8])
    masks[0, 25:35, 70:] = False  # free pixels reaching the right edge
    free = ~masks.any(axis=0)
    rows, cols = harmonic.free_box(masks.any(axis=0))
    ys, xs = np.nonzero(free)
    assert (rows.start, rows.stop) == (ys.min() - 1, ys.max() + 2)
    assert (cols.start, cols.stop) == (xs.min() - 1, w)
    assert rows.start > 0 and rows.stop < h and cols.start > 0
    got = mask_weights(masks).x
    np.testing.assert_allclose(got, dense_reference(masks), atol=2e-5)
    assert harmonic.free_box(np.ones((4, 5), dtype=bool)) is None
    full = np.ones((2, 4, 5), dtype=bool)
    full[1] = False
    np.testing.assert_array_equal(mask_weights(full).x, full.astype(np.float32))
