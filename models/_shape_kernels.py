"""The catheter's single-configuration shape, compiled (numba).

The filters evaluate the model's points at one configuration every frame (and at six
around it when a new expansion node is needed), where numpy's calls on arrays of a few
elements cost far more than the arithmetic. :func:`points_from_basis` is the whole
evaluation of :meth:`models.catheter.Catheter.points` from the joint bases' rows: the
bending angle at every quadrature node, the integrals of ``exp(i theta)`` at every limit,
and the paper's eq. DKfull at delta_1 = 0 for every point. Pure arithmetic, compiled once on
a machine and cached next to this file.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def points_from_basis(eta, G, W, column_1, column_2, cos_delta_2, sin_delta_2):
    """The points c of k configurations from their basis rows.

    Parameters
    ----------
    eta : array (k, m)
        ``[eta_1(q_p), eta_2(q_d)]`` of each configuration.
    G : array (m, N)
        theta at the quadrature nodes and, last, at L1 (``_Plan.G_single``).
    W : array (2 N, 2 J)
        The weights of the interleaved (cos, sin) pairs of ``exp(i theta)``
        (``_Plan.weights_single``): the (x, z) pairs of p_1 and p_2 at every limit, then
        (cos, sin)(theta_1(L1)).
    column_1, column_2 : int arrays (P,)
        Each point's limit columns of p_1 and p_2.
    cos_delta_2, sin_delta_2 : float

    Returns
    -------
    array (k, P, 3)
        ``c = p_1 + Ry(pi/2 - theta_1(L1)) Rz(delta_2) p_2``, mm, in the plan's order.
    """
    k, m = eta.shape
    N = G.shape[1]
    J2 = W.shape[1]
    P = column_1.shape[0]
    out = np.empty((k, P, 3))
    pairs = np.empty(2 * N)
    p = np.empty(J2)
    for r in range(k):
        for j in range(N):
            theta = 0.0
            for i in range(m):
                theta += eta[r, i] * G[i, j]
            pairs[2 * j] = math.cos(theta)
            pairs[2 * j + 1] = math.sin(theta)
        for j in range(J2):
            t = 0.0
            for i in range(2 * N):
                t += pairs[i] * W[i, j]
            p[j] = t
        c1, s1 = p[J2 - 2], p[J2 - 1]
        for i in range(P):
            j1, j2 = column_1[i], column_2[i]
            x1, z1, x2, z2 = p[2 * j1], p[2 * j1 + 1], p[2 * j2], p[2 * j2 + 1]
            out[r, i, 0] = x1 + s1 * cos_delta_2 * x2 + c1 * z2
            out[r, i, 1] = sin_delta_2 * x2
            out[r, i, 2] = z1 - c1 * cos_delta_2 * x2 + s1 * z2
    return out


@numba.njit(cache=True, nogil=True)
def points_at_powers(
    q_p, q_d, size_p, size_d, G, W, column_1, column_2, cos_delta_2, sin_delta_2
):  # fmt: skip
    """:func:`points_from_basis` of k configurations (q_p, q_d) (arrays (k,), mm) whose
    joint bases are power bases of ``size_p`` and ``size_d`` terms: the rows ``[1, q, q^2,
    ...]`` made here by the same running products as the model's own (so the same numbers).
    """
    k = q_p.shape[0]
    eta = np.empty((k, size_p + size_d))
    for r in range(k):
        eta[r, 0] = 1.0
        for j in range(1, size_p):
            eta[r, j] = eta[r, j - 1] * q_p[r]
        eta[r, size_p] = 1.0
        for j in range(size_p + 1, size_p + size_d):
            eta[r, j] = eta[r, j - 1] * q_d[r]
    return points_from_basis(eta, G, W, column_1, column_2, cos_delta_2, sin_delta_2)


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) the kernel once per process."""
    columns = np.zeros(1, dtype=np.int64)
    # The plan's matrices are read-only (a type of their own): as the model passes them.
    G, W = np.zeros((2, 2)), np.zeros((4, 4))
    for matrix in (G, W):
        matrix.flags.writeable = False
    points_from_basis(np.zeros((1, 2)), G, W, columns, columns, 1.0, 0.0)
    points_at_powers(np.zeros(1), np.zeros(1), 1, 1, G, W, columns, columns, 1.0, 0.0)


__all__ = ["points_at_powers", "points_from_basis", "warm_up"]
