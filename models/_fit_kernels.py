"""One frame's rotation fit and its noise's information, compiled (numba).

The per-frame estimators fit one rotation about z every frame (:mod:`models.rotation_fit`)
from a few vectors and invert a few 3 x 3 covariances (:mod:`models.bounds`): arithmetic on
a dozen numbers, which numpy's calls (or Python's float operations) cost many times over.
These kernels are those single-problem paths, step for step: the same Cholesky steps, Gram
coefficients, stationary candidates (the unit-circle roots of the quartic, as LAPACK's
eigenvalues of its companion matrix), Newton iterations and choice of the minimum.
Compiled once on a machine and cached next to this file.
"""

from __future__ import annotations

import cmath
import functools
import math

import numba
import numpy as np

# Status of information_blocks.
INFORMATION_OK = 0
NOT_FINITE = 1
NOT_POSITIVE_DEFINITE = 2


@numba.njit(cache=True, nogil=True)
def information_blocks(cov):
    """Inverses of 3 x 3 covariances (k, 3, 3): symmetrise, Cholesky factor L, then
    ``L^-T L^-1``. Returns ``(status, information (k, 3, 3))``: :data:`NOT_FINITE` or
    :data:`NOT_POSITIVE_DEFINITE` at the first block that is (the rest unfilled)."""
    k = cov.shape[0]
    out = np.zeros((k, 3, 3))
    for n in range(k):
        A = cov[n]
        for a in range(3):
            for b in range(3):
                if not math.isfinite(A[a, b]):
                    return NOT_FINITE, out
        s10 = 0.5 * (A[1, 0] + A[0, 1])
        s20 = 0.5 * (A[2, 0] + A[0, 2])
        s21 = 0.5 * (A[2, 1] + A[1, 2])
        if not A[0, 0] > 0.0:
            return NOT_POSITIVE_DEFINITE, out
        l00 = math.sqrt(A[0, 0])
        l10, l20 = s10 / l00, s20 / l00
        pivot = A[1, 1] - l10 * l10
        if not pivot > 0.0:
            return NOT_POSITIVE_DEFINITE, out
        l11 = math.sqrt(pivot)
        l21 = (s21 - l20 * l10) / l11
        pivot = A[2, 2] - l20 * l20 - l21 * l21
        if not pivot > 0.0:
            return NOT_POSITIVE_DEFINITE, out
        l22 = math.sqrt(pivot)
        # M = L^-1 (lower triangular), information = M^T M.
        m00, m11, m22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
        m10 = -l10 * m00 / l11
        m21 = -l21 * m11 / l22
        m20 = -(l20 * m00 + l21 * m10) / l22
        w01 = m10 * m11 + m20 * m21
        w02 = m20 * m22
        w12 = m21 * m22
        out[n, 0, 0] = m00 * m00 + m10 * m10 + m20 * m20
        out[n, 0, 1] = out[n, 1, 0] = w01
        out[n, 0, 2] = out[n, 2, 0] = w02
        out[n, 1, 1] = m11 * m11 + m21 * m21
        out[n, 1, 2] = out[n, 2, 1] = w12
        out[n, 2, 2] = m22 * m22
    return INFORMATION_OK, out


@numba.njit(cache=True, nogil=True, inline="always")
def _newton(phi, a1, b1, a2, b2, steps):
    """Newton steps on f'(phi) = 0 towards a minimum; stops at a fixed point (no step, or
    one that leaves phi as it is), from where every further step would repeat it."""
    for _ in range(steps):
        s1, c1, s2, c2 = math.sin(phi), math.cos(phi), math.sin(2 * phi), math.cos(2 * phi)
        d1 = -a1 * s1 + b1 * c1
        d1 += -2 * a2 * s2 + 2 * b2 * c2
        d2 = -a1 * c1 - b1 * s1
        d2 += -4 * a2 * c2 - 4 * b2 * s2
        if not d2 > 0:
            break
        stepped = phi - d1 / d2
        if stepped == phi:
            break
        phi = stepped
    return phi


@numba.njit(cache=True, nogil=True, inline="always")
def _cost(phi, k, a1, b1, a2, b2):
    return (
        k
        + a1 * math.cos(phi)
        + b1 * math.sin(phi)
        + a2 * math.cos(2 * phi)
        + b2 * math.sin(2 * phi)
    )


@numba.njit(cache=True, nogil=True)
def _candidates(a1, b1, a2, b2):
    """The stationary angles of ``a1 cos + b1 sin + a2 cos 2 + b2 sin 2``: the phases of the
    quartic's roots, then the Procrustes angle (alone when the quadratic terms vanish)."""
    lead, half = complex(b2, a2), 0.5 * complex(b1, a1)
    scale = max(abs(lead), abs(half))
    procrustes = math.atan2(-b1, -a1)
    if not abs(lead) > 1e-12 * (scale if scale > 0 else 1.0):
        return np.array([procrustes])
    # The coefficients are (lead, half, 0, conj(half), conj(lead)).
    companion = np.zeros((4, 4), dtype=np.complex128)
    companion[0, 0] = -(half / lead)
    companion[0, 1] = -(0j / lead)
    companion[0, 2] = -(half.conjugate() / lead)
    companion[0, 3] = -(lead.conjugate() / lead)
    for i in range(3):
        companion[i + 1, i] = 1.0
    out = np.full(5, procrustes)
    for i in range(4):
        if not (cmath.isfinite(companion[0, i])):
            return out
    roots = np.linalg.eigvals(companion)
    for i in range(4):
        angle = cmath.phase(roots[i])
        if math.isfinite(angle):
            out[i] = angle
    return out


