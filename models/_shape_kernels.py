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


@numba.njit(cache=True, nogil=True, inline="always")
def _power_rows(eta, q_p, q_d, size_p, size_d):
    """``eta`` (size_p + size_d,): the power bases' rows ``[1, q_p, q_p^2, ..., 1, q_d, ...]``
    by running products, as the model makes them."""
    eta[0] = 1.0
    for j in range(1, size_p):
        eta[j] = eta[j - 1] * q_p
    eta[size_p] = 1.0
    for j in range(size_p + 1, size_p + size_d):
        eta[j] = eta[j - 1] * q_d


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
        _power_rows(eta[r], q_p[r], q_d[r], size_p, size_d)
    return points_from_basis(eta, G, W, column_1, column_2, cos_delta_2, sin_delta_2)


@numba.njit(cache=True, nogil=True)
def points_and_tip_velocity_at_powers(
    q, q_dot, size_p, size_d, G, W, column_1, column_2, tip_1, tip_2, cos_delta_2,
    sin_delta_2,
):  # fmt: skip
    """The points c of one configuration q (3,) of a model with power bases, as
    :func:`points_at_powers` gives them, and the tip's velocity u (3,) at joint rates
    ``q_dot`` (3,): ``q_r_dot e_z x c_tip + dc_tip/dq_p q_p_dot + dc_tip/dq_d q_d_dot``.

    The derivatives of the bases' rows, then of theta at the nodes, of ``exp(i theta)``
    (``i dtheta exp(i theta)``) and of its integrals at every limit give those of p_1, p_2
    and theta_1(L1); ``tip_1``, ``tip_2`` are the tip's limit columns.
    """
    m = size_p + size_d
    eta = np.empty((1, m))
    _power_rows(eta[0], q[1], q[2], size_p, size_d)
    # Their derivatives: d(q^j)/dq = j q^(j - 1).
    deta = np.zeros(m)
    for j in range(1, size_p):
        deta[j] = j * eta[0, j - 1]
    for j in range(size_p + 1, m):
        deta[j] = (j - size_p) * eta[0, j - 1]
    points = points_from_basis(eta, G, W, column_1, column_2, cos_delta_2, sin_delta_2)[0]
    N = G.shape[1]
    J2 = W.shape[1]
    pairs = np.empty(2 * N)
    dpairs = np.empty(2 * N)
    for j in range(N):
        theta = 0.0
        dtheta = 0.0
        for i in range(m):
            theta += eta[0, i] * G[i, j]
            dtheta += deta[i] * G[i, j]
        c, s = math.cos(theta), math.sin(theta)
        pairs[2 * j], pairs[2 * j + 1] = c, s
        dpairs[2 * j], dpairs[2 * j + 1] = -dtheta * s, dtheta * c
    p = np.empty(J2)
    dp = np.empty(J2)
    for j in range(J2):
        t = 0.0
        dt = 0.0
        for i in range(2 * N):
            t += pairs[i] * W[i, j]
            dt += dpairs[i] * W[i, j]
        p[j], dp[j] = t, dt
    c1, s1 = p[J2 - 2], p[J2 - 1]
    dc1, ds1 = dp[J2 - 2], dp[J2 - 1]  # d(cos, sin)(theta_1(L1)) / dq_p
    x2, z2 = p[2 * tip_2], p[2 * tip_2 + 1]
    dx1, dz1 = dp[2 * tip_1], dp[2 * tip_1 + 1]  # d/dq_p on segment 1's columns
    dx2, dz2 = dp[2 * tip_2], dp[2 * tip_2 + 1]  # d/dq_d on segment 2's
    cd2, sd2 = cos_delta_2, sin_delta_2
    dc_p = (dx1 + ds1 * cd2 * x2 + dc1 * z2, 0.0, dz1 - dc1 * cd2 * x2 + ds1 * z2)
    dc_d = (s1 * cd2 * dx2 + c1 * dz2, sd2 * dx2, -c1 * cd2 * dx2 + s1 * dz2)
    r_dot, p_dot, d_dot = q_dot[0], q_dot[1], q_dot[2]
    tip = points.shape[0] - 1
    u = np.empty(3)
    u[0] = -r_dot * points[tip, 1] + dc_p[0] * p_dot + dc_d[0] * d_dot
    u[1] = r_dot * points[tip, 0] + dc_p[1] * p_dot + dc_d[1] * d_dot
    u[2] = dc_p[2] * p_dot + dc_d[2] * d_dot
    return points, u


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
    # The plan's columns are read-only too when the model passes them whole.
    fixed = columns.copy()
    fixed.flags.writeable = False
    points_from_basis(np.zeros((1, 2)), G, W, fixed, fixed, 1.0, 0.0)
    points_and_tip_velocity_at_powers(
        np.zeros(3), np.zeros(3), 1, 1, G, W, fixed, fixed, 0, 0, 1.0, 0.0
    )


__all__ = [
    "points_and_tip_velocity_at_powers", "points_at_powers", "points_from_basis", "warm_up"
]
