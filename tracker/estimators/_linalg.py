"""Small dense linear algebra of the bending-plane filters: Cholesky factors with a documented
jitter, sigma points, and solves of a few symmetric positive-definite systems (whole, or
their diagonal blocks: the per-group gates).

For one or two matrices LAPACK is called directly: numpy's stacked wrappers cost ten times
the arithmetic on matrices of a few rows, which is what the live filter (a bank of one,
:mod:`tracker.estimators.ukf_core`) factorises every frame.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.linalg import lapack

Array = np.ndarray

# Relative jitter added (times the mean variance) before a second Cholesky attempt.
COVARIANCE_JITTER = 1e-9
# Absolute floor of that jitter, rad^2 (or the squared measurement unit).
COVARIANCE_JITTER_FLOOR = 1e-15


class CovarianceError(np.linalg.LinAlgError):
    """A covariance stayed non-positive-definite after symmetrisation and jitter."""


def _jittered(A: Array) -> Array:
    A = 0.5 * (A + np.swapaxes(A, -1, -2))
    scale = np.maximum(np.trace(A, axis1=-2, axis2=-1) / A.shape[-1], 0.0)
    jitter = np.maximum(COVARIANCE_JITTER * scale, COVARIANCE_JITTER_FLOOR)
    return A + jitter[..., None, None] * np.eye(A.shape[-1])


def cholesky(A: Array) -> tuple[Array, Array]:
    """Lower Cholesky factors of a stack (..., m, m) and which succeeded (retried once with
    the documented jitter, ``COVARIANCE_JITTER`` times the mean variance)."""
    lead = A.shape[:-2]
    if A.ndim == 3 and A.shape[0] == 1:
        # One matrix: LAPACK directly (numpy's stacked wrappers cost ten times the work).
        c, info = lapack.dpotrf(A[0], lower=1, clean=1)
        if info == 0:
            return c[None], np.ones(1, dtype=bool)
    else:
        try:
            return np.linalg.cholesky(A), np.ones(lead, dtype=bool)
        except np.linalg.LinAlgError:
            pass
    flat = A.reshape((-1,) + A.shape[-2:])
    L = np.zeros_like(flat)
    ok = np.zeros(flat.shape[0], dtype=bool)
    for i in np.flatnonzero(np.isfinite(flat).all(axis=(-2, -1))):
        for attempt in (flat[i], _jittered(flat[i])):
            try:
                L[i] = np.linalg.cholesky(attempt)
                ok[i] = True
                break
            except np.linalg.LinAlgError:
                continue
    return L.reshape(A.shape), ok.reshape(lead)


def sigma_sqrt(A: Array) -> Array:
    """Upper-triangular square root U (U^T U = A) of one matrix, with the documented jitter.

    Raises CovarianceError (a LinAlgError) when ``A`` is not positive definite even after it.
    """
    A = np.asarray(A, dtype=float)
    if A.shape == (1, 1):
        a = float(A[0, 0])
        if not math.isfinite(a) or a < -COVARIANCE_JITTER_FLOOR:
            raise CovarianceError(f"variance {a} is not a variance")
        return np.array([[math.sqrt(max(a, COVARIANCE_JITTER_FLOOR))]])
    L, ok = cholesky(A)
    if not ok:
        raise CovarianceError("covariance is not positive definite, even after jitter")
    return L.T


def spd_inverse(A: Array) -> Array:
    """Inverse of symmetric positive-definite matrices (..., m, m) by Cholesky solves."""
    L, ok = cholesky(np.asarray(A, dtype=float))
    if not np.all(ok):
        raise CovarianceError("covariance could not be inverted")
    inverse = np.linalg.solve(L, np.broadcast_to(np.eye(L.shape[-1]), L.shape))
    return np.swapaxes(inverse, -1, -2) @ inverse


@lru_cache(maxsize=64)
def block_index(G: int, d: int) -> Array:
    """Flat indices of the G diagonal d x d blocks of a (G d, G d) matrix, block-major."""
    m = G * d
    g, i, j = np.meshgrid(np.arange(G), np.arange(d), np.arange(d), indexing="ij")
    return ((g * d + i) * m + g * d + j).ravel()


def spd_solve(S: Array, rhs: Array) -> tuple[Array, Array, Array]:
    """Solutions of ``S x = rhs`` for symmetric positive-definite S (r, m, m), rhs (r, m, k),
    by Cholesky; log det S; which S were positive definite (others: zeros, NaN)."""
    r = S.shape[0]
    if r == 1:
        c, x, info = lapack.dposv(S[0], rhs[0], lower=1)
        if info == 0:
            # A handful of positive numbers: their logs in Python floats (the same values).
            logdet = 2.0 * sum(map(math.log, c.diagonal().tolist()))
            return x[None], np.array([logdet]), np.ones(1, bool)
    x = np.zeros_like(rhs)
    logdet = np.full(r, np.nan)
    ok = np.zeros(r, dtype=bool)
    for i in range(r) if r <= 2 else ():
        # A few matrices: LAPACK directly (numpy's stacked wrappers cost ten times the work).
        c, xi, info = lapack.dposv(S[i], rhs[i], lower=1)
        if info == 0:
            x[i], logdet[i], ok[i] = xi, 2.0 * np.log(c.diagonal()).sum(), True
    if r > 2:
        L, ok = cholesky(S)
        x = np.where(
            ok[:, None, None],
            np.linalg.solve(np.where(ok[:, None, None], S, np.eye(S.shape[-1])), rhs),
            0.0,
        )
        logdet = np.where(ok, 2.0 * np.sum(np.log(np.abs(np.diagonal(L, axis1=-2, axis2=-1))),
                                           -1), np.nan)  # fmt: skip
    return x, logdet, ok


@lru_cache(maxsize=8)
def _sigma_offsets(n: int) -> Array:
    """[0; I; -I], (2n + 1, n): the sigma points are x + offsets @ U (exact)."""
    return np.concatenate([np.zeros((1, n)), np.eye(n), -np.eye(n)])


def sigma_points(
    x: Array, P: Array, spread: float, factor: Array | None = None
) -> tuple[Array, Array, Array]:
    """van der Merwe's sigma points ``x``, ``x +- rows of sqrt(spread P)`` of stacks x (r, n),
    P (r, n, n): the points (r, 2n + 1, n), their offsets from x and which P factorised.

    ``factor``: P's lower Cholesky factors when already known (then ``sqrt(spread) L``: one
    factorisation for the predict's check and the update). An angle in x is left unwrapped
    (the filters' models are periodic in it); the offsets are the wrapped residuals while
    they stay within pi.
    """
    n = x.shape[-1]
    if factor is not None:
        offsets = _sigma_offsets(n) @ (math.sqrt(spread) * factor.mT)
        return x[:, None] + offsets, offsets, np.ones(x.shape[0], dtype=bool)
    A = spread * P
    if n == 1:
        a = A[:, 0, 0]
        ok = np.isfinite(a) & (a >= -COVARIANCE_JITTER_FLOOR)
        U = np.sqrt(np.where(ok, np.maximum(a, COVARIANCE_JITTER_FLOOR), 1.0))[:, None, None]
    elif np.isfinite(A).all():
        L, ok = cholesky(A)
        U = L.mT
    else:
        finite = np.isfinite(A.reshape(A.shape[0], -1)).all(1)
        L, ok = cholesky(np.where(finite[:, None, None], A, np.eye(n)))
        ok &= finite
        U = L.mT
    offsets = _sigma_offsets(n) @ U
    return x[:, None] + offsets, offsets, ok


@lru_cache(maxsize=64)
def _block_mask(G: int, d: int) -> Array:
    """1 on the G diagonal d x d blocks of a (G d, G d) matrix, 0 elsewhere."""
    return np.kron(np.eye(G), np.ones((d, d)))


def diagonal_blocks(S: Array, G: int, d: int) -> Array:
    """The G diagonal d x d blocks of matrices S (r, G d, G d): (r, G, d, d)."""
    r = S.shape[0]
    return S.reshape(r, -1)[:, block_index(G, d)].reshape(r, G, d, d)


def block_mahalanobis(S: Array, v: Array, G: int, d: int) -> Array:
    """``v_g^T S_g^-1 v_g`` of the G parts v_g (d each) of vectors v (r, G d) under the
    diagonal blocks S_g of matrices S (r, G d, G d): (r, G)."""
    r = S.shape[0]
    if r == 1:
        # One LAPACK solve with the block-diagonal part of S: its Cholesky factor is the
        # blocks' own, so its solution is every block's.
        _, x, info = lapack.dposv(S[0] * _block_mask(G, d), v[0], lower=1)
        if info == 0:
            return (v[0] * x).reshape(1, G, d).sum(-1)
    v_g = v.reshape(r, G, d)
    return (v_g * np.linalg.solve(diagonal_blocks(S, G, d), v_g[..., None])[..., 0]).sum(-1)


__all__ = [
    "COVARIANCE_JITTER",
    "COVARIANCE_JITTER_FLOOR",
    "CovarianceError",
    "block_index",
    "block_mahalanobis",
    "cholesky",
    "diagonal_blocks",
    "sigma_points",
    "sigma_sqrt",
    "spd_inverse",
    "spd_solve",
]
