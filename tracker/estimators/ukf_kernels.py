"""The UKF's per-hypothesis arithmetic, compiled (numba): the numbers behind the rules of
:mod:`tracker.estimators.ukf_rules` and :mod:`tracker.estimators.ukf_gate`.

A hypothesis' state has one to four components and a frame a few groups of two or three
values, so numpy spends ten times the arithmetic on calling its stacked routines for each
small array. Here each stage is one compiled loop over the rows (hypotheses) it is given;
the live filter (one row) and the trial-batched studies (thousands) call the same loops:

- :func:`predict_row`: the linear process model, ``F x``, ``F P F^T + Q`` (delta_L
  wrapped), the finiteness test, the std cap and the Cholesky factor that the update's sigma
  points reuse;
- :func:`row_factors`, :func:`sigma_rows`: the sigma points' factors (the predict's where
  it has one) and van der Merwe's sigma points;
- :func:`predict_3d` and :func:`innovation_3d`: the 3-D measurement model at the sigma
  points in the model frame, the measured vectors turned into that frame, and the
  innovation statistics;
- :func:`innovation_stats`: the innovation statistics of predictions made elsewhere (the
  single views' projections): the weighted mean, the residual, the innovation covariance
  ``S`` with its noise blocks, the cross-covariance ``Pxz`` and each group's squared
  residual under its own block of ``S`` (the gate);
- :func:`fuse_row`: the update with only the inlying groups (the others made inert: zero
  rows and columns, unit variance), one Cholesky solve for the gain, the NIS and the log
  determinant, and the posterior mean and covariance;
- :func:`mixture_rows`: two Gaussians matched by their moments (a doubtful group's update,
  hypotheses that agree).

The small linear algebra is :mod:`tracker.estimators.linalg_kernels` (Cholesky as LAPACK's
``potrf`` computes it, with the documented jitter of :mod:`tracker.estimators._linalg` on a
second attempt). Every kernel is ``njit(cache=True, nogil=True)``, compiled to
``__pycache__`` once on a machine and loaded afterwards; :func:`warm_up` compiles or loads
them with the argument types a run passes, once per process when the first filter is made,
so that no frame waits and nothing compiles while the live loop's threads run
(``tests/tracker/test_ukf_kernels.py`` checks it). Arrays are float64 and C-contiguous
(another layout would compile a second version on first use).
"""
from __future__ import annotations

import functools
import math

import numba
import numpy as np

from tracker.estimators.linalg_kernels import (
    _JITTER_FLOOR,
    _cap_row,
    _cholesky_into,
    _cholesky_jittered,
    _solve_lower,
    _wrap,
)


# ------------------------------------------------------------------------------ predict
@numba.njit(cache=True, nogil=True)
def predict_row(x, P, Q, decay, prior_p, prior_d, dt, deviation, rate, rate_noise,
                 max_variance, L, work):  # fmt: skip
    """The process model of one hypothesis in place, and the Cholesky factor of its predicted
    covariance; whether the prediction is usable.

    It is linear: a random walk of delta_L (variance ``Q`` over the interval), the torsion
    rate integrated (a random walk of intensity ``rate_noise``), the deviation an
    Ornstein-Uhlenbeck process (correlation ``decay`` over the interval, stationary variance
    ``prior_p``, ``prior_d``); delta_L is wrapped and its variance capped at ``max_variance``
    (row and column 0 scaled: the correlations are kept).

    Parameters
    ----------
    x : array (n,), P : array (n, n)
        State and covariance, changed in place.
    Q : float
        Variance of the torsion change over the interval, rad^2.
    decay : float
        The deviation's correlation over the interval (unused without a deviation).
    prior_p, prior_d : float
        The deviation's prior variance at the frame's joints, mm^2.
    dt : float
        Frame interval, s (the rate's integration).
    deviation, rate : int
        Index of the deviation (dq_p, dq_d) and of the torsion rate in the state; -1: none.
    rate_noise : float
        Process noise of the rate, rad^2/s^3.
    max_variance : float
        The delta_L variance cap, rad^2.
    L, work : arrays (n, n)
        The factor (written) and scratch.

    Returns
    -------
    bool
        Finite, positive delta_L variance, and (n > 1) positive definite after the jitter.
    """
    n = x.shape[0]
    P[0, 0] += Q
    if deviation >= 0:
        k = deviation
        for j in (k, k + 1):
            x[j] *= decay
            for c in range(n):
                P[j, c] *= decay
            for c in range(n):
                P[c, j] *= decay
        fresh = 1.0 - decay * decay
        P[k, k] += fresh * prior_p
        P[k + 1, k + 1] += fresh * prior_d
    if rate >= 0:
        j = rate
        x[0] += dt * x[j]
        for c in range(n):
            P[0, c] += dt * P[j, c]
        for c in range(n):
            P[c, 0] += dt * P[c, j]
        P[0, 0] += rate_noise * dt**3 / 3.0
        P[0, j] += rate_noise * dt**2 / 2.0
        P[j, 0] += rate_noise * dt**2 / 2.0
        P[j, j] += rate_noise * dt
    x[0] = _wrap(x[0])
    good = P[0, 0] > 0.0
    for a in range(n):
        good = good and math.isfinite(x[a])
        for c in range(n):
            good = good and math.isfinite(P[a, c])
    if not good:
        return False
    _cap_row(P, max_variance)
    if n == 1:
        L[0, 0] = math.sqrt(P[0, 0])
        return True
    return _cholesky_jittered(P, L, work)


