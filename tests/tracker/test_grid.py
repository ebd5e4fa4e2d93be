"""The grid (point-mass) filter: the exact posterior on the circle, with the UKF's models.

Noise is simulated in {B} as in tests/tracker/test_ukf.py; seeds and trial counts are fixed.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig
from models.rotations import wrap_angle
from tests.tracker.test_ukf import BENT, DT_S, EXACT, simulate, view_frame
from tracker.estimators import make_estimator
from tracker.estimators.deviation import ShapeExpansion
from tracker.estimators.grid import GridFilter
from tracker.estimators.measurement import group_coefficients, trig_table
from tracker.estimators.ukf import BendingPlaneUKF, UKFSettings, observation_groups
from tracker.types import Flag, Observation


def run(estimator, frames):
    estimator.reset()
    return [estimator.step(frame) for frame in frames]


@pytest.mark.parametrize("delta_2", [0.0, np.pi / 2])
def test_one_frame_from_a_uniform_prior_is_the_closed_form(delta_2):
    """Low noise, exact model: the posterior of one frame is the closed form's Gaussian."""
    catheter = default_catheter(delta_2)
    frame = simulate(catheter, BENT, -2.2, np.random.default_rng(1), sigma_mm=0.05)[0]
    closed = make_estimator("body-positions", catheter).step(frame)
    estimate = GridFilter(catheter, UKFSettings(**EXACT), cells=4096).step(frame)
    assert estimate.valid and estimate.flags == Flag.NONE
    assert abs(wrap_angle(estimate.delta_L_rad - closed.delta_L_rad)) < 0.1 * closed.std_rad
    assert estimate.std_rad == pytest.approx(closed.std_rad, rel=0.05)


def test_one_frame_posterior_is_the_groups_trigonometric_cost():
    """No deviation, no heavy tail: the log posterior of one frame from a uniform prior is
    minus half the summed d^2 of its groups, the trigonometric polynomials of
    ``group_coefficients``, on every cell (up to a constant)."""
    catheter = default_catheter(np.pi / 2)
    frame = simulate(catheter, BENT, 2.9, np.random.default_rng(6), sigma_mm=3.0)[0]
    grid = GridFilter(catheter, UKFSettings(**EXACT), cells=512)
    grid.step(frame)
    groups, _ = observation_groups(ShapeExpansion(catheter), frame, np.asarray(frame.q))
    W = np.linalg.inv(groups.R_bar)
    cost = group_coefficients(groups.y, groups.c, W, groups.q_r)[0].sum(0) @ trig_table(grid.angles)
    log_p = np.log(grid.p)
    np.testing.assert_allclose(log_p - log_p.max(), -0.5 * (cost - cost.min()), atol=1e-9)


@pytest.mark.parametrize("center", [np.pi - 0.01, -np.pi, -np.pi + 0.004, 0.3, -2.0])
def test_moments_are_the_circular_mean_and_the_wrapped_spread(center):
    """Also for a posterior across the seam at +-pi, with mass on the far side too."""
    grid = GridFilter(default_catheter(), cells=256)
    p = np.exp(-0.5 * (wrap_angle(grid.angles - center) / 0.2) ** 2) + 1e-3
    grid.p = p / p.sum()
    mean, std = grid.moments()
    expected = np.angle(grid.p @ np.exp(1j * grid.angles))
    spread = wrap_angle(grid.angles - expected)
    assert abs(wrap_angle(mean - expected)) < 1e-12
    assert std**2 == pytest.approx(grid.p @ spread**2 + grid.cell_rad**2 / 12, rel=1e-12)


def test_prediction_convolves_and_moment_matches_the_deviation_means():
    """Without a measurement, a step convolves p with the random walk's wrapped normal (here
    as a matrix), mixes in a jump's uniform density and gives every cell the deviation mean
    of the convolved joint density (decayed with time; a jump lands on the prior mean 0)."""
    catheter = default_catheter()
    settings = UKFSettings(process_noise_rad2_s=0.5)
    grid = GridFilter(catheter, settings, cells=64)
    frame = simulate(catheter, BENT, 0.3, np.random.default_rng(3), sigma_mm=0.1)[0]
    grid.step(frame)
    assert grid.initialised
    rng = np.random.default_rng(0)
    p = rng.uniform(0.1, 1.0, grid.cells)
    grid.p = p / p.sum()
    grid.mu[:] = rng.normal(0.0, 0.1, (2, grid.cells))
    before_p, before_mu = grid.p.copy(), grid.mu.copy()
    dt = 0.2
    grid.step(Observation(time_s=frame.time_s + dt, q=frame.q))
    offsets = wrap_angle(grid.angles[None] - grid.angles[:, None])
    kernel = sum(np.exp(-0.5 * (offsets + 2 * np.pi * k) ** 2 / (0.5 * dt)) for k in (-1, 0, 1))
    kernel /= kernel.sum(axis=1, keepdims=True)
    jump = -np.expm1(-settings.jump_rate_per_s * dt)
    decay = np.exp(-settings.deviation_rate_per_s * dt)
    expected_p = (1 - jump) * kernel @ before_p + jump / grid.cells
    expected_mu = decay * (1 - jump) * (before_p * before_mu) @ kernel.T / expected_p
    np.testing.assert_allclose(grid.p, expected_p, rtol=1e-12)
    np.testing.assert_allclose(grid.mu, expected_mu, rtol=1e-10)


