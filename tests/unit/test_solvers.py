import numpy as np
import pytest
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bench.solvers import cones  # the benchmark's membership-like problem
from multiscale_camera.core.field import (
    ISOLATED_VALUE,
    apply_laplacian,
    explicit_diffusion,
    isolated_voxels,
    solve_membership,
    solvers,
)


def laplacian_matrix(shape):
    """7-point graph Laplacian with zero-flux faces, C order, as a sparse matrix."""

    def path(n):
        if n == 1:
            return sp.csr_matrix((1, 1))
        d = np.full(n, 2.0)
        d[[0, -1]] -= 1
        return sp.diags([d, -np.ones(n - 1), -np.ones(n - 1)], [0, 1, -1])

    eye = [sp.identity(n) for n in shape]
    return (
        sp.kron(path(shape[0]), sp.kron(eye[1], eye[2]))
        + sp.kron(eye[0], sp.kron(path(shape[1]), eye[2]))
        + sp.kron(eye[0], sp.kron(eye[1], path(shape[2])))
    ).tocsr()


def direct_solve(values, constrained):
    """The gold answer: spsolve of A_FF x_F = -A_FC x_C."""
    lap = laplacian_matrix(values.shape)
    fixed = constrained.ravel()
    x = np.where(constrained, values, 0.0).ravel()
    x[~fixed] = spla.spsolve(lap[~fixed][:, ~fixed].tocsc(), -lap[~fixed][:, fixed] @ x[fixed])
    return x.reshape(values.shape)


def relative_residual(x, values, constrained):
    lap = laplacian_matrix(values.shape)
    free = ~constrained.ravel()
    b = -lap[free][:, ~free] @ values.ravel()[~free]
    return np.linalg.norm(b - lap[free][:, free] @ x.ravel()[free]) / np.linalg.norm(b)


def slabs(shape, axis=0):
    """Planar slabs valued 1, 2, 3 across ``axis``, as the membership problem has."""
    values = np.zeros(shape)
    constrained = np.zeros(shape, bool)
    n = shape[axis]
    for value, start, stop in ((1, 0, 0.15), (2, 0.45, 0.55), (3, 0.85, 1.0)):
        idx = [slice(None)] * 3
        idx[axis] = slice(int(start * n), max(int(stop * n), int(start * n) + 1))
        constrained[tuple(idx)] = True
        values[tuple(idx)] = value
    return values, constrained


def random_problem(shape, density, seed):
    rng = np.random.default_rng(seed)
    constrained = rng.random(shape) < density
    return rng.integers(1, 4, shape).astype(float), constrained


PROBLEMS = [
    ((12, 9, 7), "random"),
    ((17, 16, 15), "random"),
    ((33, 20, 25), "random"),
    ((12, 9, 7), "slabs"),
    ((17, 16, 15), "slabs"),
    ((33, 20, 25), "slabs"),
]


@pytest.mark.parametrize("shape, kind", PROBLEMS)
def test_matches_direct_sparse_solve(shape, kind):
    if kind == "random":
        values, constrained = random_problem(shape, 0.05, seed=sum(shape))
    else:
        values, constrained = slabs(shape, axis=shape.index(max(shape)))
    gold = direct_solve(values, constrained)
    for dtype in (np.float32, np.float64):
        got = solve_membership(values, constrained, dtype=dtype)
        assert got.converged and got.residuals[-1] < 1e-6
        assert got.x.dtype == dtype and got.x.shape == shape
        assert (got.x[constrained] == values[constrained].astype(dtype)).all()
        assert np.abs(got.x - gold).max() < 1e-4
    assert relative_residual(got.x, values, constrained) < 1e-6  # float64, true residual


def test_iterations_do_not_grow_with_the_grid():
    iterations = {n: solve_membership(*cones(n)).iterations for n in (16, 32, 64, 96)}
    # Measured: 7 at every size (V(1,1) cycles took 11 -> 13 over the same sizes).
    assert max(iterations.values()) <= 9, iterations
    assert iterations[96] <= iterations[16] + 1, iterations