# ------------------------------------------------------------------------------ update
@numba.njit(cache=True, nogil=True)
def _sigma_offsets(L, spread, offsets):
    """offsets (S, n): 0, then +- the columns of sqrt(spread) L."""
    n = L.shape[0]
    root = math.sqrt(spread)
    for a in range(n):
        offsets[0, a] = 0.0
    for col in range(n):
        for a in range(n):
            v = root * L[a, col]
            offsets[1 + col, a] = v
            offsets[1 + n + col, a] = -v


@numba.njit(cache=True, nogil=True)
def _sigma_factor(P, L, work):
    """The lower Cholesky factor of one covariance (n, n) into L for the sigma points (with
    the jitter's second attempt); whether it factorised."""
    if P.shape[0] == 1:
        a = P[0, 0]
        ok = math.isfinite(a) and a >= -_JITTER_FLOOR
        L[0, 0] = math.sqrt(max(a, _JITTER_FLOOR)) if ok else 1.0
        return ok
    return _cholesky_jittered(P, L, work)


@numba.njit(cache=True, nogil=True)
def row_factors(b, h, P_all, L_all, factor_ok):
    """The sigma points' factors of hypotheses (rows ``b``, ``h`` of P_all (B, H, n, n)):
    the predict's ``L_all`` where ``factor_ok``, else a fresh factorisation; the rows'
    covariances (r, n, n), factors (r, n, n) and which factorised (r,)."""
    r = b.shape[0]
    n = P_all.shape[2]
    P = np.empty((r, n, n))
    L = np.zeros((r, n, n))
    ok = np.ones(r, dtype=np.bool_)
    work = np.empty((n, n))
    for i in range(r):
        P[i] = P_all[b[i], h[i]]
        if factor_ok[b[i], h[i]]:
            L[i] = L_all[b[i], h[i]]
        else:
            ok[i] = _sigma_factor(P[i], L[i], work)
    return P, L, ok


@numba.njit(cache=True, nogil=True)
def sigma_rows(x, L, spread):
    """van der Merwe's sigma points of states x (r, n) with factors L (r, n, n): the points
    (r, 2n + 1, n) and their offsets from x."""
    r, n = x.shape
    S = 2 * n + 1
    offsets = np.empty((r, S, n))
    sigmas = np.empty((r, S, n))
    for i in range(r):
        _sigma_offsets(L[i], spread, offsets[i])
        for s in range(S):
            for a in range(n):
                sigmas[i, s, a] = x[i, a] + offsets[i, s, a]
    return sigmas, offsets


@numba.njit(cache=True, nogil=True)
def _statistics(hs, z, offsets, noise, Wm, Wc, G, d, S, rho, Pxz, d2, zp, D, block, work):
    """One row's innovation statistics (see :func:`innovation_stats`)."""
    n_sigma, m = hs.shape
    n = offsets.shape[1]
    for j in range(m):
        t = 0.0
        for s in range(n_sigma):
            t += Wm[s] * hs[s, j]
        zp[j] = t
    for s in range(n_sigma):
        for j in range(m):
            D[s, j] = hs[s, j] - zp[j]
    for j in range(m):
        rho[j] = z[j] - zp[j]
    for a in range(m):
        for b in range(a, m):
            t = 0.0
            for s in range(n_sigma):
                t += Wc[s] * D[s, a] * D[s, b]
            S[a, b] = t
            S[b, a] = t
    for g in range(G):
        for a in range(d):
            for b in range(d):
                S[g * d + a, g * d + b] += noise[g, a, b]
    for a in range(n):
        for j in range(m):
            t = 0.0
            for s in range(n_sigma):
                t += offsets[s, a] * Wc[s] * D[s, j]
            Pxz[a, j] = t
    for g in range(G):
        for a in range(d):
            for b in range(d):
                block[a, b] = S[g * d + a, g * d + b]
            work[a] = rho[g * d + a]
        if _cholesky_into(block, block):
            _solve_lower(block, work)
            t = 0.0
            for a in range(d):
                t += rho[g * d + a] * work[a]
            d2[g] = t
        else:
            d2[g] = math.inf


