"""Reconstruction of points seen by a pinhole rig, compiled (numba).

The live loop reconstructs a frame's few points from two or more views on every frame (the
tip and the markers; the pair's tip band at four nudged positions), where numpy spends far
more on calling its routines for arrays of a few elements than on the arithmetic.
:func:`triangulate` and :func:`propagate` are the arithmetic of
:meth:`models.imaging.Rig.reconstruct` and :meth:`models.imaging.Rig.reconstruction_covariance`
for cameras without distortion (the rig's own Notes give the formulas), one point at a time.
:func:`distorted_pixel` is ``cv2.projectPoints`` for one point in a camera's frame, for the
compiled steps that project (the epipolar check, single views' predictions).
:func:`to_base` moves points and covariances into a registered base frame, and
:func:`observe_frame` is a whole usual live frame (checks, both steps above, the move to the
base and the finite-difference velocity) in one call. Compiled once on a machine and cached
next to this file.
"""

from __future__ import annotations

import functools

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def triangulate(uv, principal, focal, R_cam_w, t_cam_w):
    """Least-squares points of the DLT equations of every view.

    Parameters
    ----------
    uv : array (N, V, 2)
        Undistorted image points, px.
    principal, focal : arrays (V, 2)
    R_cam_w, t_cam_w : arrays (V, 3, 3), (V, 3)

    Returns
    -------
    points : array (N, 3)
        ``x`` minimising ``|A x - b|`` (``x_cam[:2] = m x_cam[2]``, two rows per view), by
        the singular value decomposition of A.
    parallel : array of bool (N,)
        Points whose rays are parallel (smallest singular value at most 1e-12 of the
        largest): no point.
    """
    N, V = uv.shape[0], uv.shape[1]
    points = np.empty((N, 3))
    parallel = np.zeros(N, dtype=np.bool_)
    A = np.empty((2 * V, 3))
    b = np.empty(2 * V)
    for n in range(N):
        for v in range(V):
            for a in range(2):
                m = (uv[n, v, a] - principal[v, a]) / focal[v, a]
                for j in range(3):
                    A[2 * v + a, j] = m * R_cam_w[v, 2, j] - R_cam_w[v, a, j]
                b[2 * v + a] = t_cam_w[v, a] - m * t_cam_w[v, 2]
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        if s[2] <= 1e-12 * s[0]:
            parallel[n] = True
            points[n] = np.nan
            continue
        y = np.empty(3)
        for k in range(3):
            t = 0.0
            for i in range(2 * V):
                t += U[i, k] * b[i]
            y[k] = t / s[k]
        for j in range(3):
            t = 0.0
            for k in range(3):
                t += Vt[k, j] * y[k]
            points[n, j] = t
    return points, parallel


@numba.njit(cache=True, nogil=True)
def propagate(x, cov, R_cam_w, t_cam_w, inverse_focal):
    """First-order covariances of the points from their image noise.

    ``H^-1 N H^-1`` with ``H = sum_v A_v^T A_v``, ``N = sum_v A_v^T C_v A_v``,
    ``A_v = [I | -n_v] R_cam_w`` and ``C_v = L_v^-1 cov_v L_v^-T``, ``L_v^-1 = Z_v
    K_2^-1`` (the Notes of :meth:`models.imaging.Rig.reconstruction_covariance`),
    symmetrised.

    Parameters
    ----------
    x : array (N, 3)
    cov : array (N, V, 2, 2)
        Image noise, px^2.
    R_cam_w, t_cam_w, inverse_focal : arrays (V, 3, 3), (V, 3), (V, 2, 2)

    Returns
    -------
    cov_w : array (N, 3, 3)
        mm^2.
    behind : array of bool (N,)
        Points at or behind a camera's centre (no covariance).
    """
    N, V = x.shape[0], cov.shape[1]
    out = np.empty((N, 3, 3))
    behind = np.zeros(N, dtype=np.bool_)
    A = np.empty((2, 3))
    C = np.empty((2, 2))
    L = np.empty((2, 2))
    for p in range(N):
        H = np.zeros((3, 3))
        M = np.zeros((3, 3))
        for v in range(V):
            xc = np.empty(3)
            for i in range(3):
                xc[i] = (R_cam_w[v, i, 0] * x[p, 0] + R_cam_w[v, i, 1] * x[p, 1]
                         + R_cam_w[v, i, 2] * x[p, 2]) + t_cam_w[v, i]  # fmt: skip
            depth = xc[2]
            if not depth > 0.0:
                behind[p] = True
            for a in range(2):
                n_a = xc[a] / depth
                for j in range(3):
                    A[a, j] = R_cam_w[v, a, j] - n_a * R_cam_w[v, 2, j]
            for i in range(2):
                for j in range(2):
                    L[i, j] = depth * inverse_focal[v, i, j]
            # C = L cov L^T
            for i in range(2):
                for j in range(2):
                    t = 0.0
                    for k in range(2):
                        for m in range(2):
                            t += L[i, k] * cov[p, v, k, m] * L[j, m]
                    C[i, j] = t
            for i in range(3):
                for j in range(3):
                    h = 0.0
                    s = 0.0
                    for a in range(2):
                        h += A[a, i] * A[a, j]
                        for c in range(2):
                            s += A[a, i] * C[a, c] * A[c, j]
                    H[i, j] += h
                    M[i, j] += s
        if behind[p]:
            out[p] = np.nan
            continue
        H_inv = np.linalg.inv(H)
        W = H_inv @ M @ H_inv
        for i in range(3):
            for j in range(3):
                out[p, i, j] = 0.5 * (W[i, j] + W[j, i])
    return out, behind


