"""Small dense linear algebra of the bending-plane filters in numpy: Cholesky factors with a
documented jitter, the square root of a prior covariance, the inverse of a few symmetric
positive-definite matrices (the grid filter's and the filters' set-up; the per-frame
arithmetic is compiled in :mod:`tracker.estimators.linalg_kernels`, with the same jitter).

For one matrix LAPACK is called directly: numpy's stacked wrappers cost ten times the
arithmetic on matrices of a few rows.
"""

from __future__ import annotations

import math

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


__all__ = [
    "COVARIANCE_JITTER",
    "COVARIANCE_JITTER_FLOOR",
    "CovarianceError",
    "cholesky",
    "sigma_sqrt",
    "spd_inverse",
]