@numba.njit(cache=True, nogil=True)
def innovation_stats(hs, z, offsets, noise, Wm, Wc, d):
    """The innovation statistics of r hypotheses from predicted measurements.

    Parameters
    ----------
    hs : array (r, S, m)
        The measurement model at each sigma point, m = G d.
    z : array (r, m)
        The measured values.
    offsets : array (r, S, n)
        The sigma points' offsets from the mean.
    noise : array (r, G, d, d)
        Each group's noise covariance.
    Wm, Wc : arrays (S,)
        Sigma-point weights of the mean and the covariance.
    d : int
        Dimension of a group.

    Returns
    -------
    S : array (r, m, m)
        ``sum_s Wc dz dz^T`` plus the noise blocks.
    rho : array (r, m)
        Residual ``z - sum_s Wm hs``.
    Pxz : array (r, n, m)
        Cross-covariance of state and measurement.
    d2 : array (r, G)
        Each group's squared residual under its block of S (inf where that block is not
        positive definite: the gate rejects it).
    """
    r, n_sigma, m = hs.shape
    n = offsets.shape[2]
    G = m // d
    S = np.empty((r, m, m))
    rho = np.empty((r, m))
    Pxz = np.empty((r, n, m))
    d2 = np.empty((r, G))
    zp = np.empty(m)
    D = np.empty((n_sigma, m))
    block = np.empty((d, d))
    work = np.empty(d)
    for i in range(r):
        _statistics(
            hs[i], z[i], offsets[i], noise[i], Wm, Wc, G, d, S[i], rho[i], Pxz[i], d2[i], zp,
            D, block, work,
        )
    return S, rho, Pxz, d2


@numba.njit(cache=True, nogil=True)
def predict_3d(sigmas, c, JK, about, deviation, rate, has_velocity, hs):
    """The 3-D measurement model at the sigma points (S, n) of one hypothesis, into hs
    (S, G * 3): ``Rz(x_0 - about) (c + [J K] basis(dq))`` in the model frame at angle
    ``about``, plus ``rate e_z x c_tip`` on the velocity group (the last, with
    ``has_velocity``). c (G, 3), JK (G, 3, 5); ``deviation``, ``rate``: indices in the state
    (-1: none)."""
    n_sigma = sigmas.shape[0]
    G = c.shape[0]
    basis = np.empty(5)
    for s in range(n_sigma):
        angle = sigmas[s, 0] - about
        cs, sn = math.cos(angle), math.sin(angle)
        if deviation >= 0:
            p, q = sigmas[s, deviation], sigmas[s, deviation + 1]
            basis[0], basis[1], basis[2], basis[3], basis[4] = p, q, p * p, p * q, q * q
        for g in range(G):
            v0, v1, v2 = c[g, 0], c[g, 1], c[g, 2]
            if deviation >= 0:
                t0 = 0.0
                t1 = 0.0
                t2 = 0.0
                for e in range(5):
                    t0 += basis[e] * JK[g, 0, e]
                    t1 += basis[e] * JK[g, 1, e]
                    t2 += basis[e] * JK[g, 2, e]
                v0 += t0
                v1 += t1
                v2 += t2
            if rate >= 0 and has_velocity and g == G - 1:
                v0 -= sigmas[s, rate] * c[0, 1]
                v1 += sigmas[s, rate] * c[0, 0]
            hs[s, 3 * g] = cs * v0 - sn * v1
            hs[s, 3 * g + 1] = sn * v0 + cs * v1
            hs[s, 3 * g + 2] = v2


