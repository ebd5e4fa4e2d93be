"""The UKF update's results and the constants of its group rules
(:class:`~tracker.estimators.ukf_core.FilterBank`; the rules' arithmetic is compiled in
:func:`~tracker.estimators.ukf_kernels.gate_and_fuse`): the gates of the joint consistency of
groups that each passed their own, the threshold of doubt, and the merging of hypotheses
that agree (docs/design.md, "Joint consistency and doubtful groups"). Rows are hypotheses;
groups are of dimension d."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from tracker.estimators import ukf_kernels
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


def mixture(w: Array, x1: Array, P1: Array, x2: Array, P2: Array) -> tuple[Array, Array]:
    """Mean and covariance of the mixture ``w N(x1, P1) + (1 - w) N(x2, P2)`` (rows; the
    first component of the state an angle, the two close enough for a linear mean)."""
    c = np.ascontiguousarray
    return ukf_kernels.mixture_rows(c(w, dtype=float), c(x1), c(P1), c(x2), c(P2))


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
