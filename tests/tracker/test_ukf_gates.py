"""The rules of ukf_core added for data the model does not explain: a doubtful group's update
mixed with the update without it (moments of a two-Gaussian mixture), and hypotheses that
have come to agree merged into one. Their effect on whole recordings is tested in
tests/replay/test_combined_recording.py."""

from __future__ import annotations

import math

import numpy as np

from tracker.estimators.ukf_core import FilterBank
from tracker.estimators.ukf_settings import UKFSettings
from tracker.estimators.ukf_update import mixture as _mixture


def test_the_mixture_of_two_gaussians_has_the_moments_of_samples():
    rng = np.random.default_rng(0)
    w = np.array([0.3])
    x1, x2 = np.array([[0.2, 1.0]]), np.array([[-0.1, -0.5]])
    P1 = np.array([[[0.01, 0.002], [0.002, 0.04]]])
    P2 = np.array([[[0.02, -0.001], [-0.001, 0.01]]])
    x, P = _mixture(w, x1, P1, x2, P2)
    n = 400_000
    pick = rng.random(n) < w[0]
    samples = np.where(pick[:, None], rng.multivariate_normal(x1[0], P1[0], n),
                       rng.multivariate_normal(x2[0], P2[0], n))  # fmt: skip
    np.testing.assert_allclose(x[0], samples.mean(0), atol=3e-3)
    np.testing.assert_allclose(P[0], np.cov(samples.T), atol=3e-3)


def test_the_mixture_mean_of_angles_is_taken_across_the_wrap():
    x, _ = _mixture(np.array([0.5]), np.array([[math.pi - 0.1]]), np.eye(1)[None] * 1e-4,
                    np.array([[-math.pi + 0.1]]), np.eye(1)[None] * 1e-4)  # fmt: skip
    assert abs(abs(x[0, 0]) - math.pi) < 1e-12  # on the wrap, not at 0


def _bank_with(x2: float, var2: float, weights=(0.9, 0.1)) -> FilterBank:
    bank = FilterBank(UKFSettings(), n_trials=2)
    n = bank.n
    bank.start(np.arange(2), np.array([0.5, 0.5]), np.array([0.01, 0.01]), np.zeros((2, 3)))
    bank.active[:, 1] = True
    bank.x[:, 1] = bank.x[:, 0]
    bank.P[:, 1] = bank.P[:, 0]
    bank.x[0, 1, 0] = x2
    bank.P[0, 1] = np.eye(n) * var2
    bank.P[1, 1, 0, 0] = 4.0 * bank.P[1, 0, 0, 0]  # trial 1: its second one four times wider
    bank.log_weight[:] = np.log(weights)
    return bank


def test_hypotheses_that_agree_are_merged_by_moments_and_others_kept():
    var = 0.01**2
    bank = _bank_with(0.5 + 0.02 * 0.01, var)  # 0.02 std apart, same variance
    before_x, before_P = bank.x[0].copy(), bank.P[0].copy()
    bank._normalise()
    assert bank.active[0].tolist() == [True, False]  # merged
    assert bank.active[1].tolist() == [True, True]  # variances 4x apart: two hypotheses
    expected_x, expected_P = _mixture(np.array([0.9]), before_x[None, 0], before_P[None, 0],
                                      before_x[None, 1], before_P[None, 1])  # fmt: skip
    np.testing.assert_allclose(bank.x[0, 0], expected_x[0], atol=1e-15)
    np.testing.assert_allclose(bank.P[0, 0], expected_P[0], atol=1e-18)
    assert bank.weights()[0, 0] == 1.0


def test_hypotheses_apart_by_more_than_the_merge_distance_are_kept():
    bank = _bank_with(0.5 + 0.5 * 0.01, 0.01**2)  # half a std apart
    bank._normalise()
    assert bank.active[0].tolist() == [True, True]