@numba.njit(cache=True, nogil=True)
def innovation_3d(
    x, L, spread, c, JK, y, q_r, R, scale, M, Wm, Wc, deviation, rate, has_velocity
):  # fmt: skip
    """Sigma points, the 3-D measurement model and the innovation statistics of r
    hypotheses, in the model frame at each one's prior mean (the measured vectors turned by
    ``-(q_r + x_0)``).

    Parameters
    ----------
    x : array (r, n), L : array (r, n, n)
        Prior means and the lower Cholesky factors of their covariances.
    spread : float
        (lambda + n) of the sigma points.
    c : array (r, G, 3), JK : array (r, G, 3, 5)
        Model vectors and their expansion in the deviation
        (:class:`~tracker.estimators.measurement.FrameGroups`).
    y : array (r, G, 3)
        Measured vectors in {B}.
    q_r : array (r,)
        Base rotation, rad.
    R : array (r, G, 3, 3), scale : array (r,), M : array (r, G, 3, 3)
        Each group's noise covariance in the model frame is ``scale R + M`` (segmentation
        noise, its adaptive scale, the white model error).
    Wm, Wc : arrays (2n + 1,)
    deviation, rate : int
        Indices in the state (-1: none).
    has_velocity : bool
        The last group is the velocity (the rate adds ``rate e_z x c_tip`` to it).

    Returns
    -------
    S, rho, Pxz, d2 : as :func:`innovation_stats` (d = 3)
    offsets : array (r, 2n + 1, n)
        The sigma points' offsets.
    """
    r, n = x.shape
    G = c.shape[1]
    m = 3 * G
    n_sigma = 2 * n + 1
    S = np.empty((r, m, m))
    rho = np.empty((r, m))
    Pxz = np.empty((r, n, m))
    d2 = np.empty((r, G))
    offsets = np.empty((r, n_sigma, n))
    sigmas = np.empty((n_sigma, n))
    hs = np.empty((n_sigma, m))
    z = np.empty(m)
    zp = np.empty(m)
    D = np.empty((n_sigma, m))
    block = np.empty((3, 3))
    work = np.empty(3)
    noise = np.empty((G, 3, 3))
    for i in range(r):
        for g in range(G):
            for a in range(3):
                for b in range(3):
                    noise[g, a, b] = R[i, g, a, b] * scale[i] + M[i, g, a, b]
        _sigma_offsets(L[i], spread, offsets[i])
        for s in range(n_sigma):
            for a in range(n):
                sigmas[s, a] = x[i, a] + offsets[i, s, a]
        about = x[i, 0]
        predict_3d(sigmas, c[i], JK[i], about, deviation, rate, has_velocity, hs)
        turn = -(q_r[i] + about)
        cs, sn = math.cos(turn), math.sin(turn)
        for g in range(G):
            y0, y1 = y[i, g, 0], y[i, g, 1]
            z[3 * g] = cs * y0 - sn * y1
            z[3 * g + 1] = sn * y0 + cs * y1
            z[3 * g + 2] = y[i, g, 2]
        _statistics(
            hs, z, offsets[i], noise, Wm, Wc, G, 3, S[i], rho[i], Pxz[i], d2[i], zp, D,
            block, work,
        )
    return S, rho, Pxz, d2, offsets


