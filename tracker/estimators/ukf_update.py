"""The UKF update's results and the numerics of its group rules
(:class:`~tracker.estimators.ukf_core.FilterBank`): the solve with only the inlying groups,
the joint consistency of groups that each passed their gate, the mixture with the update
without a doubtful group, and the merging of hypotheses that agree (docs/design.md, "Joint
consistency and doubtful groups"). Rows are hypotheses; groups are of dimension d."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from tracker.estimators._linalg import block_index, spd_solve
from tracker.estimators.measurement import wrap
from tracker.estimators.ukf_settings import gate_threshold

Array = np.ndarray


@dataclass
class StepResult:
    """What a bank step reports per trial (arrays of length B)."""

    delta_L_rad: Array
    std_rad: Array
    flags: Array
    nis: Array
    nis_dof: Array
    rejected: Array
    radius_mm: Array
    innovation: list


@dataclass
class UpdateResult:
    """What the update did, per updated hypothesis (rows: trial ``b``, slot ``h``)."""

    b: Array
    h: Array
    status: Array
    nis: Array
    dof: Array
    rejected: Array
    inlier: Array  # (r, G)
    fused_tip: Array
    innovation: list | None


# A gated-in group whose posterior probability of being a gross error exceeds this is
# doubtful: the update is mixed with the update without it.
DOUBT_PROBABILITY = 1e-3
# Hypotheses whose delta_L differ by less than this many stds, with variances within this
# ratio, are one: merged by moments.
MERGE_DISTANCE = 0.1
MERGE_VARIANCE_RATIO = 1.2


def masked(S: Array, keep: Array) -> Array:
    """S (r, m, m) with the rows and columns not kept (r, m) zeroed and unit variance there:
    the entries left out become inert in a solve."""
    return S * (keep[:, :, None] & keep[:, None, :]) + np.where(keep, 0.0, 1.0)[
        :, :, None
    ] * np.eye(S.shape[-1])


def fuse_inliers(S: Array, rho: Array, Pxz: Array, inlier: Array, d: int):
    """The update's one solve with only the inlying groups (r, G) of dimension d: the others
    get zero rows and columns and unit noise. With ``A = [Pxz; rho^T]``, returns
    ``A S^-1 A^T = [[K Pxz^T, K rho], [., nis]]`` (gain ``K = Pxz S^-1``), log det S and
    which S factorised."""
    if not inlier.all():
        keep = np.repeat(inlier, d, axis=1)
        S = masked(S, keep)
        Pxz = Pxz * keep[:, None, :]
        rho = rho * keep
    A = np.concatenate((Pxz, rho[:, None]), axis=1)
    solved, logdet_S, ok_S = spd_solve(S, A.mT)
    return A @ solved, logdet_S, ok_S


def posterior(x: Array, P: Array, products: Array, n: int) -> tuple[Array, Array]:
    """The posterior mean (delta_L wrapped) and symmetric covariance from
    :func:`fuse_inliers`'s products."""
    x_post = x + products[:, :n, n]
    x_post[:, 0] = wrap(x_post[:, 0])
    P_post = P - products[:, :n, :n]
    return x_post, 0.5 * (P_post + P_post.mT)


def mixture(w: Array, x1: Array, P1: Array, x2: Array, P2: Array) -> tuple[Array, Array]:
    """Mean and covariance of the mixture ``w N(x1, P1) + (1 - w) N(x2, P2)`` (rows; the
    first component of the state an angle, the two close enough for a linear mean)."""
    diff = x1 - x2
    diff[:, 0] = wrap(diff[:, 0])
    x = x2 + w[:, None] * diff
    x[:, 0] = wrap(x[:, 0])
    spread = (w * (1.0 - w))[:, None, None] * diff[:, :, None] * diff[:, None, :]
    return x, w[:, None, None] * P1 + (1.0 - w)[:, None, None] * P2 + spread


