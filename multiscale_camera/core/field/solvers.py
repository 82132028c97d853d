"""Membership field solve: smooth the constraint field M into N (paper, eq. 4 and 5).

N minimises sum |grad N|^2 over a voxel grid with N = M on the constrained voxels (the
hard-constraint limit of eq. 5): the discrete Laplace equation, 7-point stencil, unit
spacing, zero-flux box faces. On the free voxels F, with the constrained ones C fixed,

    A_FF x_F = b,    b = -A_FC x_C,

where A is the graph Laplacian of the grid, (A u)_p = sum_{q ~ p} (u_p - u_q).

``solve_membership`` runs conjugate gradients preconditioned by one geometric multigrid
cycle (a W(2,2)-cycle): 2x2x2 coarsening in which a coarse cell is constrained when any
of its children is, cell-centred trilinear prolongation and its transpose as
restriction, red-black Gauss-Seidel smoothing mirrored before and after the coarse
correction, and a dense solve on the coarsest grid. The cycle is a fixed symmetric
positive definite operator, so PCG applies, and the iteration count stays flat as the
grid grows (7-8 from 16^3 to 256^3 on membership-like constraints).
``explicit_diffusion`` is the paper's explicit iteration, kept as the reference the
solver is benchmarked against.
"""

from dataclasses import dataclass

import numpy as np

from ..diagnostics import check_stop

# Stop at this relative residual ||b - A x|| / ||b||: N then errs by ~1e-5 (values
# 1..N), far below what bends a ray visibly.
TOLERANCE = 1e-6
# PCG needs 7-13 iterations at any grid size; 100 leaves room for awkward constraint sets.
MAX_ITERATIONS = 100
# Symmetric red-black Gauss-Seidel sweeps before and after each coarse correction, and
# visits to the coarser level per cycle (2: a W-cycle, which costs 4/3 of a V-cycle in
# 3D). Measured on cone-shaped constraints: V(1,1) needed 11-13 PCG iterations from 32^3
# to 128^3, growing; W(2,2) 7 at every size, in less time.
SWEEPS = 2
COARSE_VISITS = 2
# Coarsest grid's cell count: its free cells are solved densely (at most a 512 x 512
# inverse, ``spd_inverse``).
COARSEST_CELLS = 512
# Value given to isolated voxels. They exist only when no voxel is constrained (see
# ``isolated_voxels``), so there is no constraint mean to take: 0 is eq. 4's "no camera".
ISOLATED_VALUE = 0.0
# explicit_diffusion records its residual every this many steps: a record costs about
# one step, so recording every step would inflate the reference method's timings.
RESIDUAL_EVERY = 10
# Largest stable explicit rate: the Laplacian's eigenvalues lie below 12 (degree <= 6).
MAX_RATE = 1.0 / 6.0


@dataclass(frozen=True)
class SolveResult:
    """Outcome of an iterative solve.

    Attributes
    ----------
    x : ndarray, the solution.
    converged : bool
    iterations : int
    residuals : tuple of float, relative residual after each iteration.
    """

    x: np.ndarray
    converged: bool
    iterations: int
    residuals: tuple


def apply_laplacian(u):
    """The 7-point graph Laplacian with zero-flux faces: (A u)_p = sum_{q ~ p} (u_p - u_q).

    Parameters
    ----------
    u : (nx, ny, nz) float array.

    Returns
    -------
    (nx, ny, nz) array of u's dtype; A is symmetric positive semi-definite, A 1 = 0.
    """
    u = np.asarray(u)
    return _degree(u.shape, u.dtype) * u - _neighbour_sum(u)


def isolated_voxels(constrained):
    """Free voxels that no path of free voxels (6-neighbour steps) links to a constraint.

    Such voxels make the Laplace system singular. In a single box they are all the
    voxels when none is constrained, and none otherwise: a connected set of free voxels
    that is not the whole box has a neighbour outside itself, which can only be a
    constrained voxel. So no connected-components pass is needed.

    Parameters
    ----------
    constrained : (nx, ny, nz) bool array.

    Returns
    -------
    (nx, ny, nz) bool array; ``solve_membership`` sets these voxels to ISOLATED_VALUE.
    """
    constrained = np.asarray(constrained, dtype=bool)
    return np.full(constrained.shape, not constrained.any())


