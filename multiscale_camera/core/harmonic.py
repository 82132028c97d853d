"""Harmonic interpolation of masks over the image (the IMAGE_BLEND weights).

Pixels inside camera i's mask have weight 1 for i and 0 for the others; pixels that no
mask owns get the harmonic interpolation (discrete Laplace equation, 4-neighbourhood,
zero-flux image borders). The weights of every pixel sum to one.

The solve is cascadic: conjugate gradients on a coarse copy of the image, then on each
finer level starting from the upsampled coarser answer, so the finest level needs only
a few dozen iterations whatever the image size.
"""

from dataclasses import dataclass

import numpy as np

from .errors import RigError, SolverDidNotConverge

# Stop the finest level at this relative residual: weights then err by ~1e-5,
# far below what moves a ray by a visible amount.
TOLERANCE = 1e-6
# Coarsest level's longest side, pixels: small enough that CG there is instant.
COARSEST = 48
MAX_ITERATIONS = 4000


@dataclass(frozen=True)
class SolveResult:
    """Outcome of an iterative solve.

    Attributes
    ----------
    x : ndarray, the solution.
    converged : bool
    iterations : int, at the finest level.
    residuals : tuple of float, relative residual after each finest-level iteration.
    """

    x: np.ndarray
    converged: bool
    iterations: int
    residuals: tuple


def apply_laplacian(u):
    """The negative graph Laplacian with zero-flux borders: (A u)_p = sum_q (u_p - u_q).

    Parameters
    ----------
    u : (C, H, W) float array.

    Returns
    -------
    (C, H, W) float array, symmetric positive semi-definite in u.
    """
    out = np.zeros_like(u)
    dx = u[:, :, 1:] - u[:, :, :-1]
    dy = u[:, 1:, :] - u[:, :-1, :]
    out[:, :, 1:] += dx
    out[:, :, :-1] -= dx
    out[:, 1:, :] += dy
    out[:, :-1, :] -= dy
    return out


def _degree(h, w):
    deg = np.full((h, w), 4.0)
    deg[0, :] -= 1
    deg[-1, :] -= 1
    deg[:, 0] -= 1
    deg[:, -1] -= 1
    return deg


def conjugate_gradient(fixed, x0, tol=TOLERANCE, max_iterations=MAX_ITERATIONS):
    """Solve A x = 0 on the free pixels with x given on the ``fixed`` ones.

    Jacobi-preconditioned CG, one independent system per channel, vectorised.

    Parameters
    ----------
    fixed : (H, W) bool array, pixels whose values in ``x0`` are kept.
    x0 : (C, H, W) float64 array, boundary values and the initial guess.
    tol : float, stop when every channel's residual norm over its right-hand side norm
        falls below it.

    Returns
    -------
    SolveResult with ``x`` of shape (C, H, W).
    """
    free = ~fixed
    x = x0.copy()
    r = -apply_laplacian(x) * free
    minv = free / _degree(*fixed.shape)
    scale = np.sqrt((r * r).sum(axis=(1, 2)))
    scale = np.where(scale > 0, scale, 1.0)
    z = r * minv
    d = z.copy()
    rz = (r * z).sum(axis=(1, 2))
    history = []
    for it in range(1, max_iterations + 1):
        ad = apply_laplacian(d) * free
        dad = (d * ad).sum(axis=(1, 2))
        alpha = np.divide(rz, dad, out=np.zeros_like(rz), where=dad > 0)
        x += alpha[:, None, None] * d
        r -= alpha[:, None, None] * ad
        rel = float((np.sqrt((r * r).sum(axis=(1, 2))) / scale).max())
        history.append(rel)
        if rel < tol:
            return SolveResult(x, True, it, tuple(history))
        z = r * minv
        rz_new = (r * z).sum(axis=(1, 2))
        beta = np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0)
        d = z + beta[:, None, None] * d
        rz = rz_new
    return SolveResult(x, False, max_iterations, tuple(history))


def _downsample(owner):
    """Halve an owner map (-1 = free): a coarse pixel takes the owner of any of its
    children, the highest camera index winning, so thin masks survive coarsening."""
    h, w = owner.shape
    padded = np.full((h + h % 2, w + w % 2), -1, dtype=owner.dtype)
    padded[:h, :w] = owner
    return padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2).max(axis=(1, 3))


def _upsample(x, shape):
    """Bilinear upsampling of (C, h, w) to (C, *shape), pixel centres aligned."""
    c, h, w = x.shape
    ys = np.clip((np.arange(shape[0]) + 0.5) * (h / shape[0]) - 0.5, 0, h - 1)
    xs = np.clip((np.arange(shape[1]) + 0.5) * (w / shape[1]) - 0.5, 0, w - 1)
    y0 = np.minimum(ys.astype(int), h - 2) if h > 1 else np.zeros(len(ys), int)
    x0 = np.minimum(xs.astype(int), w - 2) if w > 1 else np.zeros(len(xs), int)
    fy = (ys - y0)[:, None] if h > 1 else np.zeros((len(ys), 1))
    fx = (xs - x0)[None, :] if w > 1 else np.zeros((1, len(xs)))
    y1 = np.minimum(y0 + 1, h - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    top = x[:, y0][:, :, x0] * (1 - fx) + x[:, y0][:, :, x1] * fx
    bottom = x[:, y1][:, :, x0] * (1 - fx) + x[:, y1][:, :, x1] * fx
    return top * (1 - fy) + bottom * fy


def _one_hot(owner, n):
    return (owner[None] == np.arange(n)[:, None, None]).astype(np.float64)


def mask_weights(masks, tol=TOLERANCE):
    """Per-pixel camera weights: one-hot in the masks, harmonic in between.

    Parameters
    ----------
    masks : (N, H, W) bool array, at most one True per pixel, at least one True overall.
    tol : float, relative residual of the finest solve.

    Returns
    -------
    SolveResult whose ``x`` is (N, H, W) float32, each pixel's weights summing to one.

    Raises
    ------
    RigError if every mask is empty; SolverDidNotConverge if the finest solve stalls.
    """
    masks = np.asarray(masks, dtype=bool)
    n, h, w = masks.shape
    if not masks.any():
        raise RigError("Every mask is empty: paint white where each camera's view should be kept")
    owner = np.where(masks.any(axis=0), masks.argmax(axis=0), -1)
    if (owner >= 0).all():
        return SolveResult(_one_hot(owner, n).astype(np.float32), True, 0, ())
    levels = [owner]
    while max(levels[-1].shape) > COARSEST:
        levels.append(_downsample(levels[-1]))
    x = None
    for level in reversed(levels):
        fixed = level >= 0
        guess = np.full((n, *level.shape), 1.0 / n) if x is None else _upsample(x, level.shape)
        guess = np.where(fixed[None], _one_hot(level, n), guess)
        coarse = level is not owner
        result = conjugate_gradient(fixed, guess, tol=1e-3 if coarse else tol)
        x = result.x
    if not result.converged:
        raise SolverDidNotConverge(
            f"Mask weights did not converge: relative residual {result.residuals[-1]:.2e} "
            f"after {result.iterations} iterations"
        )
    x = np.clip(x, 0.0, 1.0)
    x /= x.sum(axis=0, keepdims=True)
    return SolveResult(x.astype(np.float32), True, result.iterations, result.residuals)
