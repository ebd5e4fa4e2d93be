"""Small dense linear algebra compiled for the filters' kernels (numba): Cholesky factors
with the documented jitter of :mod:`tracker.estimators._linalg`, their solves, Gaussian
elimination with partial pivoting, the std cap of a covariance and the angle wrap. Matrices
of a few rows, written as plain loops (LAPACK's operations in the same order for these
sizes: results equal to rounding)."""

from __future__ import annotations

import math

import numba

# As tracker.estimators._linalg (the same documented jitter).
_JITTER = 1e-9
_JITTER_FLOOR = 1e-15
_TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, nogil=True)
def _wrap(angle):
    return (angle + math.pi) % _TWO_PI - math.pi


@numba.njit(cache=True, nogil=True)
def _cholesky_into(A, L):
    """Lower Cholesky factor of A (m, m) into L; False if A is not positive definite."""
    m = A.shape[0]
    for j in range(m):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, m):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@numba.njit(cache=True, nogil=True)
def _cholesky_jittered(A, L, work):
    """:func:`_cholesky_into`, retried once on the symmetrised A with the documented jitter
    (``_JITTER`` times the mean variance, at least ``_JITTER_FLOOR``); False if both fail or
    A is not finite."""
    m = A.shape[0]
    for i in range(m):
        for j in range(m):
            if not math.isfinite(A[i, j]):
                return False
    if _cholesky_into(A, L):
        return True
    trace = 0.0
    for i in range(m):
        for j in range(m):
            work[i, j] = 0.5 * (A[i, j] + A[j, i])
        trace += work[i, i]
    jitter = max(_JITTER * max(trace / m, 0.0), _JITTER_FLOOR)
    for i in range(m):
        work[i, i] += jitter
    return _cholesky_into(work, L)


@numba.njit(cache=True, nogil=True)
def _solve_lower(L, b):
    """Solve L L^T x = b in place (L lower, b (m,))."""
    m = L.shape[0]
    for i in range(m):
        t = b[i]
        for k in range(i):
            t -= L[i, k] * b[k]
        b[i] = t / L[i, i]
    for i in range(m - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, m):
            t -= L[k, i] * b[k]
        b[i] = t / L[i, i]


@numba.njit(cache=True, nogil=True)
def _cap_row(P, max_variance):
    """Scale row and column 0 of P (n, n) so that its delta_L variance is at most
    ``max_variance`` (the correlations kept), in place; whether it was capped."""
    if not P[0, 0] > max_variance:
        return False
    n = P.shape[0]
    f = math.sqrt(max_variance / P[0, 0])
    for c in range(n):
        P[0, c] *= f
    for c in range(n):
        P[c, 0] *= f
    return True


@numba.njit(cache=True, nogil=True)
def _lu_solve(A, b, work):
    """Solve A x = b in place (b (m,) or (m, k)) by Gaussian elimination with partial
    pivoting on a copy ``work`` of A; log |det A| (-inf if singular)."""
    m = A.shape[0]
    for i in range(m):
        for j in range(m):
            work[i, j] = A[i, j]
    logdet = 0.0
    for col in range(m):
        pivot = col
        for i in range(col + 1, m):
            if abs(work[i, col]) > abs(work[pivot, col]):
                pivot = i
        if work[pivot, col] == 0.0:
            return -math.inf
        if pivot != col:
            for j in range(m):
                work[col, j], work[pivot, j] = work[pivot, j], work[col, j]
            for j in range(b.shape[1]):
                b[col, j], b[pivot, j] = b[pivot, j], b[col, j]
        logdet += math.log(abs(work[col, col]))
        for i in range(col + 1, m):
            f = work[i, col] / work[col, col]
            for j in range(col, m):
                work[i, j] -= f * work[col, j]
            for j in range(b.shape[1]):
                b[i, j] -= f * b[col, j]
    for col in range(m - 1, -1, -1):
        for j in range(b.shape[1]):
            t = b[col, j]
            for k in range(col + 1, m):
                t -= work[col, k] * b[k, j]
            b[col, j] = t / work[col, col]
    return logdet