def solve_membership(
    values,
    constrained,
    tol=TOLERANCE,
    max_iterations=MAX_ITERATIONS,
    x0=None,
    dtype=np.float32,
    should_stop=None,
):
    """Smooth the constraint field M into the membership field N (eq. 5, hard constraints).

    Solves A_FF x_F = b (module docstring) by multigrid-preconditioned conjugate
    gradients. The iterate and the residual are kept in float64, so the stopping test
    can be trusted below float32's resolution; the preconditioner and the search
    directions use ``dtype``.

    Parameters
    ----------
    values : (nx, ny, nz) float array, M: read on the constrained voxels only (finite
        there), membership units (camera numbers 1..N).
    constrained : (nx, ny, nz) bool array, voxels where N = M exactly.
    tol : float, stop when ||b - A_FF x_F|| / ||b|| < tol (2-norms over the free
        voxels, b the right-hand side from the constraints, i.e. the residual of x_F = 0).
    max_iterations : int, PCG iterations before giving up (``converged`` False).
    x0 : (nx, ny, nz) float array or None, initial guess on the free voxels (default 0,
        eq. 4's value off the rays).
    dtype : numpy float dtype of the returned field and of the working arrays.
    should_stop : callable () -> bool or None, asked before every iteration (one takes
        up to half a second on a large grid).

    Returns
    -------
    SolveResult whose ``x`` is (nx, ny, nz) ``dtype``: ``values`` on the constrained
    voxels, the solution elsewhere, ISOLATED_VALUE everywhere when nothing is
    constrained (``isolated_voxels``); never NaN. ``iterations`` counts PCG iterations
    and ``residuals`` holds the relative residual after each (empty when none was run).

    Raises
    ------
    ValueError if the shapes differ, the grid is not 3D, or a constrained value is not
    finite. Cancelled when ``should_stop`` says so.
    """
    values, constrained, dtype = _check(values, constrained, dtype)
    x = np.where(constrained, values, 0.0)
    if not constrained.any():
        return SolveResult(np.full(x.shape, ISOLATED_VALUE, dtype), True, 0, ())
    free = ~constrained
    if x0 is not None:
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.shape != x.shape:
            raise ValueError(f"x0 has shape {x0.shape}, the grid {x.shape}")
        x[free] = np.nan_to_num(x0[free])
    b = _neighbour_sum(x * constrained) * free
    b_norm = np.sqrt(_dot(b, b))
    if not free.any() or b_norm == 0.0:
        # No unknowns, or every constraint next to a free voxel is 0: x_F = 0 is exact.
        x[free] = 0.0
        return SolveResult(x.astype(dtype), True, 0, ())

    hierarchy = _Hierarchy(free, dtype)
    check_stop(should_stop)
    fine = hierarchy.levels[0]
    work = np.empty(x.shape)  # float64 scratch for the outer products A p
    r = b if x0 is None else fine.apply(-x, work=work)  # b - A_FF x_F = -(A x)_F
    del b
    history = []
    if np.sqrt(_dot(r, r)) / b_norm < tol:
        return SolveResult(x.astype(dtype), True, 0, ())
    z = hierarchy.precondition(r.astype(dtype))
    p = z.astype(np.float64)
    ap = np.empty_like(p)
    rz = _dot(r, z)
    for it in range(1, max_iterations + 1):
        check_stop(should_stop)
        fine.apply(p, out=ap, work=work)
        pap = _dot(p, ap)
        if not pap > 0.0:
            break  # p vanished: r is at float64's floor.
        alpha = rz / pap
        x += alpha * p
        r -= alpha * ap
        rel = np.sqrt(_dot(r, r)) / b_norm
        if rel < tol:
            # Confirm with the true residual, so `converged` never rests on drift.
            r = fine.apply(-x, work=work)
            rel = np.sqrt(_dot(r, r)) / b_norm
        history.append(float(rel))
        if rel < tol:
            return SolveResult(x.astype(dtype), True, it, tuple(history))
        z_old = z
        z = hierarchy.precondition(r.astype(dtype))
        rz_new = _dot(r, z)
        # Polak-Ribiere beta (flexible CG): robust to the preconditioner's rounding.
        beta = (rz_new - _dot(r, z_old)) / rz
        p *= beta
        p += z
        rz = rz_new
    return SolveResult(x.astype(dtype), False, len(history), tuple(history))