def test_ill_conditioned_problem_still_has_a_true_residual():
    # One constrained voxel: the answer is that value everywhere, and b is tiny, so a
    # float32 residual recurrence would drift; the float64 recurrence must not.
    values = np.full((40, 30, 20), 2.5)
    constrained = np.zeros(values.shape, bool)
    constrained[3, 4, 5] = True
    got = solve_membership(values, constrained)
    assert got.converged
    assert np.abs(got.x - 2.5).max() < 1e-5


def test_no_constraint_gives_the_isolated_value_everywhere():
    shape = (6, 5, 4)
    values = np.full(shape, np.nan)
    constrained = np.zeros(shape, bool)
    assert isolated_voxels(constrained).all()
    solved = solve_membership(values, constrained)
    for result in (solved, explicit_diffusion(values, constrained, 5)):
        assert result.converged and not np.isnan(result.x).any()
        assert (result.x == ISOLATED_VALUE).all()


def test_enclosed_pocket_is_not_isolated_and_free_values_are_ignored():
    shape = (14, 12, 10)
    values = np.full(shape, np.nan)  # only constrained voxels are read
    constrained = np.zeros(shape, bool)
    constrained[3:10, 3:9, 2:8] = True
    constrained[4:9, 4:8, 3:7] = False  # a free pocket inside a constrained shell
    values[constrained] = 2.0
    values[0, 0, 0], constrained[0, 0, 0] = 1.0, True
    assert not isolated_voxels(constrained).any()
    got = solve_membership(values, constrained, dtype=np.float64)
    assert got.converged and not np.isnan(got.x).any()
    np.testing.assert_allclose(got.x[4:9, 4:8, 3:7], 2.0, atol=1e-5)
    np.testing.assert_allclose(got.x, direct_solve(np.nan_to_num(values), constrained), atol=1e-5)


@pytest.mark.parametrize("density", [0.0, 0.3, 0.6, 0.9, 1.0])
def test_isolated_voxels_match_a_connected_components_pass(density):
    constrained = np.random.default_rng(7).random((9, 8, 7)) < density
    labels, count = ndi.label(~constrained)  # 6-connectivity
    touching = np.unique(labels[ndi.binary_dilation(constrained) & ~constrained])
    expected = (labels > 0) & ~np.isin(labels, touching)
    assert (isolated_voxels(constrained) == expected).all()


def test_rejects_bad_input():
    with pytest.raises(ValueError):
        solve_membership(np.full((3, 3, 3), np.nan), np.ones((3, 3, 3), bool))
    with pytest.raises(ValueError):
        solve_membership(np.zeros((3, 3, 3)), np.ones((3, 3, 2), bool))
    with pytest.raises(ValueError):
        explicit_diffusion(np.zeros((3, 3, 3)), np.ones((3, 3, 3), bool), 1, rate=0.2)


def test_warm_start_from_the_answer_needs_no_iteration():
    values, constrained = slabs((20, 11, 9))
    first = solve_membership(values, constrained, tol=1e-9, dtype=np.float64)
    again = solve_membership(values, constrained, x0=first.x, tol=1e-8)
    assert again.converged and again.iterations == 0


def test_explicit_diffusion_converges_to_the_same_answer_but_far_slower():
    values, constrained = slabs((10, 9, 8), axis=0)
    gold = direct_solve(values, constrained)
    pcg = solve_membership(values, constrained)
    pcg_error = np.abs(pcg.x - gold).max()
    same_budget = explicit_diffusion(values, constrained, pcg.iterations)
    assert np.abs(same_budget.x - gold).max() > 1000 * pcg_error
    long_run = explicit_diffusion(values, constrained, 600, dtype=np.float64)
    assert np.abs(long_run.x - gold).max() < 1e-4
    assert (long_run.x[constrained] == values[constrained]).all()
    # A residual every RESIDUAL_EVERY steps, decreasing.
    assert len(long_run.residuals) == 600 // solvers.RESIDUAL_EVERY
    assert long_run.residuals[-1] < long_run.residuals[0]


def test_laplacian_is_symmetric_with_zero_flux_faces():
    rng = np.random.default_rng(3)
    u, v = rng.normal(size=(2, 7, 6, 5))
    assert np.isclose((apply_laplacian(u) * v).sum(), (u * apply_laplacian(v)).sum())
    assert np.allclose(apply_laplacian(np.ones((7, 6, 5))), 0)
    np.testing.assert_allclose(apply_laplacian(u).ravel(), laplacian_matrix(u.shape) @ u.ravel())