@numba.njit(cache=True, nogil=True)
def fuse_row(S, rho, Pxz, inlier, d, x, P, products, x_post, P_post, Sm, A, solved, keep):
    """The update of one hypothesis with only its inlying groups, into ``products``,
    ``x_post`` and ``P_post``; returns ``(logdet, ok)``.

    The groups left out get zero rows and columns and unit variance (inert in the solve).
    With ``A = [Pxz; rho^T]`` and the gain ``K = Pxz S^-1``, the products ``A S^-1 A^T =
    [[K Pxz^T, K rho], [., nis]]`` (zeros where S does not factorise) give the posterior
    ``x + K rho`` (delta_L wrapped) and ``P - K S K^T`` (symmetrised); logdet is that of the
    masked S (NaN where it does not factorise). ``S`` (m, m), ``rho`` (m,), ``Pxz`` (n, m)
    as :func:`innovation_stats` gives them, ``inlier`` (G,), groups of dimension ``d``;
    ``Sm``, ``A``, ``solved``, ``keep``: scratch.
    """
    m = rho.shape[0]
    n = Pxz.shape[0]
    for j in range(m):
        keep[j] = inlier[j // d]
    for a in range(m):
        for b in range(m):
            if keep[a] and keep[b]:
                Sm[a, b] = S[a, b]
            elif a == b:
                Sm[a, b] = 1.0
            else:
                Sm[a, b] = 0.0
    for j in range(m):
        for a in range(n):
            A[a, j] = Pxz[a, j] if keep[j] else 0.0
        A[n, j] = rho[j] if keep[j] else 0.0
    logdet = math.nan
    ok = _cholesky_into(Sm, Sm)
    for a in range(n + 1):
        for b in range(n + 1):
            products[a, b] = 0.0
    if ok:
        t = 0.0
        for j in range(m):
            t += math.log(Sm[j, j])
        logdet = 2.0 * t
        for a in range(n + 1):
            for j in range(m):
                solved[a, j] = A[a, j]
            _solve_lower(Sm, solved[a])
        for a in range(n + 1):
            for b in range(a, n + 1):
                t = 0.0
                for j in range(m):
                    t += A[a, j] * solved[b, j]
                products[a, b] = t
                products[b, a] = t
    for a in range(n):
        x_post[a] = x[a] + products[a, n]
    x_post[0] = _wrap(x_post[0])
    for a in range(n):
        for b in range(n):
            P_post[a, b] = P[a, b] - products[a, b]
    for a in range(n):
        for b in range(a + 1, n):
            t = 0.5 * (P_post[a, b] + P_post[b, a])
            P_post[a, b] = t
            P_post[b, a] = t
    return logdet, ok


@numba.njit(cache=True, nogil=True)
def _mixture_row(w, x1, P1, x2, P2, x, P, diff):
    """Mean x and covariance P (may be x1, P1) of ``w N(x1, P1) + (1 - w) N(x2, P2)``, the
    first component an angle (the two close enough for a linear mean)."""
    n = x1.shape[0]
    for a in range(n):
        diff[a] = x1[a] - x2[a]
    diff[0] = _wrap(diff[0])
    for a in range(n):
        for b in range(n):
            P[a, b] = w * P1[a, b] + (1.0 - w) * P2[a, b] + w * (1.0 - w) * diff[a] * diff[b]
    for a in range(n):
        x[a] = x2[a] + w * diff[a]
    x[0] = _wrap(x[0])


@numba.njit(cache=True, nogil=True)
def mixture_rows(w, x1, P1, x2, P2):
    """Mean (r, n) and covariance (r, n, n) of the mixtures ``w N(x1, P1) + (1 - w) N(x2,
    P2)`` of r pairs of Gaussians (weights w (r,)), matched by moments; the first component
    of the state an angle."""
    r, n = x1.shape
    x = np.empty((r, n))
    P = np.empty((r, n, n))
    diff = np.empty(n)
    for i in range(r):
        _mixture_row(w[i], x1[i], P1[i], x2[i], P2[i], x[i], P[i], diff)
    return x, P


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) every kernel on tiny inputs of the filters' types (once
    per process)."""
    for n in (1, 3, 4):
        x = np.zeros((1, n))
        P = np.eye(n)[None].copy()
        rows = np.zeros(1, dtype=np.intp)
        P, L, ok = row_factors(rows, rows, P[:, None], P[:, None], np.zeros((1, 1), bool))
        fixed = rows.copy()
        fixed.flags.writeable = False  # a bank of one's standing indices (single views)
        row_factors(fixed, fixed, P[:, None], P[:, None], np.zeros((1, 1), bool))
        sigmas, offsets = sigma_rows(x, L, 1.0)
        W = np.full(2 * n + 1, 1.0 / (2 * n + 1))
        G = 2
        c = np.ones((1, G, 3))
        eye = np.broadcast_to(np.eye(3), (1, G, 3, 3)).copy()
        innovation_3d(
            x, L, 1.0, c, np.zeros((1, G, 3, 5)), c, np.zeros(1), eye, np.ones(1), eye, W, W,
            -1, -1, False,
        )  # fmt: skip
        for d in (2, 3):
            hs = np.zeros((1, 2 * n + 1, G * d))
            noise = np.broadcast_to(np.eye(d), (1, G, d, d)).copy()
            innovation_stats(hs, np.zeros((1, G * d)), offsets, noise, W, W, d)
        mixture_rows(np.ones(1), x, P, x, P)


__all__ = [
    "fuse_row",
    "innovation_3d",
    "innovation_stats",
    "mixture_rows",
    "predict_3d",
    "predict_row",
    "row_factors",
    "sigma_rows",
    "warm_up",
]