@pytest.mark.parametrize(
    "delta_2, mean_std, std_rel", [(0.0, 0.1, 0.03), (np.pi / 2, 0.5, 0.2)],
    ids=["planar", "non-planar"],
)
def test_grid_and_ukf_agree_where_the_posterior_is_gaussian(delta_2, mean_std, std_rel):
    """A moving, bent sequence: after the first frames both filters report the same mean
    (within ``mean_std`` stds) and std (within ``std_rel``). For a planar catheter the
    deviation moves the shape within the bending plane and the two agree closely; for a
    non-planar one it couples with the angle, and the grid's Rao-Blackwellisation is
    approximate (one deviation covariance for all cells, its Jacobian at the posterior
    mean's deviation, groups independent given the cell)."""
    catheter = default_catheter(delta_2)
    t = np.arange(60) * DT_S
    qs = np.array([0.2, 0.6, -0.5]) + t[:, None] * np.array([0.3, 0.2, 0.3])
    frames = simulate(catheter, qs, 0.8, np.random.default_rng(2), sigma_mm=0.3,
                      q_dots=np.broadcast_to([0.3, 0.2, 0.3], qs.shape))  # fmt: skip
    ukf = run(BendingPlaneUKF(catheter), frames)
    grid = run(GridFilter(catheter), frames)
    for a, b in zip(ukf[10:], grid[10:], strict=True):
        assert abs(wrap_angle(a.delta_L_rad - b.delta_L_rad)) < mean_std * b.std_rad
        assert a.std_rad == pytest.approx(b.std_rad, rel=std_rel)


def test_a_nearly_straight_frame_leaves_the_posterior_on_both_sides():
    """Deflectable by the deviation's prior, a nearly straight frame cannot tell a plane from
    its opposite: the posterior has two modes, and the grid does not report an estimate."""
    catheter = default_catheter()
    frames = simulate(catheter, np.broadcast_to([0.2, 0.05, 0.0], (10, 3)), 1.0,
                      np.random.default_rng(5), sigma_mm=0.1)  # fmt: skip
    grid = GridFilter(catheter)
    estimates = run(grid, frames)
    assert all(not e.valid and Flag.NOT_INITIALISED in e.flags for e in estimates)
    near = np.abs(wrap_angle(grid.angles - 1.0)) < 0.5
    opposite = np.abs(wrap_angle(grid.angles - 1.0 - np.pi)) < 0.5
    assert grid.p[near].sum() > 0.1 and grid.p[opposite].sum() > 0.1


def test_a_torsion_jump_moves_the_posterior():
    catheter = default_catheter()
    deltas = np.r_[np.full(20, 0.4), np.full(10, 0.4 + np.pi / 2)]
    frames = simulate(catheter, np.broadcast_to(BENT, (30, 3)), deltas, np.random.default_rng(8))
    estimates = run(GridFilter(catheter), frames)
    for e, truth in zip(estimates[21:], deltas[21:], strict=True):
        assert abs(wrap_angle(e.delta_L_rad - truth)) < 3 * e.std_rad < 0.1


def test_a_wrong_point_is_rejected_and_counted():
    catheter = default_catheter()
    frames = simulate(catheter, np.broadcast_to(BENT, (20, 3)), 0.7, np.random.default_rng(4))
    frames[15] = replace(frames[15], tip_b_mm=frames[15].tip_b_mm + np.array([8.0, -6.0, 0.0]))
    estimates = run(GridFilter(catheter), frames)
    assert Flag.OUTLIER_REJECTED in estimates[15].flags
    assert estimates[-1].rejected_outliers == 1
    assert abs(wrap_angle(estimates[15].delta_L_rad - 0.7)) < 3 * estimates[15].std_rad


def test_prediction_adds_the_process_variance():
    """Without measurements the posterior spreads by exactly the process variance."""
    catheter = default_catheter()
    settings = UKFSettings(process_noise_rad2_s=0.02, jump_rate_per_s=0.0, **EXACT)
    grid = GridFilter(catheter, settings, cells=4096)
    frame = simulate(catheter, BENT, 0.3, np.random.default_rng(3), sigma_mm=0.5)[0]
    first = grid.step(frame)
    later = grid.step(Observation(time_s=2.0, q=BENT))
    assert Flag.NO_MEASUREMENT in later.flags and Flag.HELD in later.flags
    assert later.delta_L_rad == pytest.approx(first.delta_L_rad, abs=1e-9)
    assert later.std_rad**2 == pytest.approx(first.std_rad**2 + 0.02 * 2.0, rel=1e-3)


def test_single_views_update_the_grid():
    catheter = default_catheter()
    rig = default_orthographic_rig()
    rng = np.random.default_rng(14)
    grid = GridFilter(catheter, cells=2048)
    first = grid.step(simulate(catheter, BENT, -1.1, rng, sigma_mm=3.0)[0])
    estimates = [grid.step(view_frame(catheter, rig.views[k % 2], BENT, -1.1, rng, k * DT_S, 0.5))
                 for k in range(1, 21)]  # fmt: skip
    assert estimates[-1].std_rad < first.std_rad / 3
    assert abs(wrap_angle(estimates[-1].delta_L_rad + 1.1)) < 3 * estimates[-1].std_rad


def test_cells_are_validated():
    with pytest.raises(ValueError, match="cells"):
        GridFilter(default_catheter(), cells=10)