def explicit_diffusion(values, constrained, iterations, rate=MAX_RATE, x0=None, dtype=np.float32):
    """The paper's explicit smoothing: N <- N - rate * A N on the free voxels.

    Constrained voxels keep their values (the reset after every step), faces are
    zero-flux. With rate 1/6 an interior voxel becomes the mean of its six neighbours
    (Jacobi). Converges to ``solve_membership``'s answer, but needs O(n^2) steps on an
    n^3 grid; kept as the reference for tests and benchmarks. In float32 it stalls once
    a step's change drops below half a unit in the last place (errors of ~1e-4 on a
    64^3 grid): use float64 to follow it further.

    Parameters
    ----------
    values : (nx, ny, nz) float array, M, read on the constrained voxels (finite there).
    constrained : (nx, ny, nz) bool array.
    iterations : int, number of steps, all run.
    rate : float in (0, 1/6], the step size.
    x0 : (nx, ny, nz) float array or None, the starting field on the free voxels
        (default 0, eq. 4).
    dtype : numpy float dtype of the field.

    Returns
    -------
    SolveResult whose ``x`` is (nx, ny, nz) ``dtype``. ``residuals`` holds the relative
    residual ||b - A_FF x_F|| / ||b|| after every RESIDUAL_EVERY-th step and after the
    last: ``residuals[j]`` belongs to the field after min((j + 1) * RESIDUAL_EVERY,
    iterations) steps. ``converged`` says whether the last one is below TOLERANCE.
    Nothing constrained: every voxel is ISOLATED_VALUE.
    """
    values, constrained, dtype = _check(values, constrained, dtype)
    if not 0.0 < rate <= MAX_RATE:
        raise ValueError(f"rate must lie in (0, 1/6] for a stable explicit step, got {rate}")
    iterations = int(iterations)
    if not constrained.any():
        return SolveResult(np.full(values.shape, ISOLATED_VALUE, dtype), True, 0, ())
    free = ~constrained
    x = np.where(constrained, values, 0.0)
    if x0 is not None:
        x[free] = np.nan_to_num(np.asarray(x0, dtype=np.float64)[free])
    x = x.astype(dtype)
    b = _neighbour_sum(np.where(constrained, x, 0)) * free
    b_norm = np.sqrt(_dot(b, b)) or 1.0
    del b
    # x <- keep * x + gain * (neighbour sum): the step with the constraints untouched.
    gain = (rate * free).astype(dtype)
    keep = (1.0 - rate * free * _degree(x.shape, np.float64)).astype(dtype)
    t = np.empty_like(x)
    history = []
    for k in range(1, iterations + 1):
        _neighbour_sum(x, out=t)
        t *= gain
        x *= keep
        x += t
        if k % RESIDUAL_EVERY == 0 or k == iterations:
            r = apply_laplacian(x)
            r *= free
            history.append(float(np.sqrt(_dot(r, r)) / b_norm))
    converged = bool(history) and history[-1] < TOLERANCE
    return SolveResult(x, converged, iterations, tuple(history))


# --- grid kernels --------------------------------------------------------------------


