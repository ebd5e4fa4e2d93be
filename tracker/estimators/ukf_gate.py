"""The UKF update's rules per hypothesis, compiled (numba), given the innovation statistics
of :mod:`tracker.estimators.ukf_kernels`: the gate of each group, the joint consistency of the
groups that pass, the mixture with the update without a doubtful group, the frame's
likelihood under the hypothesis and the update's status (:func:`gate_and_fuse`); the
write-back (:func:`commit_update`); both for a 3-D frame in one call with its innovation
(:func:`update_3d`), and for single views with their projections (:func:`update_views`).
Used by :class:`~tracker.estimators.ukf_core.FilterBank` for the live filter and the batch
alike (docs/design.md, "Joint consistency and doubtful groups"), and warmed up by
:func:`tracker.estimators.ukf_rules.warm_up`. Flags are passed as integers in the order of
``FLAG_ORDER``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from tracker.estimators.linalg_kernels import _lu_solve
from tracker.estimators.measurement_kernels import view_projections
from tracker.estimators.ukf_kernels import (
    _mixture_row,
    fuse_row,
    innovation_3d,
    innovation_stats,
    row_factors,
    sigma_rows,
)

# The flags the kernels set, in the order of the ``flags`` array they are given.
FLAG_ORDER = (
    "PARTIAL", "NO_MEASUREMENT", "HELD", "NOT_INITIALISED", "OUTLIER_REJECTED",
    "COVARIANCE_REPAIRED", "UNINFORMATIVE", "MODEL_MISMATCH",
)  # fmt: skip
_PARTIAL, _NO_MEASUREMENT, _HELD, _NOT_INITIALISED, _OUTLIER, _REPAIRED, _UNINFORMATIVE = range(7)
_MISMATCH = 7


@numba.njit(cache=True, nogil=True)
def _exclude_inconsistent(S, rho, inlier, d, threshold):
    """Inlying groups whose residual *given the other inlying groups* exceeds the group
    threshold, left out one at a time (the worst first) while two remain (in place).

    The residual of group g given the others is Gaussian with covariance
    ``((S^-1)_gg)^-1`` and mean zero under the model; its squared Mahalanobis length is
    ``e_g^T ((S^-1)_gg)^-1 e_g`` with ``e = S^-1 rho``: how much the joint NIS drops when g
    is left out."""
    m = rho.shape[0]
    G = m // d
    Sm = np.empty((m, m))
    inverse = np.empty((m, m))
    work = np.empty((m, m))
    block = np.empty((d, d))
    rhs = np.empty((d, 1))
    small = np.empty((d, d))
    while True:
        for a in range(m):
            for b in range(m):
                both = inlier[a // d] and inlier[b // d]
                Sm[a, b] = S[a, b] if both else (1.0 if a == b else 0.0)
                inverse[a, b] = 1.0 if a == b else 0.0
        if _lu_solve(Sm, inverse, work) == -math.inf:
            return
        worst, largest = -1, -math.inf
        for g in range(G):
            if not inlier[g]:
                continue
            for a in range(d):
                t = 0.0
                for j in range(m):
                    if inlier[j // d]:
                        t += inverse[g * d + a, j] * rho[j]
                rhs[a, 0] = t
                for b in range(d):
                    block[a, b] = inverse[g * d + a, g * d + b]
            e = rhs.copy()
            if _lu_solve(block, rhs, small) == -math.inf:
                continue
            given = 0.0
            for a in range(d):
                given += e[a, 0] * rhs[a, 0]
            if given > largest:
                worst, largest = g, given
        if worst < 0 or not largest > threshold:
            return
        inlier[worst] = False
        count = 0
        for g in range(G):
            count += inlier[g]
        if count < 2:
            return


@numba.njit(cache=True, nogil=True)
def gate_and_fuse(
    S, rho, Pxz, d2, present, ok_sigma, x, P, d, outlier_probability, outlier_scale,
    threshold, doubt, gates, min_information, flag,
):  # fmt: skip
    """The update's rules for r hypotheses, given their innovation statistics (docs/design.md,
    "Joint consistency and doubtful groups").

    Per hypothesis: a group is an inlier when present and its squared residual ``d2`` is
    within ``threshold`` (where its posterior probability of being a gross error is one
    half); the inliers are fused in one solve. When two or more inliers pass alone but their
    joint NIS exceeds ``gates[count]`` (its chi-square gate), the group least consistent
    with the others is left out, one at a time (:func:`_exclude_inconsistent`). Inliers
    beyond ``doubt`` (a gross error with probability above ``DOUBT_PROBABILITY``) are doubtful:
    the posterior is the moment-matched mixture of the update with them (weight: the product
    of their inlier probabilities) and the update without them. The frame's log-likelihood
    under the hypothesis counts the inliers as Gaussian and the rejected groups under the
    heavy tail.

    Parameters
    ----------
    S, rho, Pxz, d2 : arrays
        From :func:`innovation_stats` or :func:`innovation_3d`.
    present : bool array (r, G)
    ok_sigma : bool array (r,)
        Whether the sigma points' factorisation succeeded.
    x, P : arrays (r, n), (r, n, n)
        The priors.
    d : int
        Dimension of a group.
    outlier_probability, outlier_scale : float
        The heavy-tailed component: its probability and its widening.
    threshold, doubt : float
        Squared residuals of the gate and of doubt (inf: none).
    gates : array (G + 1,)
        The joint NIS gate of k inlying groups (inf: no consistency check).
    min_information : float
        Least information about delta_L (1/rad^2) for an update to count.
    flag : int array
        Flag values in the order of ``FLAG_ORDER``.

    Returns
    -------
    x_post, P_post : arrays (r, n), (r, n, n)
    nis : array (r,)
        The NIS of the inliers (NaN where the update is not shown: unusable or
        uninformative).
    dof : int array (r,)
        Its degrees of freedom (0 where not shown).
    log_lik : array (r,)
        The frame's log-likelihood under each hypothesis (-1e300 where not finite).
    inlier : bool array (r, G)
    status : int array (r,)
        Flags of the update.
    rejected : int array (r,)
        Groups rejected as gross errors.
    done : bool array (r,)
        Whether the posterior replaces the prior.
    innovation_shown : bool array (r,)
        Whether the update is shown (usable and informative).
    """
    r, m = rho.shape
    n = x.shape[1]
    G = m // d
    x_post = np.empty((r, n))
    P_post = np.empty((r, n, n))
    nis_out = np.empty(r)
    dof = np.zeros(r, dtype=np.int64)
    log_lik = np.empty(r)
    inlier = np.zeros((r, G), dtype=np.bool_)
    status = np.zeros(r, dtype=np.int64)
    rejected = np.zeros(r, dtype=np.int64)
    done = np.zeros(r, dtype=np.bool_)
    shown = np.zeros(r, dtype=np.bool_)
    products = np.empty((n + 1, n + 1))
    alt_products = np.empty((n + 1, n + 1))
    x_alt = np.empty(n)
    P_alt = np.empty((n, n))
    diff = np.empty(n)
    Sm = np.empty((m, m))
    A = np.empty((n + 1, m))
    solved = np.empty((n + 1, m))
    keep = np.empty(m, dtype=np.bool_)
    fewer = np.empty(G, dtype=np.bool_)
    block = np.empty((d, d))
    work = np.empty((d, d))
    eye = np.empty((d, 1))
    log_2pi = math.log(2.0 * math.pi)
    per_group = math.log1p(-outlier_probability) - 0.5 * d * log_2pi
    flag_outlier, flag_held = flag[_OUTLIER], flag[_HELD]
    flag_repaired, flag_uninformative = flag[_REPAIRED], flag[_UNINFORMATIVE]
    for i in range(r):
        row_in = inlier[i]
        for g in range(G):
            row_in[g] = present[i, g] and d2[i, g] <= threshold
        logdet, ok_S = fuse_row(
            S[i], rho[i], Pxz[i], row_in, d, x[i], P[i], products, x_post[i], P_post[i],
            Sm, A, solved, keep,
        )  # fmt: skip
        count = 0
        for g in range(G):
            count += row_in[g]
        if count >= 2 and products[n, n] > gates[count]:
            _exclude_inconsistent(S[i], rho[i], row_in, d, threshold)
            logdet, ok_S = fuse_row(
                S[i], rho[i], Pxz[i], row_in, d, x[i], P[i], products, x_post[i],
                P_post[i], Sm, A, solved, keep,
            )  # fmt: skip
        count = 0
        for g in range(G):
            count += row_in[g]
        nis = products[n, n]
        # A doubtful inlier: the mixture of the update with it and the update without it.
        w = 1.0
        any_doubt = False
        for g in range(G):
            fewer[g] = row_in[g]
            if row_in[g] and d2[i, g] > doubt:
                any_doubt = True
                fewer[g] = False
                log_ratio = (
                    math.log(outlier_probability / (1.0 - outlier_probability))
                    - d * math.log(outlier_scale)
                    + 0.5 * (1.0 - outlier_scale**-2) * min(d2[i, g], 1e4)
                )
                w *= 1.0 / (1.0 + math.exp(min(log_ratio, 700.0)))
        if any_doubt:
            fuse_row(
                S[i], rho[i], Pxz[i], fewer, d, x[i], P[i], alt_products, x_alt, P_alt, Sm,
                A, solved, keep,
            )  # fmt: skip
            _mixture_row(w, x_post[i], P_post[i], x_alt, P_alt, x_post[i], P_post[i], diff)
        # The frame's likelihood under the hypothesis (weighs it against a restarted one).
        lik = count * per_group - 0.5 * (nis + logdet)
        outliers = 0
        for g in range(G):
            if present[i, g] and not row_in[g]:
                outliers += 1
                if outlier_probability > 0.0:
                    for a in range(d):
                        eye[a, 0] = 0.0
                        for b in range(d):
                            block[a, b] = S[i, g * d + a, g * d + b]
                    logdet_g = _lu_solve(block, eye, work)
                    lik += (
                        math.log(outlier_probability) - d * math.log(outlier_scale)
                        - 0.5 * d2[i, g] / outlier_scale**2 - 0.5 * (logdet_g + d * log_2pi)
                    )  # fmt: skip
        log_lik[i] = lik if math.isfinite(lik) else -1e300
        rejected[i] = outliers
        usable = ok_sigma[i] and ok_S and count > 0
        prior_var, post_var = P[i, 0, 0], P_post[i, 0, 0]
        post_ok = post_var > 0 and math.isfinite(x_post[i, 0])
        # The frame's information about delta_L (how much it shrank the variance) must
        # exceed the minimum: 1/post - 1/prior > min, i.e. prior - post > min prior post.
        informative = prior_var - post_var > min_information * prior_var * post_var
        settled = usable and post_ok
        done[i] = settled and informative
        uninformative = settled and not informative
        st = flag_outlier if outliers else 0
        if not (done[i] or uninformative):
            st |= flag_held
        if count > 0 and not (ok_S and post_ok):
            st |= flag_repaired
        if uninformative:
            st |= flag_uninformative | flag_held
        status[i] = st
        shown[i] = usable and not uninformative
        nis_out[i] = nis if shown[i] else math.nan
        dof[i] = d * count if shown[i] else 0
    return x_post, P_post, nis_out, dof, log_lik, inlier, status, rejected, done, shown




@numba.njit(cache=True, nogil=True)
def commit_update(b, h, done, x_post, P_post, log_lik, x, P, good_x, good_P, log_weight,
                  mismatch_scale, mismatch_decay):  # fmt: skip
    """Write the updated hypotheses (rows ``b``, ``h``) back, in place: the posterior where
    ``done`` (also as the last good state), the frame's log-likelihood added to every row's
    weight, and the model-mismatch inflation of each trial with a posterior brought back
    towards 1 by ``mismatch_decay`` (once per trial)."""
    B = x.shape[0]
    decayed = np.zeros(B, dtype=np.bool_)
    n = x.shape[2]
    for i in range(b.shape[0]):
        t, k = b[i], h[i]
        if done[i]:
            for a in range(n):
                x[t, k, a] = good_x[t, k, a] = x_post[i, a]
                for c in range(n):
                    P[t, k, a, c] = good_P[t, k, a, c] = P_post[i, a, c]
            if not decayed[t]:
                mismatch_scale[t] = 1.0 + mismatch_decay * (mismatch_scale[t] - 1.0)
                decayed[t] = True
        log_weight[t, k] += log_lik[i]


@numba.njit(cache=True, nogil=True)
def update_3d(
    b, h, x_all, P_all, L_all, factor_ok, good_x, good_P, log_weight, mismatch_scale,
    mismatch_decay, spread, c, JK, y, q, R_bar, scale, M, present, has_velocity, Wm, Wc,
    deviation, rate, outlier_probability, outlier_scale, threshold, doubt, gates,
    min_information, flag,
):  # fmt: skip
    """The update of hypotheses (rows ``b``, ``h``) with a 3-D frame, written back in place:
    their sigma points (the predict's factors ``L_all`` where ``factor_ok``, else a fresh
    factorisation), the innovation statistics
    (:func:`~tracker.estimators.ukf_kernels.innovation_3d`), the rules of
    :func:`gate_and_fuse` and the write-back of :func:`commit_update`.

    Returns ``(status, nis, dof, rejected, inlier, shown, rho)`` per row as
    :func:`gate_and_fuse` gives them (``rho``: the residuals, (r, 3G)).
    """
    r = b.shape[0]
    n = x_all.shape[2]
    G = c.shape[1]
    P, L, ok_sigma = row_factors(b, h, P_all, L_all, factor_ok)
    x = np.empty((r, n))
    rows_c = np.empty((r, G, 3))
    rows_JK = np.empty((r, G, 3, 5))
    rows_y = np.empty((r, G, 3))
    rows_q = np.empty(r)
    rows_R = np.empty((r, G, 3, 3))
    rows_M = np.empty((r, G, 3, 3))
    rows_scale = np.empty(r)
    rows_present = np.empty((r, G), dtype=np.bool_)
    for i in range(r):
        t = b[i]
        x[i] = x_all[t, h[i]]
        rows_c[i] = c[t]
        rows_JK[i] = JK[t]
        rows_y[i] = y[t]
        rows_q[i] = q[t, 0]
        rows_R[i] = R_bar[t]
        rows_M[i] = M[t]
        rows_scale[i] = scale[t]
        rows_present[i] = present[t]
    S, rho, Pxz, d2, _ = innovation_3d(
        x, L, spread, rows_c, rows_JK, rows_y, rows_q, rows_R, rows_scale, rows_M, Wm, Wc,
        deviation, rate, has_velocity,
    )  # fmt: skip
    x_post, P_post, nis, dof, log_lik, inlier, status, rejected, done, shown = gate_and_fuse(
        S, rho, Pxz, d2, rows_present, ok_sigma, x, P, 3, outlier_probability,
        outlier_scale, threshold, doubt, gates, min_information, flag,
    )  # fmt: skip
    commit_update(
        b, h, done, x_post, P_post, log_lik, x_all, P_all, good_x, good_P, log_weight,
        mismatch_scale, mismatch_decay,
    )  # fmt: skip
    return status, nis, dof, rejected, inlier, shown, rho


@numba.njit(cache=True, nogil=True)
def update_views(
    b, h, x_all, P_all, L_all, factor_ok, good_x, good_P, log_weight, mismatch_scale,
    mismatch_decay, spread, q_r, C, A, t, intrinsics, dist, pinhole, z, R, scale, present, Wm,
    Wc, outlier_probability, outlier_scale, threshold, doubt, gates, min_information, flag,
):  # fmt: skip
    """The update of hypotheses (rows ``b``, ``h``) with single views' points, written back
    in place, as :func:`update_3d` does it for a 3-D frame: their sigma points, each
    projected into its view (:func:`~tracker.estimators.measurement_kernels.
    view_projections`: ``q_r`` plus the angle, the points' model vectors ``C`` and cameras
    ``A``, ``t``, ``intrinsics``, ``dist``, ``pinhole``), the innovation statistics with the
    noise ``R`` times ``scale`` (:func:`~tracker.estimators.ukf_kernels.innovation_stats`),
    the rules of :func:`gate_and_fuse` and the write-back of :func:`commit_update`. The same
    kernels in the same order as those calls one by one, so the same numbers.

    Returns ``(status, nis, dof, rejected, inlier, shown, rho)`` per row as
    :func:`gate_and_fuse` gives them, and the least depth of a pinhole point, mm: when it is
    not positive nothing is written back (a point behind its camera; the caller says so).
    """
    r = b.shape[0]
    n = x_all.shape[2]
    G = C.shape[0]
    P, L, ok_sigma = row_factors(b, h, P_all, L_all, factor_ok)
    x = np.empty((r, n))
    for i in range(r):
        x[i] = x_all[b[i], h[i]]
    sigmas, offsets = sigma_rows(x, L, spread)
    n_sigma = sigmas.shape[1]
    angle = np.empty(r * n_sigma)
    for i in range(r):
        for k in range(n_sigma):
            angle[i * n_sigma + k] = q_r + sigmas[i, k, 0]
    points, least_depth = view_projections(angle, C, A, t, intrinsics, dist, pinhole)
    hs = points.reshape((r, n_sigma, 2 * G))
    rows_z = np.empty((r, 2 * G))
    noise = np.empty((r, G, 2, 2))
    rows_present = np.empty((r, G), dtype=np.bool_)
    for i in range(r):
        k = b[i]
        for g in range(G):
            rows_present[i, g] = present[k, g]
            for a in range(2):
                rows_z[i, 2 * g + a] = z[k, g, a]
                for c in range(2):
                    noise[i, g, a, c] = R[k, g, a, c] * scale[k]
    S, rho, Pxz, d2 = innovation_stats(hs, rows_z, offsets, noise, Wm, Wc, 2)
    x_post, P_post, nis, dof, log_lik, inlier, status, rejected, done, shown = gate_and_fuse(
        S, rho, Pxz, d2, rows_present, ok_sigma, x, P, 2, outlier_probability,
        outlier_scale, threshold, doubt, gates, min_information, flag,
    )  # fmt: skip
    if least_depth <= 0.0:
        return status, nis, dof, rejected, inlier, shown, rho, least_depth
    commit_update(
        b, h, done, x_post, P_post, log_lik, x_all, P_all, good_x, good_P, log_weight,
        mismatch_scale, mismatch_decay,
    )  # fmt: skip
    return status, nis, dof, rejected, inlier, shown, rho, least_depth


__all__ = ["FLAG_ORDER", "commit_update", "gate_and_fuse", "update_3d", "update_views"]