@numba.njit(cache=True, nogil=True)
def fit_per_vector(y, c, W, newton_steps, polish_steps):
    """The global least-squares angle of one rotation about z: ``y``, ``c`` (n, 3) with the
    vectors' own informations ``W`` (n, 3, 3).

    Returns ``(phi wrapped to [-pi, pi), Fisher information, cost, informative radius)``.
    """
    cc = cs = ss = r0_c = r0_s = r0_r0 = 0.0
    # Independent vectors: the coefficients are sums of one quadratic form per vector.
    for v in range(c.shape[0]):
        cx, cy, cz = c[v, 0], c[v, 1], c[v, 2]
        u, w, rz = y[v, 0], y[v, 1], y[v, 2] - cz
        B = W[v]
        # W m_c and W m_s, with m_c = (cx, cy, 0) and m_s = (-cy, cx, 0).
        a0 = B[0, 0] * cx + B[0, 1] * cy
        a1 = B[1, 0] * cx + B[1, 1] * cy
        a2 = B[2, 0] * cx + B[2, 1] * cy
        b0 = B[0, 1] * cx - B[0, 0] * cy
        b1 = B[1, 1] * cx - B[1, 0] * cy
        b2 = B[2, 1] * cx - B[2, 0] * cy
        cc += cx * a0 + cy * a1
        cs += cx * a1 - cy * a0
        ss += cx * b1 - cy * b0
        r0_c += u * a0 + w * a1 + rz * a2
        r0_s += u * b0 + w * b1 + rz * b2
        r0_r0 += (
            u * (B[0, 0] * u + B[0, 1] * w + B[0, 2] * rz)
            + w * (B[1, 0] * u + B[1, 1] * w + B[1, 2] * rz)
            + rz * (B[2, 0] * u + B[2, 1] * w + B[2, 2] * rz)
        )
    return _minimum(c, cc, cs, ss, r0_c, r0_s, r0_r0, newton_steps, polish_steps)


@numba.njit(cache=True, nogil=True)
def fit_joint(y, c, W, newton_steps, polish_steps):
    """:func:`fit_per_vector` with the joint information ``W`` (3n, 3n) of the vectors."""
    n = c.shape[0]
    # Rows m_c, m_s and r0 = y - m0; their Gram matrix under W holds every coefficient.
    M = np.zeros((3, 3 * n))
    for v in range(n):
        M[0, 3 * v], M[0, 3 * v + 1] = c[v, 0], c[v, 1]
        M[1, 3 * v], M[1, 3 * v + 1] = -c[v, 1], c[v, 0]
        M[2, 3 * v], M[2, 3 * v + 1], M[2, 3 * v + 2] = y[v, 0], y[v, 1], y[v, 2] - c[v, 2]
    gram = (M @ W) @ M.T
    return _minimum(
        c, gram[0, 0], gram[1, 0], gram[1, 1], gram[2, 0], gram[2, 1], gram[2, 2],
        newton_steps, polish_steps,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _minimum(c, cc, cs, ss, r0_c, r0_s, r0_r0, newton_steps, polish_steps):
    """The global minimum of the cost from its Gram coefficients (see :func:`fit_per_vector`)."""
    a1, b1 = -2.0 * r0_c, -2.0 * r0_s
    a2, b2 = 0.5 * (cc - ss), cs
    k = r0_r0 + 0.5 * (cc + ss)
    best_phi, best_cost = math.nan, math.inf
    for phi in _candidates(a1, b1, a2, b2):
        phi = _newton(phi, a1, b1, a2, b2, newton_steps)
        cost = _cost(phi, k, a1, b1, a2, b2)
        if cost < best_cost or math.isnan(best_phi):
            best_phi, best_cost = phi, cost
    best_phi = _newton(best_phi, a1, b1, a2, b2, polish_steps)
    best_cost = _cost(best_phi, k, a1, b1, a2, b2)
    s1, c1 = math.sin(best_phi), math.cos(best_phi)
    radius = 0.0
    for v in range(c.shape[0]):
        radius += c[v, 0] * c[v, 0] + c[v, 1] * c[v, 1]
    return (
        (best_phi + math.pi) % (2 * math.pi) - math.pi,
        s1 * s1 * cc + c1 * c1 * ss - 2 * s1 * c1 * cs,
        max(best_cost, 0.0),
        math.sqrt(radius),
    )


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) the kernels once per process."""
    information_blocks(np.eye(3)[None].copy())
    vectors = np.ones((2, 3))
    fit_per_vector(vectors, vectors, np.broadcast_to(np.eye(3), (2, 3, 3)).copy(), 3, 2)
    fit_joint(vectors, vectors, np.eye(6), 3, 2)


__all__ = [
    "INFORMATION_OK",
    "NOT_FINITE",
    "NOT_POSITIVE_DEFINITE",
    "fit_joint",
    "fit_per_vector",
    "information_blocks",
    "warm_up",
]