def _check(values, constrained, dtype):
    values = np.asarray(values, dtype=np.float64)
    constrained = np.asarray(constrained, dtype=bool)
    if values.ndim != 3 or values.shape != constrained.shape:
        raise ValueError(
            f"values {values.shape} and constrained {constrained.shape} must be one 3D shape"
        )
    if not np.isfinite(values[constrained]).all():
        raise ValueError("constrained values must be finite")
    return values, constrained, np.dtype(dtype)


def _dot(a, b):
    """Inner product accumulated in float64, whatever the inputs' dtype (einsum, not
    BLAS: see the note on BLAS threads in ``core/runtime``)."""
    if a.dtype == b.dtype == np.float64:
        return float(np.einsum("i,i->", a.ravel(), b.ravel()))
    return float(np.add.reduce((a * b).ravel(), dtype=np.float64))


def _neighbour_sum(u, out=None, plus=None):
    """sum_{q ~ p} u_q over the in-box 6-neighbours of every voxel, plus ``plus`` if
    given (one pass fewer than adding it afterwards)."""
    if out is None:
        out = np.empty_like(u)
    if plus is None:
        out[:-1] = u[1:]
        out[-1] = 0
    else:
        np.add(plus[:-1], u[1:], out=out[:-1])
        out[-1] = plus[-1]
    out[1:] += u[:-1]
    out[:, :-1] += u[:, 1:]
    out[:, 1:] += u[:, :-1]
    out[:, :, :-1] += u[:, :, 1:]
    out[:, :, 1:] += u[:, :, :-1]
    return out


def _degree(shape, dtype):
    """Number of in-box 6-neighbours per voxel, (nx, ny, nz) ``dtype``."""
    deg = np.zeros(shape, dtype)
    for axis, n in enumerate(shape):
        if n > 1:
            count = np.full(n, 2, dtype)
            count[[0, -1]] = 1
            deg += count.reshape([-1 if a == axis else 1 for a in range(3)])
    return deg


def _along(axis, s):
    return (slice(None),) * axis + (s,)


def _prolong_axis(e, axis, n):
    """Cell-centred linear interpolation doubling ``axis`` (then cropped to n); the
    ghost cell beyond a face copies the face cell (zero flux)."""
    m = e.shape[axis]
    lo, hi = e[_along(axis, slice(None, -1))], e[_along(axis, slice(1, None))]
    even = 0.75 * e
    even[_along(axis, slice(1, None))] += 0.25 * lo
    even[_along(axis, slice(0, 1))] += 0.25 * e[_along(axis, slice(0, 1))]
    odd = 0.75 * e
    odd[_along(axis, slice(None, -1))] += 0.25 * hi
    odd[_along(axis, slice(-1, None))] += 0.25 * e[_along(axis, slice(-1, None))]
    out = np.stack([even, odd], axis=axis + 1)
    shape = list(e.shape)
    shape[axis] = 2 * m
    return out.reshape(shape)[_along(axis, slice(0, n))]


def _restrict_axis(r, axis, m):
    """The exact transpose of ``_prolong_axis``: fine ``axis`` of length n -> m."""
    n = r.shape[axis]
    if n < 2 * m:
        pad = [(0, 0)] * r.ndim
        pad[axis] = (0, 2 * m - n)
        r = np.pad(r, pad)
    r0, r1 = r[_along(axis, slice(0, None, 2))], r[_along(axis, slice(1, None, 2))]
    out = r0 + r1
    out *= 0.75
    out[_along(axis, slice(None, -1))] += 0.25 * r0[_along(axis, slice(1, None))]
    out[_along(axis, slice(1, None))] += 0.25 * r1[_along(axis, slice(None, -1))]
    out[_along(axis, slice(0, 1))] += 0.25 * r0[_along(axis, slice(0, 1))]
    out[_along(axis, slice(-1, None))] += 0.25 * r1[_along(axis, slice(-1, None))]
    return out


RED, BLACK = 0, 1  # cells with i + j + k even, odd


