"""A frame's measurement groups, compiled (numba): the numbers of
:mod:`tracker.estimators.measurement` that both filters compute from every frame.

- :func:`assemble_positions`: the tip's and the markers' vectors and covariances, whether
  each is present, and the noise's part invariant under rotations about z;
- :func:`horizontal_radius`: how far the present points are from the rotation axis (how
  much a frame can say about the bending plane);
- :func:`model_error`: the white model-error covariance of every group;
- :func:`velocity_group`: the velocity's group of a frame;
- :func:`carry_expansion`, :func:`carry_expansions`: the shape's expansion carried from its grid
  node to the frame (one configuration, or several with the same numbers);
- :func:`view_projections`: single views' points at many angles, projected as the views
  project them (pinhole with OpenCV's distortion, or orthographic).

Each replaces a dozen numpy calls on arrays of a few elements. ``njit(cache=True,
nogil=True)`` as in :mod:`tracker.estimators.ukf_kernels`; :func:`warm_up` compiles or loads
them when a filter is made.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from models._imaging_kernels import distorted_pixel as _distorted_pixel


@numba.njit(cache=True, nogil=True)
def horizontal_radius(c, present, n_positions):
    """Root of the summed squared horizontal radii of the present positions' model vectors
    (the first ``n_positions`` groups of c (B, G, 3)), mm (B,)."""
    B = c.shape[0]
    out = np.empty(B)
    for t in range(B):
        total = 0.0
        for g in range(n_positions):
            if present[t, g]:
                total += c[t, g, 0] * c[t, g, 0] + c[t, g, 1] * c[t, g, 1]
        out[t] = math.sqrt(total)
    return out


@numba.njit(cache=True, nogil=True)
def model_error(JK, white_mm, has_velocity, c, u_norm, relative_error, process_var, dt):
    """The white model-error covariance ``white^2 J J^T`` of every group (B, G, 3, 3), plus on
    the velocity group (the last, with ``has_velocity``) the relative error of the modelled
    velocity, ``(relative_error |u|)^2 I``, and the torsion change over the interval,
    ``process_var / dt^2 t t^T`` with t the tip's tangent ``e_z x c_tip`` (``process_var``
    (B,), rad^2; ``dt`` (B,), s; none where dt is not positive)."""
    B, G = JK.shape[0], JK.shape[1]
    M = np.empty((B, G, 3, 3))
    w2 = white_mm * white_mm
    for t in range(B):
        for g in range(G):
            for a in range(3):
                for b in range(3):
                    M[t, g, a, b] = w2 * (JK[t, g, a, 0] * JK[t, g, b, 0]
                                          + JK[t, g, a, 1] * JK[t, g, b, 1])  # fmt: skip
        if has_velocity:
            rate_var = process_var[t] / dt[t] ** 2 if dt[t] > 0 else 0.0
            v = relative_error * u_norm[t]
            tangent = (-c[t, 0, 1], c[t, 0, 0], 0.0)
            for a in range(3):
                M[t, G - 1, a, a] += v * v
                for b in range(3):
                    M[t, G - 1, a, b] += rate_var * tangent[a] * tangent[b]
    return M


@numba.njit(cache=True, nogil=True, inline="always")
def _rotation_invariant_into(out, A):
    """``out`` (3, 3): the part of A (3, 3) invariant under rotations about z,
    ``diag((A_xx + A_yy) / 2, (A_xx + A_yy) / 2, A_zz)`` plus the antisymmetric horizontal
    part (zero for a covariance), every other entry 0."""
    horizontal = 0.5 * A[0, 0] + 0.5 * A[1, 1]
    skew = 0.5 * A[0, 1] - 0.5 * A[1, 0]
    for a in range(3):
        for b in range(3):
            out[a, b] = 0.0
    out[0, 0] = out[1, 1] = horizontal
    out[0, 1] = skew
    out[1, 0] = -skew
    out[2, 2] = A[2, 2]


@numba.njit(cache=True, nogil=True)
def assemble_positions(tip, tip_cov, markers, markers_cov, B, P, G, has_tip, has_markers):
    """The position groups of B trials' frames: each group's vector and covariance, its
    rotation-invariant noise and whether it is present (finite vector and covariance).

    Parameters
    ----------
    tip, tip_cov : arrays (B, 3), (B, 3, 3)
        Used with ``has_tip``.
    markers, markers_cov : arrays (B, P - 1, 3), (B, P - 1, 3, 3)
        Used with ``has_markers`` (NaN rows: markers not found).
    B, P, G : int
        Trials, position groups (the tip and the markers) and groups (G > P: a velocity
        group follows, filled by the caller).

    Returns
    -------
    y : array (B, G, 3), R, R_bar : arrays (B, G, 3, 3), present : bool array (B, G)
        Absent groups hold the placeholders 0 and I. R_bar is R's part invariant under
        rotations about z: ``diag((R_xx + R_yy) / 2, (R_xx + R_yy) / 2, R_zz)`` plus the
        antisymmetric horizontal part (:func:`_rotation_invariant_into`).
    """
    y = np.zeros((B, G, 3))
    R = np.zeros((B, G, 3, 3))
    R_bar = np.zeros((B, G, 3, 3))
    present = np.zeros((B, G), dtype=np.bool_)
    for t in range(B):
        for g in range(G):
            source = -1
            if g == 0 and has_tip:
                source = 0
            elif 0 < g < P and has_markers:
                source = g
            finite = source >= 0
            for a in range(3):
                v = 0.0
                if source == 0:
                    v = tip[t, a]
                elif source > 0:
                    v = markers[t, source - 1, a]
                y[t, g, a] = v
                finite = finite and math.isfinite(v)
                for b in range(3):
                    w = 0.0
                    if source == 0:
                        w = tip_cov[t, a, b]
                    elif source > 0:
                        w = markers_cov[t, source - 1, a, b]
                    R[t, g, a, b] = w
                    finite = finite and math.isfinite(w)
            present[t, g] = finite
            if not finite:
                for a in range(3):
                    y[t, g, a] = 0.0
                    for b in range(3):
                        R[t, g, a, b] = 1.0 if a == b else 0.0
            _rotation_invariant_into(R_bar[t, g], R[t, g])
    return y, R, R_bar, present


@numba.njit(cache=True, nogil=True)
def velocity_group(c, JK, rates, v_bar, cov_bar, gain, ok, y, R, R_bar, C, JK_all):
    """The velocity group (the last of G) of B trials' frames, in place.

    ``c`` (B, P, 3) and ``JK`` (B, P, 3, 5) are the positions' model vectors and expansion
    (the tip first), ``rates`` (B, 3) the joint rates, ``v_bar``, ``cov_bar`` (B, 3), (B, 3,
    3) the velocity decorrelated from the tip with its gain ``gain`` (B, 3, 3), ``ok`` (B,)
    where the velocity is usable. Fills ``y``, ``R``, ``R_bar``, ``C``, ``JK_all`` at the last
    group: the measured velocity, its noise and rotation-invariant noise, the model
    ``u - K_bar c_tip`` with ``u = q_r_dot e_z x c_tip + J_tip (q_p_dot, q_d_dot)`` (the
    modelled tip velocity) and its expansion ``-K_bar JK_tip``. Returns K_bar (B, 3, 3), the
    gain's rotation-invariant part, and |u| (B,), 0 where not ok.
    """
    B = c.shape[0]
    g = y.shape[1] - 1
    K_bar = np.zeros((B, 3, 3))
    u_norm = np.zeros(B)
    for t in range(B):
        _rotation_invariant_into(K_bar[t], gain[t])
        if ok[t]:
            for a in range(3):
                y[t, g, a] = v_bar[t, a]
                for b in range(3):
                    R[t, g, a, b] = cov_bar[t, a, b]
        _rotation_invariant_into(R_bar[t, g], R[t, g])
        if not ok[t]:
            continue
        # d/dt [Rz(delta_1) c] = Rz(delta_1) [q_r_dot e_z x c + J (q_p_dot, q_d_dot)].
        u = np.empty(3)
        u[0] = -c[t, 0, 1] * rates[t, 0]
        u[1] = c[t, 0, 0] * rates[t, 0]
        u[2] = 0.0
        for a in range(3):
            u[a] += JK[t, 0, a, 0] * rates[t, 1] + JK[t, 0, a, 1] * rates[t, 2]
        for a in range(3):
            C[t, g, a] = u[a] - (
                K_bar[t, a, 0] * c[t, 0, 0] + K_bar[t, a, 1] * c[t, 0, 1]
                + K_bar[t, a, 2] * c[t, 0, 2]
            )  # fmt: skip
            for m in range(5):
                JK_all[t, g, a, m] = -(
                    K_bar[t, a, 0] * JK[t, 0, 0, m] + K_bar[t, a, 1] * JK[t, 0, 1, m]
                    + K_bar[t, a, 2] * JK[t, 0, 2, m]
                )  # fmt: skip
        u_norm[t] = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
    return K_bar, u_norm


@numba.njit(cache=True, nogil=True, inline="always")
def _carry_into(out, JK, p, d):
    """``[J K]`` (P, 3, 5) of a grid node carried to (p, d) into ``out`` (P, 3, 5)."""
    for i in range(JK.shape[0]):
        for a in range(3):
            row = JK[i, a]
            out[i, a, 0] = row[0] + 2.0 * p * row[2] + d * row[3]
            out[i, a, 1] = row[1] + p * row[3] + 2.0 * d * row[4]
            out[i, a, 2] = row[2]
            out[i, a, 3] = row[3]
            out[i, a, 4] = row[4]


@numba.njit(cache=True, nogil=True)
def carry_expansion(JK, p, d):
    """``[J K]`` (P, 3, 5) of a grid node carried to a deviation (p, d) mm from it: J gains
    ``K dquad/ddq`` (columns ``J_p + 2 p K_pp + d K_pd`` and ``J_d + p K_pd + 2 d K_dd``), K
    stays; the product ``[J K] T`` of :meth:`ShapeExpansion.expanded` without its zeros,
    (1, P, 3, 5)."""
    out = np.empty((1,) + JK.shape)
    _carry_into(out[0], JK, p, d)
    return out


@numba.njit(cache=True, nogil=True)
def carry_expansions(nodes, node, p, d):
    """:func:`carry_expansion` of B configurations at once: ``nodes`` (k, P, 3, 5) the grid
    nodes' ``[J K]``, ``node`` (B,) each configuration's node, ``p``, ``d`` (B,) its offsets
    from it; (B, P, 3, 5), the same numbers."""
    B = node.shape[0]
    out = np.empty((B,) + nodes.shape[1:])
    for t in range(B):
        _carry_into(out[t], nodes[node[t]], p[t], d[t])
    return out


@numba.njit(cache=True, nogil=True)
def view_projections(angle, C, A, t, intrinsics, dist, pinhole):
    """The image points of model vectors turned about z_b by each angle.

    Point g of angle i is ``A_g Rz(angle_i) C_g + t_g`` in its camera's frame, then, for a
    pinhole camera, divided by its depth, distorted and scaled as ``cv2.projectPoints`` does
    (:func:`models._imaging_kernels.distorted_pixel`); for an orthographic plane its first two
    coordinates are the image's (mm).

    Parameters
    ----------
    angle : array (n,)
        q_r + delta_L of each prediction, rad.
    C : array (G, 3)
        Model vectors of the points, mm.
    A, t : arrays (G, 3, 3), (G, 3)
        Each point's camera: the rotation it projects with times its view's R_w_b, and that
        rotation applied to o_b_w plus the camera's translation, mm.
    intrinsics, dist : arrays (G, 4), (G, 5)
        fx, fy, cx, cy (px) and the distortion coefficients of each point's camera.
    pinhole : bool array (G,)

    Returns
    -------
    points : array (n, G, 2)
        px, or mm for orthographic planes.
    least_depth : float
        The smallest depth of a pinhole point, mm (inf without one).
    """
    n = angle.shape[0]
    G = C.shape[0]
    out = np.empty((n, G, 2))
    least_depth = np.inf
    for i in range(n):
        c = math.cos(angle[i])
        s = math.sin(angle[i])
        for g in range(G):
            x0 = c * C[g, 0] - s * C[g, 1]
            x1 = s * C[g, 0] + c * C[g, 1]
            x2 = C[g, 2]
            R = A[g]
            X = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[g, 0]
            Y = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[g, 1]
            if not pinhole[g]:
                out[i, g, 0] = X
                out[i, g, 1] = Y
                continue
            Z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[g, 2]
            least_depth = min(least_depth, Z)
            out[i, g, 0], out[i, g, 1] = _distorted_pixel(X, Y, Z, intrinsics[g], dist[g])
    return out, least_depth


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs of the filters' types (once
    per process)."""
    G = 3
    c = np.ones((1, G, 3))
    eye = np.broadcast_to(np.eye(3), (1, G, 3, 3)).copy()
    horizontal_radius(c, np.ones((1, G), dtype=bool), G)
    for has in (True, False):
        assemble_positions(c[:, 0], eye[:, 0], c[:, 1:], eye[:, 1:], 1, G, G + 1, has, has)
    model_error(np.zeros((1, G, 3, 5)), 0.1, True, c, np.ones(1), 0.1, np.ones(1), np.ones(1))
    carry_expansion(np.zeros((G, 3, 5)), 0.1, 0.1)
    carry_expansions(np.zeros((1, G, 3, 5)), np.zeros(1, dtype=np.intp), np.ones(1), np.ones(1))
    v, m = np.ones((1, 3)), np.ones((1, 3, 3))
    velocity_group(
        c, np.zeros((1, G, 3, 5)), v, v, m, m, np.ones(1, dtype=bool), np.zeros((1, G + 1, 3)),
        np.zeros((1, G + 1, 3, 3)), np.zeros((1, G + 1, 3, 3)), np.zeros((1, G + 1, 3)),
        np.zeros((1, G + 1, 3, 5)),
    )  # fmt: skip
    view_projections(
        np.zeros(1), c[0], eye[0], c[0], np.ones((G, 4)), np.zeros((G, 5)),
        np.ones(G, dtype=bool),
    )  # fmt: skip


__all__ = [
    "assemble_positions",
    "carry_expansion",
    "carry_expansions",
    "horizontal_radius",
    "model_error",
    "velocity_group",
    "view_projections",
    "warm_up",
]