@numba.njit(cache=True, nogil=True)
def distorted_pixel(X, Y, Z, intrinsics, k):
    """The pixel (u, v) of a point (X, Y, Z) in a camera's frame, mm, as
    ``cv2.projectPoints`` computes it: divided by its depth (1 where the depth is 0),
    distorted (``k``: k1, k2, p1, p2, k3) and scaled (``intrinsics``: fx, fy, cx, cy, px)."""
    z = 1.0 / Z if Z != 0.0 else 1.0
    x = X * z
    y = Y * z
    r2 = x * x + y * y
    r4 = r2 * r2
    cdist = 1.0 + k[0] * r2 + k[1] * r4 + k[4] * (r4 * r2)
    xd = x * cdist + k[2] * (2.0 * x * y) + k[3] * (r2 + 2.0 * x * x)
    yd = y * cdist + k[2] * (r2 + 2.0 * y * y) + k[3] * (2.0 * x * y)
    return xd * intrinsics[0] + intrinsics[2], yd * intrinsics[1] + intrinsics[3]


@numba.njit(cache=True, nogil=True)
def _point_to_base(x, c, R, o, point_out, cov_out):
    """One point ``x`` (3,) and its covariance ``c`` (3, 3) in {W} into {B}: ``R^T (x - o)``
    element by element (``d_x R[0] + d_y R[1] + d_z R[2]``, as
    :meth:`models.pose.Pose.base_from_world`) and ``(R^T C) R`` with every sum in index order."""
    d0, d1, d2 = x[0] - o[0], x[1] - o[1], x[2] - o[2]
    for j in range(3):
        point_out[j] = d0 * R[0, j] + d1 * R[1, j] + d2 * R[2, j]
    A = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            A[i, j] = R[0, i] * c[0, j] + R[1, i] * c[1, j] + R[2, i] * c[2, j]
    for i in range(3):
        for j in range(3):
            cov_out[i, j] = A[i, 0] * R[0, j] + A[i, 1] * R[1, j] + A[i, 2] * R[2, j]


@numba.njit(cache=True, nogil=True)
def to_base(points_w, cov_w, R_w_b, o_b_w):
    """Points (N, 3) and covariances (N, 3, 3) in {W} -> {B} (rotation ``R_w_b``, origin
    ``o_b_w``), point by point as :func:`observe_frame` does: the same numbers for a point
    whatever else is in the batch."""
    N = points_w.shape[0]
    points_b = np.empty((N, 3))
    covs_b = np.empty((N, 3, 3))
    for n in range(N):
        _point_to_base(points_w[n], cov_w[n], R_w_b, o_b_w, points_b[n], covs_b[n])
    return points_b, covs_b


FRAME_OK, FRAME_UNUSUAL = 0, 1
""":func:`observe_frame`'s status: done, or a frame for the general path (which names what is
wrong with it, if anything)."""