class _Level:
    """One grid of the hierarchy: A = s * (graph Laplacian on the free cells), with the
    constant s folded into the restriction (``scale``) so every level uses the plain
    stencil."""

    def __init__(self, free, dtype):
        self.shape = free.shape
        self.free = free
        self.free_f = free.astype(dtype)
        i, j, k = np.indices(self.shape, sparse=True)
        red = ((i + j + k) % 2 == 0) & free
        self.degree = _degree(self.shape, dtype)
        inv_degree = self.free_f / self.degree
        # Per colour (RED, BLACK): 1/degree on its free cells, and 1 off them. Arithmetic
        # masks: np.copyto(..., where=) measured several times slower on large grids.
        self.inv_degree = (inv_degree * red, inv_degree * (free & ~red))
        self.keep = ((~red).astype(dtype), (red | ~free).astype(dtype))
        self.buffer = np.empty(self.shape, dtype)
        self.axes = ()  # axes halved to reach the next level
        self.scale = 1.0  # Galerkin-consistent ratio of the next level's stencil to this one's

    def apply(self, v, out=None, work=None):
        """(A v) on the free cells, 0 on the constrained ones: A_FF v when v is 0 on
        the constrained cells. ``out`` and the scratch ``work`` (v's dtype) are optional."""
        out = np.multiply(self.degree, v, out=out)
        out -= _neighbour_sum(v, out=self.buffer if work is None else work)
        out *= self.free_f
        return out

    def sweep(self, e, r, colour):
        """One Gauss-Seidel half-sweep over the free cells of ``colour``, in place:
        e_p <- (r_p + sum_{q ~ p} e_q) / degree_p."""
        t = _neighbour_sum(e, out=self.buffer, plus=r)
        t *= self.inv_degree[colour]
        e *= self.keep[colour]
        e += t

    def coarsen(self):
        """Halve every axis longer than one cell; a coarse cell is constrained when any
        child is (so constraints survive coarsening and no coarse block floats free)."""
        self.axes = tuple(a for a, n in enumerate(self.shape) if n > 1)
        fixed = ~self.free
        for axis in self.axes:
            n = fixed.shape[axis]
            if n % 2:
                pad = [(0, 0)] * 3
                pad[axis] = (0, 1)
                fixed = np.pad(fixed, pad)  # the extra half cell is free
            fixed = fixed[_along(axis, slice(0, None, 2))] | fixed[_along(axis, slice(1, None, 2))]
        # Galerkin with this P scales the stencil by prod(c) / c^2, c = 2 on halved axes.
        self.scale = 2.0 ** len(self.axes) / 4.0
        return ~fixed

    def restrict(self, r, coarse_shape):
        for axis in self.axes:
            r = _restrict_axis(r, axis, coarse_shape[axis])
        return r

    def prolong(self, e):
        for axis in reversed(self.axes):
            e = _prolong_axis(e, axis, self.shape[axis])
        return e


class _Hierarchy:
    """The multigrid preconditioner: levels from the fine grid down to COARSEST_CELLS."""

    def __init__(self, free, dtype):
        self.dtype = dtype
        self.levels = [_Level(free, dtype)]
        while self.levels[-1].free.size > COARSEST_CELLS and max(self.levels[-1].shape) > 1:
            coarse_free = self.levels[-1].coarsen()
            if not coarse_free.any():
                self.levels[-1].axes = ()
                break  # every coarse cell constrained: no coarse correction to make
            self.levels.append(_Level(coarse_free, dtype))
        last = self.levels[-1]
        self.dense = None
        if last.free.size <= COARSEST_CELLS:
            idx = np.flatnonzero(last.free)
            lap = _dense_laplacian(last.shape)[np.ix_(idx, idx)]
            inv = spd_inverse(lap)
            self.dense = (idx, 0.5 * (inv + inv.T))

    def precondition(self, r):
        """One symmetric cycle from a zero guess: (nx, ny, nz) ``dtype`` -> same."""
        return self._cycle(0, r)

    def _cycle(self, index, r):
        level = self.levels[index]
        if index == len(self.levels) - 1 and self.dense is not None:
            idx, inv = self.dense
            e = np.zeros(level.shape, self.dtype)
            # einsum, not BLAS (``@`` wakes its threads: see ``spd_inverse``)
            e.flat[idx] = np.einsum("ij,j->i", inv, r.flat[idx].astype(np.float64))
            return e
        # Pre-smoothing, red then black; the first red half-sweep starts from e = 0.
        e = r * level.inv_degree[RED]
        level.sweep(e, r, BLACK)
        for _ in range(SWEEPS - 1):
            level.sweep(e, r, RED)
            level.sweep(e, r, BLACK)
        if level.axes:
            coarse = self.levels[index + 1]
            rc = level.restrict(r - level.apply(e), coarse.shape)
            rc *= coarse.free_f / level.scale
            ec = self._cycle(index + 1, rc)
            for _ in range(COARSE_VISITS - 1):
                ec += self._cycle(index + 1, rc - coarse.apply(ec))
            e += level.prolong(ec) * level.free_f
        # Post-smoothing in mirrored order (black then red), so the cycle is symmetric.
        for _ in range(SWEEPS):
            level.sweep(e, r, BLACK)
            level.sweep(e, r, RED)
        return e