@lru_cache(maxsize=64)
def joint_gates(probability: float, d: int, G: int) -> Array:
    """The chi-square gate of a joint residual of k groups of dimension d, for k = 0 .. G."""
    gates = np.array([gate_threshold(probability, max(d * k, 1)) for k in range(G + 1)])
    gates.flags.writeable = False  # shared by every caller through the cache
    return gates


@lru_cache(maxsize=64)
def doubt_threshold(d: int, outlier_probability: float, outlier_scale: float) -> float:
    """The squared residual beyond which a group is doubtful: its posterior probability of
    being a gross error (:func:`inlier_probability`) exceeds ``DOUBT_PROBABILITY``."""
    if outlier_probability <= 0.0:
        return math.inf
    log_odds = math.log(DOUBT_PROBABILITY / (1.0 - DOUBT_PROBABILITY)) - math.log(
        outlier_probability / (1.0 - outlier_probability)
    )
    return 2.0 * (log_odds + d * math.log(outlier_scale)) / (1.0 - outlier_scale**-2)


def exclude_inconsistent(
    S: Array, rho: Array, inlier: Array, rows: Array, d: int, threshold: float
) -> Array:
    """Inlying groups of ``rows`` whose residual *given the other inlying groups* exceeds the
    group threshold, left out one at a time (the worst first) while two remain.

    The residual of group g given the others is Gaussian with covariance
    ``((S^-1)_gg)^-1`` and mean zero under the model; its squared Mahalanobis length is
    ``e_g^T ((S^-1)_gg)^-1 e_g`` with ``e = S^-1 rho``: how much the joint NIS drops when g
    is left out."""
    inlier = inlier.copy()
    r, G = inlier.shape
    blocks = block_index(G, d)
    active = rows.copy()
    while active.any():
        keep = np.repeat(inlier, d, axis=1)
        S_inv = np.linalg.inv(masked(S, keep))
        e = (S_inv @ (rho * keep)[..., None])[..., 0].reshape(r, G, d)
        C = S_inv.reshape(r, -1)[:, blocks].reshape(r, G, d, d)
        given = (e * np.linalg.solve(C, e[..., None])[..., 0]).sum(-1)
        given = np.where(inlier, given, -np.inf)
        worst = np.argmax(given, axis=1)
        out = active & (given[np.arange(r), worst] > threshold)
        inlier[np.flatnonzero(out), worst[out]] = False
        active = out & (inlier.sum(-1) >= 2)
    return inlier


def merge_agreeing(x: Array, P: Array, log_weight: Array, active: Array, lead: Array) -> Array:
    """Merge into each trial's leading hypothesis ``lead`` (B,), in place, by moments and with
    the weights added, every hypothesis that has come to agree with it: delta_L within
    ``MERGE_DISTANCE`` stds and its variance within ``MERGE_VARIANCE_RATIO``. Both would
    follow the same data to the same place, and the mixture they make is one Gaussian to
    within those tolerances. States (B, H, n), covariances (B, H, n, n), log weights and
    activity (B, H); returns which (B, H) slots received a merge."""
    B, H = active.shape
    trials = np.arange(B)
    merged = np.zeros_like(active)
    for h in range(H):
        var, var_lead = P[:, h, 0, 0], P[trials, lead, 0, 0]
        diff = wrap(x[:, h, 0] - x[trials, lead, 0])
        ratio = var / np.where(var_lead > 0, var_lead, np.inf)
        same = (
            active[:, h]
            & (lead != h)
            & (diff * diff < MERGE_DISTANCE**2 * np.minimum(var, var_lead))
            & (ratio < MERGE_VARIANCE_RATIO)
            & (ratio * MERGE_VARIANCE_RATIO > 1.0)
        )
        if not same.any():
            continue
        b = np.flatnonzero(same)
        k = lead[b]
        total = np.logaddexp(log_weight[b, k], log_weight[b, h])
        share = np.exp(log_weight[b, k] - total)  # the leading one's
        x[b, k], P[b, k] = mixture(share, x[b, k], P[b, k], x[b, h], P[b, h])
        log_weight[b, k] = total
        active[b, h] = False
        log_weight[b, h] = -np.inf
        merged[b, k] = True
    return merged
