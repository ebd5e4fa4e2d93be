"""Small dense linear algebra of the bending-plane filters: Cholesky factors with a documented
jitter, and solves of a few symmetric positive-definite systems.

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
            return x[None], np.array([2.0 * np.log(np.diagonal(c)).sum()]), np.ones(1, bool)
    x = np.zeros_like(rhs)
    logdet = np.full(r, np.nan)
    ok = np.zeros(r, dtype=bool)
    for i in range(r) if r <= 2 else ():
        # A few matrices: LAPACK directly (numpy's stacked wrappers cost ten times the work).
        c, xi, info = lapack.dposv(S[i], rhs[i], lower=1)
        if info == 0:
            x[i], logdet[i], ok[i] = xi, 2.0 * np.log(np.diagonal(c)).sum(), True
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


__all__ = [
    "COVARIANCE_JITTER",
    "COVARIANCE_JITTER_FLOOR",
    "CovarianceError",
    "block_index",
    "cholesky",
    "sigma_sqrt",
    "spd_inverse",
    "spd_solve",
]