# Columns ``spd_inverse`` eliminates at a time: its updates are einsum products of this
# rank (16 to 64 took within 10% of each other at 510 unknowns).
INVERSE_BLOCK = 32


def spd_inverse(a):
    """The inverse of a symmetric positive definite matrix, by Gauss-Jordan elimination
    in blocks of ``INVERSE_BLOCK`` columns without pivoting (every pivot block of an SPD
    matrix is SPD), its products by ``einsum``.

    ``np.linalg.inv`` would do it faster but wakes OpenBLAS's threads, at every size (a
    3 x 3 inverse too), and they spin on the other cores for a while after each call:
    the coarsest grid's inverse, made for every solve, kept a second core busy through
    the whole mask-weights solve (2.0 CPU s beside a 3.0 s solve at 1920x1080, 0.17 beside
    0.17 s at 480x270), the core the fold count's worker needs (see the note on BLAS
    threads in ``core/runtime``). 152 unknowns (the mask weights' coarsest grid) take
    about 3 ms, 510 about 40 ms.

    a : (n, n) float array, SPD. Returns (n, n) float64.

    Raises
    ------
    np.linalg.LinAlgError where a pivot is not positive (``a`` not positive definite).
    """
    m = np.array(a, dtype=np.float64)
    n = len(m)
    for k0 in range(0, n, INVERSE_BLOCK):
        block = slice(k0, min(n, k0 + INVERSE_BLOCK))
        pivot = _pivot_inverse(m[block, block])
        col = m[:, block].copy()
        col[block] = 0.0
        row = np.einsum("ij,jk->ik", pivot, m[block])
        m -= np.einsum("ij,jk->ik", col, row)
        m[block] = row
        m[:, block] = -np.einsum("ij,jk->ik", col, pivot)
        m[block, block] = pivot
    return m


def _pivot_inverse(a):
    """``spd_inverse`` of a small block, a column at a time: (b, b) -> (b, b) float64."""
    m = np.array(a, dtype=np.float64)
    for k in range(len(m)):
        if not m[k, k] > 0.0:
            raise np.linalg.LinAlgError("matrix is not positive definite")
        piv = 1.0 / m[k, k]
        row = m[k] * piv
        row[k] = piv
        col = m[:, k].copy()
        col[k] = 0.0
        m -= np.multiply.outer(col, row)
        m[k] = row
        m[:, k] = -col * piv
        m[k, k] = piv
    return m


def _dense_laplacian(shape):
    """(n, n) float64 graph Laplacian of a small grid, C order."""
    n = int(np.prod(shape))
    idx = np.arange(n).reshape(shape)
    lap = np.diag(_degree(shape, np.float64).ravel())
    for axis in range(3):
        a = idx[_along(axis, slice(1, None))].ravel()
        b = idx[_along(axis, slice(None, -1))].ravel()
        lap[a, b] = -1.0
        lap[b, a] = -1.0
    return lap