@numba.njit(cache=True, nogil=True)
def observe_frame(q, uv, cov, principal, focal, R_cam_w, t_cam_w, inverse_focal, R_w_b,
                  o_b_w, tip_before, cov_before, dt):  # fmt: skip
    """A usual frame's points in {B} and the tip's finite-difference velocity, in one call.

    The arithmetic of :func:`triangulate`, :func:`propagate`, :func:`to_base` and
    :func:`tracker.types.velocity_from_positions` (``(p - p_before) / dt``,
    ``(S + S_before) / dt^2``, ``S / dt``), so the results are those of the batch path to the
    bit. A frame that is not usual gets ``FRAME_UNUSUAL`` and no numbers: joint values or
    image points not finite, a covariance not finite, not symmetric to 1e-9 of its view's
    largest entry or not positive semi-definite with a margin of 1e-13 of it (ten times the
    batch path's check's), a point at or behind a camera, or rays that are parallel.

    Parameters
    ----------
    q : array (3,)
    uv, cov : arrays (V, P, 2), (V, P, 2, 2)
        The frame's points and their noise, view by view.
    principal, focal, R_cam_w, t_cam_w, inverse_focal : the rig's camera arrays
    R_w_b, o_b_w : arrays (3, 3), (3,)
        The registered base.
    tip_before, cov_before : arrays (3,), (3, 3)
        The tip of the frame before, in {B}, and its covariance.
    dt : float
        The time since that frame, s; NaN: no velocity.

    Returns
    -------
    status : int
    points_b, covs_b : arrays (P, 3), (P, 3, 3)
    velocity, velocity_cov, velocity_tip_cov : arrays (3,), (3, 3), (3, 3)
    """
    V, P = uv.shape[0], uv.shape[1]
    points_b = np.empty((P, 3))
    covs_b = np.empty((P, 3, 3))
    velocity = np.empty(3)
    velocity_cov = np.empty((3, 3))
    cross = np.empty((3, 3))
    nothing = (FRAME_UNUSUAL, points_b, covs_b, velocity, velocity_cov, cross)
    for i in range(3):
        if not np.isfinite(q[i]):
            return nothing
    uv_pv = np.empty((P, V, 2))
    cov_pv = np.empty((P, V, 2, 2))
    for v in range(V):
        scale = 1e-300
        for p in range(P):
            for a in range(2):
                if not np.isfinite(uv[v, p, a]):
                    return nothing
                uv_pv[p, v, a] = uv[v, p, a]
                for b in range(2):
                    e = cov[v, p, a, b]
                    if not np.isfinite(e):
                        return nothing
                    scale = max(scale, abs(e))
                    cov_pv[p, v, a, b] = e
        for p in range(P):
            a, b, c, d = cov[v, p, 0, 0], cov[v, p, 0, 1], cov[v, p, 1, 0], cov[v, p, 1, 1]
            if abs(b - c) > 1e-9 * scale or (
                0.5 * (a + d) - np.hypot(0.5 * (a - d), c) < -1e-13 * scale
            ):
                return nothing
    points_w, parallel = triangulate(uv_pv, principal, focal, R_cam_w, t_cam_w)
    cov_w, behind = propagate(points_w, cov_pv, R_cam_w, t_cam_w, inverse_focal)
    for p in range(P):
        if parallel[p] or behind[p]:
            return nothing
        _point_to_base(points_w[p], cov_w[p], R_w_b, o_b_w, points_b[p], covs_b[p])
    if np.isfinite(dt):
        dt2 = dt**2
        for i in range(3):
            velocity[i] = (points_b[0, i] - tip_before[i]) / dt
            for j in range(3):
                velocity_cov[i, j] = (covs_b[0, i, j] + cov_before[i, j]) / dt2
                cross[i, j] = covs_b[0, i, j] / dt
    return FRAME_OK, points_b, covs_b, velocity, velocity_cov, cross


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) the kernels once per process, with the types the rig
    passes (its camera arrays are read-only)."""

    def frozen(a):
        a.flags.writeable = False
        return a

    # Two cameras 90 degrees apart, 400 mm from the origin.
    R = frozen(np.array([np.eye(3), [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]]))
    t = frozen(np.array([[0.0, 0.0, 400.0], [0.0, 0.0, 400.0]]))
    pair = frozen(np.ones((2, 2)))
    points, _ = triangulate(np.zeros((1, 2, 2)), pair, pair, R, t)
    inverse_focal = frozen(np.broadcast_to(np.eye(2), (2, 2, 2)).copy())
    propagate(np.zeros((1, 3)), np.ones((1, 2, 2, 2)), R, t, inverse_focal)
    # The base pose's arrays are read-only too (models.pose.Pose).
    R_w_b, o_b_w = frozen(np.eye(3)), frozen(np.zeros(3))
    to_base(np.zeros((1, 3)), np.ones((1, 3, 3)), R_w_b, o_b_w)
    observe_frame(np.zeros(3), np.zeros((2, 1, 2)), np.ones((2, 1, 2, 2)), pair, pair, R, t,
                  inverse_focal, R_w_b, o_b_w, np.zeros(3), np.eye(3), 0.05)  # fmt: skip


__all__ = [
    "FRAME_OK",
    "FRAME_UNUSUAL",
    "distorted_pixel",
    "observe_frame",
    "propagate",
    "to_base",
    "triangulate",
    "warm_up",
]