@pytest.mark.parametrize("n, m", [(8, 4), (9, 5), (1, 1), (2, 1)])
def test_restriction_is_the_transpose_of_prolongation(n, m):
    rng = np.random.default_rng(n)
    for axis in range(3):
        coarse_shape = [3, 4, 2]
        coarse_shape[axis] = m
        fine_shape = list(coarse_shape)
        fine_shape[axis] = n
        e, r = rng.normal(size=coarse_shape), rng.normal(size=fine_shape)
        lhs = (solvers._prolong_axis(e, axis, n) * r).sum()
        assert np.isclose(lhs, (e * solvers._restrict_axis(r, axis, m)).sum())


@pytest.fixture
def deep_hierarchy(monkeypatch):
    """A multigrid hierarchy of four levels on a small odd-sized grid."""
    monkeypatch.setattr(solvers, "COARSEST_CELLS", 8)
    constrained = cones(11)[1][:, :10, :9]
    h = solvers._Hierarchy(~constrained, np.float64)
    assert len(h.levels) >= 4
    return h, ~constrained


def test_preconditioner_is_symmetric(deep_hierarchy):
    h, free = deep_hierarchy
    rng = np.random.default_rng(5)
    u, v = rng.normal(size=(2, *free.shape)) * free
    mu, mv = h.precondition(u), h.precondition(v)
    assert np.isclose((mu * v).sum(), (u * mv).sum(), rtol=1e-12)
    h32 = solvers._Hierarchy(free, np.float32)
    u32, v32 = u.astype(np.float32), v.astype(np.float32)
    lhs = float((h32.precondition(u32).astype(float) * v).sum())
    assert np.isclose(lhs, float((u * h32.precondition(v32)).sum()), rtol=1e-5)


def test_preconditioner_is_positive_definite_and_never_overshoots(deep_hierarchy):
    h, free = deep_hierarchy
    idx = np.flatnonzero(free)
    basis = np.zeros((len(idx), *free.shape))
    basis.reshape(len(idx), -1)[np.arange(len(idx)), idx] = 1.0
    b = np.array([h.precondition(e).ravel()[idx] for e in basis])
    a = laplacian_matrix(free.shape)[idx][:, idx].toarray()
    np.testing.assert_allclose(b, b.T, atol=1e-12)
    # Eigenvalues of B A: in (0, 1] means B is SPD and each cycle reduces every error.
    chol = np.linalg.cholesky(a)
    w = np.linalg.eigvalsh(chol.T @ b @ chol)
    assert w.min() > 0.1 and w.max() < 1 + 1e-9


def test_a_stop_request_ends_a_solve_between_iterations():
    """Esc during a large level's solve waited for the whole solve (up to 4 s at HIGH):
    the solve asks before every iteration."""
    from multiscale_camera.core.errors import Cancelled

    values, constrained = cones(32)
    asked = []

    def stop_on_third():
        asked.append(1)
        return len(asked) >= 3

    with pytest.raises(Cancelled):
        solve_membership(values, constrained, should_stop=stop_on_third)
    assert len(asked) == 3
    full = solve_membership(values, constrained, should_stop=lambda: False)
    assert full.converged and full.iterations > 3


@pytest.mark.parametrize("n", [1, 5, 31, 32, 33, 152, 300])
def test_spd_inverse_matches_a_sparse_lu_solve(n):
    """The coarsest grid's inverse, written without LAPACK (``spd_inverse``), against
    scipy's sparse LU on the same restricted Laplacian, blocks not a multiple of the
    elimination's included."""
    shape = (1, 17, 30) if n > 64 else (1, 8, 8)
    rng = np.random.default_rng(n)
    cells = int(np.prod(shape))
    free = np.sort(rng.choice(cells, n, replace=False))
    a = laplacian_matrix(shape).tocsc()[free][:, free] + sp.identity(n) * 0.05
    expected = spla.splu(a.tocsc()).solve(np.eye(n))
    got = solvers.spd_inverse(a.toarray())
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_spd_inverse_rejects_a_matrix_that_is_not_positive_definite():
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        solvers.spd_inverse(np.array([[1.0, 2.0], [2.0, 1.0]]))
