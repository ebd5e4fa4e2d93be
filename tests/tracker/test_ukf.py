"""The bending-plane UKF: efficiency against the Cramer-Rao bound, consistency, robustness.

Measurement noise is simulated directly in {B} as Gaussian with covariance
``sigma^2 diag(1, 1, 0.5)`` (a reconstruction from two views is less noisy along z_b). All
Monte Carlo tests use fixed seeds and trial counts, so they are deterministic. Tests of the
filter's Gaussian machinery use ``EXACT``: the model exact (no deviation state, no model
error) and no heavy tail; the others use the default, robust settings. Sessions with
everything a lab meets are in tests/replay/test_robustness.py.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.stats import chi2

from models.bounds import crb_markers
from models.catheter import default_catheter
from models.imaging import default_orthographic_rig, default_pinhole_rig
from models.rotations import rot_y, rot_z, rotate_z, wrap_angle
from tracker.estimators import make_estimator
from tracker.estimators.ukf import BendingPlaneUKF, UKFSettings, sigma_sqrt, spd_inverse
from tracker.estimators.ukf_batch import run_ukf_batch
from tracker.types import Flag, Observation, ViewMeasurement

DELTA_2 = [0.0, np.pi / 2]
BENT = np.array([0.3, 0.8, 0.6])
NOISE_SHAPE = np.diag([1.0, 1.0, 0.5])
DT_S = 0.05
EXACT = dict(joint_error_mm=0.0, gain_error=0.0, joint_error_white_mm=0.0, outlier_probability=0.0)
QUIET = UKFSettings(process_noise_rad2_s=0.0, rotation_noise_gain_rad=0.0, **EXACT)


def noise_cov(sigma_mm: float) -> np.ndarray:
    return sigma_mm**2 * NOISE_SHAPE


def simulate(
    catheter,
    qs,
    deltas,
    rng,
    sigma_mm=1.0,
    q_dots=None,
    markers=True,
    velocity=False,
    t0_s=0.0,
):
    """Observations of a trajectory: tip, markers and finite-difference velocity in {B}.

    The velocity of frame k is (tip_k - tip_{k-1}) / dt of the *measured* tips, with its
    covariance (S + S) / dt^2 and its cross-covariance S / dt with tip_k; frame 0 has none.
    """
    qs = np.atleast_2d(qs)
    n = qs.shape[0]
    deltas = np.broadcast_to(deltas, (n,))
    cov = noise_cov(sigma_mm)
    shape = catheter.shape_vectors(qs)
    angle = qs[:, 0] + deltas
    tips = rotate_z(shape.c_tip_mm, angle) + rng.multivariate_normal(np.zeros(3), cov, size=n)
    n_markers = shape.c_markers_mm.shape[1]
    marker_noise = rng.multivariate_normal(np.zeros(3), cov, size=(n, n_markers))
    marker_points = rotate_z(shape.c_markers_mm, angle[:, None]) + marker_noise
    marker_cov = np.broadcast_to(cov, (n_markers, 3, 3)).copy()
    frames = []
    for k in range(n):
        kwargs = {}
        if markers:
            kwargs.update(markers_b_mm=marker_points[k], markers_cov_b=marker_cov)
        if q_dots is not None:
            kwargs.update(q_dot=np.atleast_2d(q_dots)[k])
        if velocity and k > 0:
            kwargs.update(
                velocity_b_mm_s=(tips[k] - tips[k - 1]) / DT_S,
                velocity_cov_b=2.0 * cov / DT_S**2,
                velocity_tip_cov_b=cov / DT_S,
            )
        frames.append(
            Observation(time_s=t0_s + k * DT_S, q=qs[k], tip_b_mm=tips[k], tip_cov_b=cov, **kwargs)
        )
    return frames


def run(ukf, frames):
    ukf.reset()
    return [ukf.step(frame) for frame in frames]


# ---------------------------------------------------------------------------- identities
def test_one_step_equals_filterpys_predict_and_update():
    """With the model exact and no heavy tail, a step of the filter (a bank of one) is
    filterpy's UnscentedKalmanFilter predict and update with the same sigma points, process
    noise and wrapped angles: the step-by-step reference of the rules' implementation."""
    catheter = default_catheter()
    settings = UKFSettings(process_noise_rad2_s=0.04, **EXACT)
    ukf = BendingPlaneUKF(catheter, settings)
    rng = np.random.default_rng(30)
    frames = simulate(catheter, np.broadcast_to(BENT, (6, 3)), 0.9, rng, sigma_mm=2.0)
    ukf.initialise(0.6, 0.3, time_s=0.0)
    points = MerweScaledSigmaPoints(1, alpha=1.0, beta=2.0, kappa=2.0)
    wrapped = lambda a, b: wrap_angle(np.subtract(a, b))  # noqa: E731

    def circular_mean(sigmas, weights):
        return np.array([np.arctan2(weights @ np.sin(sigmas[:, 0]), weights @ np.cos(sigmas[:, 0]))])

    reference = UnscentedKalmanFilter(
        dim_x=1, dim_z=6, dt=DT_S, hx=None, fx=lambda x, dt: x, points=points,
        x_mean_fn=circular_mean, residual_x=wrapped,
    )  # fmt: skip
    reference.x, reference.P = np.array([0.6]), np.array([[0.09]])
    shape = catheter.shape_vectors(BENT)
    c = np.vstack([shape.c_tip_mm, shape.c_markers_mm])
    for frame in frames[1:]:
        estimate = ukf.step(frame)
        reference.Q = np.array([[0.04 * DT_S]])
        reference.predict()
        z = np.concatenate([frame.tip_b_mm, frame.markers_b_mm.ravel()])
        R = np.kron(np.eye(2), noise_cov(2.0))
        reference.update(z, R=R, hx=lambda x: rotate_z(c, BENT[0] + x[0]).ravel())
        assert estimate.delta_L_rad == pytest.approx(wrap_angle(reference.x[0]), abs=1e-12)
        assert estimate.std_rad == pytest.approx(np.sqrt(reference.P[0, 0]), rel=1e-10)
        nis = reference.y @ np.linalg.solve(reference.S, reference.y)
        assert estimate.nis == pytest.approx(nis, rel=1e-9) and estimate.nis_dof == 6


@pytest.mark.parametrize("delta_2", DELTA_2)
@pytest.mark.parametrize("kind", ["tip-position", "body-positions"])
def test_one_update_from_a_wide_prior_matches_the_closed_form_fisher_std(delta_2, kind):
    """Low noise (0.05 mm, near linear): a prior of std 0.2 rad (80 x the frame's std) updated
    once gives the per-frame closed-form result, std within 3 % and mean within 0.2 std."""
    catheter = default_catheter(delta_2)
    rng = np.random.default_rng(12)
    frame = simulate(catheter, BENT, 1.0, rng, sigma_mm=0.05, markers=kind == "body-positions")[0]
    if kind == "body-positions":
        frame = replace(frame, tip_b_mm=None)
    closed = make_estimator(kind, catheter).step(frame)
    ukf = BendingPlaneUKF(catheter, QUIET)
    ukf.initialise(1.0, 0.2, time_s=frame.time_s)
    estimate = ukf.step(frame)
    assert estimate.flags == Flag.NONE
    assert estimate.std_rad == pytest.approx(closed.std_rad, rel=0.03)
    assert abs(wrap_angle(estimate.delta_L_rad - closed.delta_L_rad)) < 0.2 * closed.std_rad


def test_initial_state_is_the_closed_form_of_the_first_frame():
    """The model vectors come from the shape expansion (to about 1e-5 mm), hence 1e-6 rad."""
    catheter = default_catheter(np.pi / 2)
    frame = simulate(catheter, BENT, 2.9, np.random.default_rng(2), markers=False)[0]
    first = BendingPlaneUKF(catheter, UKFSettings(**EXACT)).step(frame)
    closed = make_estimator("tip-position", catheter).step(frame)
    assert first.delta_L_rad == pytest.approx(closed.delta_L_rad, abs=1e-6)
    assert first.std_rad == pytest.approx(closed.std_rad, rel=1e-4)


def test_rate_state_prediction_matches_the_linear_kalman_filter():
    """With include_rate the process model is linear: P' = F P F^T + Q exactly."""
    catheter = default_catheter()
    settings = UKFSettings(
        include_rate=True,
        process_noise_rad2_s=0.01,
        rate_process_noise_rad2_s3=0.2,
        initial_rate_std_rad_s=0.3,
    )
    ukf = BendingPlaneUKF(catheter, settings)
    ukf.initialise(0.5, 0.1, time_s=0.0)
    P0 = ukf.covariance[:2, :2]
    estimate = ukf.step(Observation(time_s=0.2, q=BENT))
    assert Flag.NO_MEASUREMENT in estimate.flags
    dt = 0.2
    F = np.array([[1.0, dt], [0.0, 1.0]])
    qa = settings.rate_process_noise_rad2_s3
    Q = np.array([[0.01 * dt + qa * dt**3 / 3, qa * dt**2 / 2], [qa * dt**2 / 2, qa * dt]])
    np.testing.assert_allclose(ukf.covariance[:2, :2], F @ P0 @ F.T + Q, rtol=1e-12, atol=1e-15)
    assert ukf.state[0] == pytest.approx(0.5)


def test_sigma_sqrt_and_inverse_are_cholesky_with_documented_jitter():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    A = A @ A.T + 0.1 * np.eye(6)
    U = sigma_sqrt(A)
    np.testing.assert_allclose(U.T @ U, A, rtol=1e-12, atol=1e-12)
    assert np.allclose(U, np.triu(U))
    np.testing.assert_allclose(spd_inverse(A), np.linalg.inv(A), rtol=1e-9, atol=1e-12)
    singular = np.array([[1.0, 1.0], [1.0, 1.0]])  # PSD, rank one: the jitter makes it PD
    U = sigma_sqrt(singular)
    np.testing.assert_allclose(U.T @ U, singular, atol=1e-8)
    with pytest.raises(np.linalg.LinAlgError):
        sigma_sqrt(np.array([[1.0, 0.0], [0.0, -1.0]]))


# ---------------------------------------------------------------------------- statistics
def simulate_runs(catheter, qs, deltas, rng, n_runs, sigma_mm=1.0):
    """``n_runs`` noisy runs of a trajectory as the arrays of ``run_ukf_batch`` (tips (B, T, 3),
    markers (B, T, M, 3)), deltas (T,) or (B, T)."""
    n = qs.shape[0]
    deltas = np.broadcast_to(deltas, (n_runs, n))
    shape = catheter.shape_vectors(qs)
    angle = qs[:, 0] + deltas
    cov = noise_cov(sigma_mm)
    root = np.linalg.cholesky(cov)
    tips = rotate_z(shape.c_tip_mm, angle) + rng.normal(size=(n_runs, n, 3)) @ root.T
    markers = rotate_z(shape.c_markers_mm, angle[..., None])
    markers = markers + rng.normal(size=markers.shape) @ root.T
    return tips, markers, cov


@pytest.mark.parametrize(
    "delta_2, settings",
    [(0.0, QUIET), (np.pi / 2, QUIET), (0.0, UKFSettings(process_noise_rad2_s=0.0))],
    ids=["planar", "non-planar", "planar, model error on"],
)
def test_final_error_reaches_the_cramer_rao_bound_over_100_frames(delta_2, settings):
    """RMS of the final estimate over 200 runs of N = 100 frames <= 1.3 CRB / sqrt(N), and
    the reported std is the bound. With the model error on, a planar catheter loses nothing:
    the deviation moves the shape within its bending plane. (The runs go through
    run_ukf_batch: the same filter, trial-batched, tests/tracker/test_ukf_batch.py.)"""
    catheter = default_catheter(delta_2)
    n_frames, n_runs, truth = 100, 200, 0.5
    qs = np.broadcast_to(BENT, (n_frames, 3))
    tips, markers, cov = simulate_runs(catheter, qs, truth, np.random.default_rng(11), n_runs)
    time = np.arange(n_frames) * DT_S
    result = run_ukf_batch(catheter, settings, time, qs, None, tips, cov, markers, cov)
    assert result.valid[:, -1].all()
    assert not np.any(result.flags[:, -1] & Flag.HELD.value)
    errors = wrap_angle(result.delta_L_rad[:, -1] - truth)
    bound = float(crb_markers(catheter, BENT, truth, noise_cov(1.0))) / np.sqrt(n_frames)
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert rms <= 1.3 * bound
    assert np.median(result.std_rad[:, -1]) == pytest.approx(bound, rel=0.05)


def test_nees_and_nis_lie_in_their_chi_square_bands():
    """200 runs of 60 frames: the base turns, delta_L random-walks with the modelled noise.

    NIS: innovations are white, so the sum over all runs and frames is chi-square with the
    summed measurement dimensions. NEES: errors are correlated in time within a run, so the
    time-averaged NEES is tested against the band of 200 independent runs (dof 200), which
    is conservative for a time average.
    """
    catheter = default_catheter(np.pi / 2)
    settings = UKFSettings(process_noise_rad2_s=2e-3, rotation_noise_gain_rad=5e-3, **EXACT)
    n_frames, n_runs = 60, 200
    t = np.arange(n_frames) * DT_S
    q_dot = np.array([0.8, 0.5, -0.4])
    qs = np.array([0.3, 0.2, 0.9]) + t[:, None] * q_dot
    intensity = settings.process_noise_rad2_s + settings.rotation_noise_gain_rad * q_dot[0]
    rng = np.random.default_rng(5)
    steps = rng.normal(0.0, np.sqrt(intensity * DT_S), (n_runs, n_frames))
    steps[:, 0] = rng.uniform(-np.pi, np.pi, n_runs)
    deltas = np.cumsum(steps, axis=1)
    tips, markers, cov = simulate_runs(catheter, qs, deltas, rng, n_runs)
    q_dots = np.broadcast_to(q_dot, qs.shape)
    result = run_ukf_batch(catheter, settings, t, qs, q_dots, tips, cov, markers, cov)
    assert result.valid.all()
    errors = wrap_angle(result.delta_L_rad - deltas)
    nees_runs = np.mean(errors**2 / result.std_rad**2, axis=1)
    nees_low, nees_high = chi2.ppf([0.025, 0.975], n_runs) / n_runs
    assert nees_low <= np.mean(nees_runs) <= nees_high
    shown = np.isfinite(result.nis)
    nis_low, nis_high = chi2.ppf([0.025, 0.975], result.nis_dof[shown].sum())
    assert nis_low <= result.nis[shown].sum() <= nis_high


def velocity_comparison(settings, frames_for_run, n_runs, rng, truth):
    """Paired runs with and without velocity: per-run MSE differences and velocity use."""
    catheter = default_catheter(np.pi / 2)
    with_velocity = BendingPlaneUKF(catheter, settings)
    position_only = BendingPlaneUKF(catheter, replace(settings, use_velocity=False))
    diffs, fused = [], []
    for _ in range(n_runs):
        frames = frames_for_run(catheter, rng)
        a, b = run(with_velocity, frames), run(position_only, frames)
        fused.append([e.nis_dof == b_e.nis_dof + 3 for e, b_e in zip(a, b, strict=True)])
        err_a = wrap_angle(np.array([e.delta_L_rad for e in a[10:]]) - truth)
        err_b = wrap_angle(np.array([e.delta_L_rad for e in b[10:]]) - truth)
        diffs.append(np.mean(err_a**2) - np.mean(err_b**2))
    return np.array(diffs), np.array(fused)


MOVING_Q_DOT = np.array([1.0, 0.3, -0.3])  # base turning at 1 rad/s


def moving_joints(n_frames):
    t = np.arange(n_frames) * DT_S
    qs = np.array([0.0, 0.5, 0.6]) + t[:, None] * MOVING_Q_DOT
    return qs, np.broadcast_to(MOVING_Q_DOT, qs.shape)


def test_a_finite_difference_velocity_is_offered_after_a_rejected_tip_and_gated_out():
    """Velocities (tip_t - tip_{t-1}) / dt of the measured tips, with their cross-covariance.

    Decorrelated from this frame's tip, such a velocity measures the previous tip, so it is
    offered only after a frame whose tip was not fused. Every 6th frame the tip is wrongly
    segmented (10 mm off): its group is rejected (the marker is fused), the next frame
    offers the velocity, which repeats the wrong tip, and its own gate rejects it. Paired
    runs: the error with velocity is the error without.
    """
    n_frames, n_runs, truth = 80, 40, -2.0
    qs, q_dots = moving_joints(n_frames)
    cov = noise_cov(0.2)

    def frames_for_run(catheter, rng):
        frames = simulate(catheter, qs, truth, rng, sigma_mm=0.2, q_dots=q_dots)
        for k in range(6, n_frames, 6):
            frames[k] = replace(frames[k], tip_b_mm=frames[k].tip_b_mm + 10.0)
        return [frames[0]] + [
            replace(now, velocity_b_mm_s=(now.tip_b_mm - before.tip_b_mm) / DT_S,
                    velocity_cov_b=2.0 * cov / DT_S**2, velocity_tip_cov_b=cov / DT_S)
            for before, now in zip(frames[:-1], frames[1:], strict=True)
        ]  # fmt: skip

    settings = UKFSettings(process_noise_rad2_s=1e-4, rotation_noise_gain_rad=1e-4)
    catheter = default_catheter(np.pi / 2)
    frames = frames_for_run(catheter, np.random.default_rng(20))
    estimates = run(BendingPlaneUKF(catheter, settings), frames)
    after = np.zeros(n_frames, dtype=bool)
    after[7::6] = True
    assert all(Flag.OUTLIER_REJECTED in e.flags for e in np.array(estimates)[after])
    assert estimates[-1].rejected_outliers == 2 * ((n_frames - 1) // 6)
    diffs, fused = velocity_comparison(
        settings, frames_for_run, n_runs, np.random.default_rng(21), truth
    )
    assert not np.any(fused)
    np.testing.assert_allclose(diffs, 0.0, atol=1e-15)


def test_an_independent_velocity_is_fused_every_frame_and_helps():
    """A velocity whose noise is independent of earlier frames (correlated with this frame's
    tip through velocity_tip_cov_b) is fused in every frame and lowers the error."""
    n_frames, n_runs, truth = 80, 100, -2.0
    qs, q_dots = moving_joints(n_frames)
    cov = noise_cov(1.0)

    shape = default_catheter(np.pi / 2).shape_vectors(qs, q_dots)
    tips_true = rotate_z(shape.c_tip_mm, qs[:, 0] + truth)
    velocities_true = rotate_z(shape.u_tip_mm_s, qs[:, 0] + truth)

    def frames_for_run(catheter, rng):
        frames = simulate(catheter, qs, truth, rng, q_dots=q_dots)
        tip_noise = np.array([f.tip_b_mm for f in frames]) - tips_true
        own_noise = rng.multivariate_normal(np.zeros(3), cov, size=n_frames)
        velocities = velocities_true + (0.5 * tip_noise + own_noise) / DT_S
        return [
            replace(
                f,
                velocity_b_mm_s=v,
                velocity_cov_b=1.25 * cov / DT_S**2,
                velocity_tip_cov_b=0.5 * cov / DT_S,
            )
            for f, v in zip(frames, velocities, strict=True)
        ]

    settings = UKFSettings(
        process_noise_rad2_s=1e-4, rotation_noise_gain_rad=1e-4, velocity_is_finite_difference=False
    )
    diffs, fused = velocity_comparison(
        settings, frames_for_run, n_runs, np.random.default_rng(22), truth
    )
    assert np.mean(fused[:, 1:]) > 0.98
    assert diffs.mean() <= 3.0 * diffs.std(ddof=1) / np.sqrt(n_runs)
    assert diffs.mean() < 0.0


# ---------------------------------------------------------------------------- tracking
@pytest.mark.parametrize("include_rate", [False, True])
def test_tracks_a_drift_through_the_wrap_without_a_two_pi_jump(include_rate):
    catheter = default_catheter()
    settings = UKFSettings(
        process_noise_rad2_s=0.01, include_rate=include_rate, rate_process_noise_rad2_s3=0.05
    )
    ukf = BendingPlaneUKF(catheter, settings)
    n_frames = 80
    deltas = wrap_angle(2.6 + 0.3 * np.arange(n_frames) * DT_S)  # crosses +pi at frame ~36
    qs = np.broadcast_to(BENT, (n_frames, 3))
    estimates = run(ukf, simulate(catheter, qs, deltas, np.random.default_rng(3), sigma_mm=0.5))
    errors = wrap_angle(np.array([e.delta_L_rad for e in estimates]) - deltas)
    stds = np.array([e.std_rad for e in estimates])
    assert np.all(np.abs(errors) < 4.0 * stds)
    assert np.max(np.abs(errors)) < 0.1
    estimate_values = np.array([e.delta_L_rad for e in estimates])
    assert np.all((estimate_values >= -np.pi) & (estimate_values < np.pi))
    assert estimate_values[0] > 2.5 and estimate_values[-1] < -2.4  # truth ends at -2.498
    if include_rate:
        assert ukf.state[1] == pytest.approx(0.3, abs=0.15)


def test_a_torsion_jump_with_the_base_still_is_followed_at_once():
    """A 90 degree jump rejects the whole frame against the held estimate; its closed form is
    informative and consistent, so a restarted hypothesis is weighed against the held one
    (prior: the jump probability with the base still) and wins on the first frame, with a
    std that covers the truth."""
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter)
    n_before, n_after = 30, 20
    deltas = np.r_[np.full(n_before, 0.4), np.full(n_after, 0.4 + np.pi / 2)]
    qs = np.broadcast_to(BENT, (n_before + n_after, 3))
    estimates = run(ukf, simulate(catheter, qs, deltas, np.random.default_rng(8)))
    for e, truth in zip(estimates[n_before:], deltas[n_before:], strict=True):
        assert abs(wrap_angle(e.delta_L_rad - truth)) < 3.0 * e.std_rad
        assert e.std_rad < 0.05
    assert ukf.hypotheses == 1


def test_a_single_wrong_point_is_rejected_counted_and_the_rest_fused():
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter)
    rng = np.random.default_rng(4)
    frames = simulate(catheter, np.broadcast_to(BENT, (30, 3)), 0.7, rng)
    direction = rng.normal(size=3)
    # A wrong segmentation: the tip 10 mm away from where it is.
    frames[20] = replace(frames[20], tip_b_mm=frames[20].tip_b_mm + 10.0 * direction
                         / np.linalg.norm(direction))  # fmt: skip
    estimates = run(ukf, frames)
    rejected = estimates[20]
    assert Flag.OUTLIER_REJECTED in rejected.flags and Flag.HELD not in rejected.flags
    assert rejected.rejected_outliers == 1 and rejected.nis_dof == 3  # the marker alone
    assert rejected.std_rad < 1.1 * estimates[19].std_rad  # the marker alone adds little
    assert abs(wrap_angle(rejected.delta_L_rad - 0.7)) < 3 * rejected.std_rad
    assert all(Flag.OUTLIER_REJECTED not in e.flags for e in estimates[21:])
    assert estimates[-1].rejected_outliers == 1


def test_a_frame_of_inconsistent_wrong_points_is_held():
    """Tip and marker both wrong, in unrelated directions: no rotation explains them, so no
    hypothesis starts from them, and the estimate holds."""
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter)
    frames = simulate(catheter, np.broadcast_to(BENT, (25, 3)), 0.7, np.random.default_rng(7))
    markers = frames[20].markers_b_mm + np.array([[0.0, -12.0, 5.0]])
    frames[20] = replace(frames[20], tip_b_mm=frames[20].tip_b_mm + np.array([9.0, 4.0, -3.0]),
                         markers_b_mm=markers)  # fmt: skip
    estimates = run(ukf, frames)
    held = estimates[20]
    assert Flag.OUTLIER_REJECTED in held.flags and Flag.HELD in held.flags
    assert held.delta_L_rad == pytest.approx(estimates[19].delta_L_rad, abs=1e-12)
    assert held.rejected_outliers == 2 and ukf.hypotheses == 1


# ---------------------------------------------------------------------------- observability
def test_near_straight_predicts_only_std_grows_and_estimate_holds():
    catheter = default_catheter(np.pi / 2)
    ukf = BendingPlaneUKF(catheter, UKFSettings(process_noise_rad2_s=0.02))
    rng = np.random.default_rng(6)
    bent = simulate(catheter, np.broadcast_to(BENT, (20, 3)), 1.2, rng)
    straight_q = np.array([[0.3, 1e-4 * (-1) ** k, 0.0] for k in range(40)])
    straight = simulate(catheter, straight_q, 1.2, rng, t0_s=bent[-1].time_s + DT_S)
    estimates = run(ukf, bent + straight)
    held = estimates[20:]
    assert all(Flag.UNINFORMATIVE in e.flags and Flag.HELD in e.flags for e in held)
    assert all(e.delta_L_rad == estimates[19].delta_L_rad for e in held)
    stds = np.array([estimates[19].std_rad] + [e.std_rad for e in held])
    assert np.all(np.diff(stds) > 0)
    assert stds[-1] <= ukf.settings.max_std_rad
    assert all(e.informative_radius_mm < 0.01 for e in held)


def test_std_growth_is_capped():
    catheter = default_catheter()
    settings = UKFSettings(process_noise_rad2_s=5.0)
    ukf = BendingPlaneUKF(catheter, settings)
    frames = simulate(
        catheter,
        np.array([[0.0, 0.8, 0.6]] + [[0.0, 0.0, 0.0]] * 50),
        0.0,
        np.random.default_rng(0),
    )
    stds = [e.std_rad for e in run(ukf, frames)]
    assert max(stds) == pytest.approx(settings.max_std_rad)
    assert np.all(np.diff(stds) >= -1e-12)


def test_not_initialised_until_the_first_informative_frame():
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter)
    qs = np.array([[0.1, 0.0, 0.0]] * 5 + [list(BENT)] * 5)
    estimates = run(ukf, simulate(catheter, qs, -0.3, np.random.default_rng(1)))
    for e in estimates[:5]:
        assert Flag.NOT_INITIALISED in e.flags and Flag.UNINFORMATIVE in e.flags
        assert np.isnan(e.delta_L_rad) and not e.valid
    first = estimates[5]
    assert first.valid and first.flags == Flag.NONE
    # The first estimate is the global closed form of that frame's data, with its Fisher std.
    closed = make_estimator("body-positions", catheter).step(
        replace(simulate(catheter, BENT, -0.3, np.random.default_rng(99))[0], tip_b_mm=None)
    )
    assert first.std_rad < 2 * closed.std_rad
    assert abs(wrap_angle(first.delta_L_rad + 0.3)) < 4 * first.std_rad


def test_a_nearly_straight_frame_never_starts_the_filter():
    """Bent 2 mm at the tip but deflected by a joint deviation of 0.1 mm (prior 0.1 mm): the
    frame cannot tell the plane from its opposite, so it starts nothing."""
    catheter = default_catheter()
    q = np.array([0.2, 0.05, 0.0])
    frames = simulate(catheter, np.broadcast_to(q, (20, 3)), 1.0, np.random.default_rng(5),
                      sigma_mm=0.1)  # fmt: skip
    estimates = run(BendingPlaneUKF(catheter), frames)
    assert all(not e.valid and Flag.NOT_INITIALISED in e.flags for e in estimates)
    assert all(Flag.UNINFORMATIVE in e.flags for e in estimates)


# ---------------------------------------------------------------------------- missing data
def test_missing_or_nan_measurements_give_predict_only_steps():
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter, UKFSettings(process_noise_rad2_s=1e-3))
    frames = simulate(catheter, np.broadcast_to(BENT, (15, 3)), 0.2, np.random.default_rng(9))
    nan = np.full(3, np.nan)
    frames[10] = replace(frames[10], tip_b_mm=nan,
                         markers_b_mm=np.full_like(frames[10].markers_b_mm, np.nan))  # fmt: skip
    frames[11] = replace(frames[11], tip_b_mm=None, markers_b_mm=None)
    frames[12] = replace(frames[12], tip_cov_b=np.full((3, 3), np.nan), markers_b_mm=None)
    estimates = run(ukf, frames)
    for k in (10, 11, 12):
        e = estimates[k]
        assert Flag.NO_MEASUREMENT in e.flags and Flag.HELD in e.flags
        assert e.valid and e.innovation is None
        assert e.delta_L_rad == estimates[9].delta_L_rad
        assert e.std_rad > estimates[k - 1].std_rad
    assert estimates[13].flags == Flag.NONE and estimates[13].std_rad < estimates[12].std_rad


def test_partially_missing_markers_update_with_what_is_there():
    catheter = default_catheter(marker_arclengths_mm=(6.5, 13.0))
    ukf = BendingPlaneUKF(catheter)
    frames = simulate(catheter, np.broadcast_to(BENT, (12, 3)), 0.2, np.random.default_rng(10))
    markers = frames[10].markers_b_mm.copy()
    markers[0] = np.nan
    frames[10] = replace(frames[10], markers_b_mm=markers)
    frames[11] = replace(frames[11], tip_b_mm=np.full(3, np.nan))
    estimates = run(ukf, frames)
    for e in estimates[10:]:
        assert e.flags == Flag.PARTIAL and e.valid
    assert estimates[10].nis_dof == 6 and estimates[11].nis_dof == 6
    assert estimates[10].std_rad < estimates[9].std_rad


def test_a_non_positive_definite_covariance_is_repaired_never_nan():
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter, UKFSettings(include_rate=True))
    frames = simulate(catheter, np.broadcast_to(BENT, (10, 3)), 0.3, np.random.default_rng(3))
    estimates = [ukf.step(f) for f in frames[:5]]
    # What no predict can factorise (as after a numerically broken update).
    bad = np.diag(np.diag(ukf.covariance))
    bad[0, 1] = bad[1, 0] = 1.0
    ukf._bank.P[0, ukf._bank.leading()[0]] = bad
    repaired = ukf.step(frames[5])
    assert Flag.COVARIANCE_REPAIRED in repaired.flags and repaired.valid
    estimates += [ukf.step(f) for f in frames[6:]]
    assert np.all(np.linalg.eigvalsh(ukf.covariance) > 0)
    assert abs(wrap_angle(estimates[-1].delta_L_rad - 0.3)) < 3 * estimates[-1].std_rad


# ---------------------------------------------------------------------------- single views
RIGS = {"orthographic": (default_orthographic_rig, 0.5), "pinhole": (default_pinhole_rig, 1.0)}
R_W_B = rot_z(0.4) @ rot_y(0.3)
O_B_W = np.array([5.0, -3.0, 20.0])


def view_frame(catheter, view, q, delta_L, rng, time_s, sigma):
    """One view's segmented tip and markers (point_index -1 and 0..n-1), noise sigma (mm or px)."""
    points_b = np.vstack(
        [
            catheter.tip(q, delta_L)[None],
            catheter.backbone(q, delta_L, catheter.marker_arclengths_mm),
        ]
    )
    uv = view.project(points_b @ R_W_B.T + O_B_W)
    uv = uv + rng.normal(0.0, sigma, uv.shape)
    measurement = ViewMeasurement(
        view=view,
        R_w_b=R_W_B,
        o_b_w_mm=O_B_W,
        uv=uv,
        cov=np.broadcast_to(sigma**2 * np.eye(2), (len(uv), 2, 2)).copy(),
        point_index=np.arange(-1, points_b.shape[0] - 1),
    )
    return Observation(time_s=time_s, q=q, views=(measurement,))


@pytest.mark.parametrize("delta_2", DELTA_2)
@pytest.mark.parametrize("rig_kind", sorted(RIGS))
def test_single_view_updates_reduce_the_std_and_converge(delta_2, rig_kind):
    """A poor 3-D start (5 mm noise), then 60 frames from alternating, unsynchronised views."""
    make_rig, sigma = RIGS[rig_kind]
    rig = make_rig()
    catheter = default_catheter(delta_2)
    ukf = BendingPlaneUKF(catheter, QUIET)
    rng = np.random.default_rng(14)
    truth = -1.1
    first = simulate(catheter, BENT, truth, rng, sigma_mm=5.0)[0]
    estimates = [ukf.step(first)]
    assert estimates[0].valid
    views = rig.views
    for k in range(1, 61):
        view = views[k % 2]
        q = BENT + np.array([0.02 * k, 0.0, 0.0])
        estimates.append(ukf.step(view_frame(catheter, view, q, truth, rng, k * DT_S, sigma)))
    stds = np.array([e.std_rad for e in estimates])
    assert np.all(np.diff(stds) < 0)
    dof = 2 * (1 + len(catheter.marker_arclengths_mm))  # tip and markers, 2-D each
    assert all(e.flags == Flag.NONE and e.nis_dof == dof for e in estimates[1:])
    assert stds[-1] < stds[0] / 5
    assert abs(wrap_angle(estimates[-1].delta_L_rad - truth)) < 3 * stds[-1]


def test_a_single_view_does_not_initialise_the_filter():
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter)
    view = default_orthographic_rig().views[0]
    frame = view_frame(catheter, view, BENT, 0.5, np.random.default_rng(0), 0.0, sigma=0.5)
    estimate = ukf.step(frame)
    assert Flag.NOT_INITIALISED in estimate.flags and not estimate.valid


# ---------------------------------------------------------------------------- settings, misc
def test_online_noise_scale_finds_an_underestimated_segmentation_noise():
    """True noise 2 mm, assumed 1 mm: the covariance scale converges towards 4."""
    catheter = default_catheter()
    ukf = BendingPlaneUKF(
        catheter, UKFSettings(estimate_noise=True, process_noise_rad2_s=1e-4, **EXACT)
    )
    rng = np.random.default_rng(15)
    frames = simulate(catheter, np.broadcast_to(BENT, (400, 3)), 0.0, rng, sigma_mm=2.0)
    assumed = noise_cov(1.0)
    frames = [
        replace(f, tip_cov_b=assumed,
                markers_cov_b=np.broadcast_to(assumed, f.markers_cov_b.shape).copy())
        for f in frames
    ]  # fmt: skip
    estimates = run(ukf, frames)
    assert ukf.noise_scale == pytest.approx(4.0, rel=0.3)
    errors = [wrap_angle(e.delta_L_rad) for e in estimates[200:]]
    stds = [e.std_rad for e in estimates[200:]]
    assert np.sqrt(np.mean(np.square(errors))) < 1.5 * np.mean(stds)


def test_make_estimator_builds_the_filters():
    catheter = default_catheter()
    ukf = make_estimator("ukf", catheter, process_noise_rad2_s=1e-3)
    position = make_estimator("ukf-position", catheter)
    grid = make_estimator("grid", catheter, cells=1024, outlier_probability=0.05)
    assert isinstance(ukf.inner, BendingPlaneUKF) and ukf.name == "ukf"
    assert ukf.settings.use_velocity and not position.settings.use_velocity
    assert position.name == "ukf-position"
    assert grid.name == "grid" and grid.cells == 1024
    assert grid.settings.outlier_probability == 0.05


@pytest.mark.parametrize(
    "bad",
    [
        {"process_noise_rad2_s": -1.0},
        {"rotation_noise_gain_rad": float("nan")},
        {"gate_probability": 0.0},
        {"gate_probability": 1.5},
        {"uninformative_std_rad": 0.0},
        {"max_std_rad": np.pi},  # sigma points beyond pi
        {"uninformative_std_rad": 1.5, "max_std_rad": 1.0},
        {"reacquire_after_rejections": -1},
        {"noise_forgetting": 1.0},
        {"initial_std_rad": 0.0},
        {"alpha": 0.0},
        {"outlier_probability": 1.0},
        {"outlier_scale": 1.0},
        {"joint_error_mm": -0.1},
        {"deviation_length_mm": 0.0},
        {"max_hypotheses": 0},
    ],
)
def test_settings_are_validated_with_clear_errors(bad):
    with pytest.raises(ValueError, match="UKFSettings"):
        UKFSettings(**bad)


def test_out_of_order_frames_are_refused():
    catheter = default_catheter()
    ukf = BendingPlaneUKF(catheter)
    frames = simulate(catheter, np.broadcast_to(BENT, (2, 3)), 0.0, np.random.default_rng(0))
    ukf.step(frames[1])
    with pytest.raises(ValueError, match="time order"):
        ukf.step(frames[0])


def test_a_noise_covariance_that_is_not_positive_definite_is_one_clear_error():
    catheter = default_catheter()
    frame = simulate(catheter, BENT, 0.0, np.random.default_rng(0))[0]
    with pytest.raises(ValueError, match="not positive definite"):
        BendingPlaneUKF(catheter).step(replace(frame, tip_cov_b=-frame.tip_cov_b))


def test_a_frame_whose_3d_points_are_all_missing_is_fused_from_its_views():
    """A frame of one view (the other missed the tip, so nothing triangulated): 3-D fields
    of NaN rows go to the single-view update and count as partial, as absent fields do not;
    one present 3-D point keeps the frame 3-D."""
    from tracker.estimators.deviation import ShapeExpansion
    from tracker.estimators.measurement import FrameGroups, ViewGroups
    from tracker.estimators.ukf import observation_groups

    catheter = default_catheter()
    expansion = ShapeExpansion(catheter)
    view = default_pinhole_rig().views[0]
    q = np.array([0.3, 0.6, -0.4])
    n = len(catheter.marker_arclengths_mm)
    uv = view.project(catheter.points(q)[:2])
    seen = ViewMeasurement(view, np.eye(3), np.zeros(3), uv, np.broadcast_to(np.eye(2), (2, 2, 2)),
                           np.array([-1, 0]))
    cov = 0.01 * np.eye(3)
    missing = Observation(
        time_s=0.0, q=q, q_dot=np.array([0.1, 0.2, 0.3]), tip_b_mm=np.full(3, np.nan), tip_cov_b=cov,
        markers_b_mm=np.full((n, 3), np.nan), markers_cov_b=np.broadcast_to(cov, (n, 3, 3)),
        velocity_b_mm_s=np.ones(3), velocity_cov_b=cov, views=(seen,),
    )  # fmt: skip
    cases = [
        (missing, ViewGroups, True),
        (replace(missing, tip_b_mm=None, markers_b_mm=None, velocity_b_mm_s=None), ViewGroups,
         False),
        (replace(missing, markers_b_mm=np.where((np.arange(n) == n - 1)[:, None], np.ones((n, 3)), np.nan)),
         FrameGroups, True),
        (replace(missing, tip_cov_b=np.full((3, 3), np.nan), tip_b_mm=np.ones(3)), ViewGroups,
         True),
        (replace(missing, views=()), FrameGroups, True),  # the velocity alone
    ]  # fmt: skip
    for observation, kind, partial in cases:
        groups, is_partial = observation_groups(expansion, observation, q)
        assert isinstance(groups, kind)
        assert is_partial is partial
    # The single-view frame's update, after a 3-D frame, is that of its views alone.
    points = rotate_z(catheter.points(q), q[0] + 1.0)
    first = Observation(time_s=0.0, q=q, tip_b_mm=points[0], tip_cov_b=cov,
                        markers_b_mm=points[1:], markers_cov_b=np.broadcast_to(cov, (n, 3, 3)))
    ukf, alone = (BendingPlaneUKF(catheter) for _ in range(2))
    ukf.step(first), alone.step(first)
    missing = replace(missing, time_s=0.05)
    a = ukf.step(missing)
    b = alone.step(replace(missing, tip_b_mm=None, markers_b_mm=None, velocity_b_mm_s=None))
    assert np.isfinite(a.delta_L_rad) and a.std_rad < 0.5
    assert a.delta_L_rad == b.delta_L_rad and a.std_rad == b.std_rad
    assert Flag.PARTIAL in a.flags and Flag.PARTIAL not in b.flags


def test_single_view_groups_hold_the_model_vectors_of_their_finite_points():
    """A frame of single views becomes the finite rows of each view, in order, each with the
    model vector of its point (Catheter.shape_vectors: the tip for -1, marker k for k), bit
    for bit; a view with no finite row is left out, one with some missing makes the frame
    partial; malformed views are named."""
    from tracker.estimators.deviation import ShapeExpansion
    from tracker.estimators.ukf import observation_groups

    catheter = default_catheter()
    expansion = ShapeExpansion(catheter)
    front, side = default_pinhole_rig().views
    q = np.array([0.3, 0.6, -0.4])
    shape = catheter.shape_vectors(q)
    n = len(catheter.marker_arclengths_mm)
    rng = np.random.default_rng(5)
    R_w_b, o_b_w = rot_z(0.3), np.array([1.0, 2.0, 3.0])

    def measurement(view, index, lost=()):
        uv = rng.uniform(100, 500, (len(index), 2))
        cov = np.broadcast_to(np.diag([0.3, 0.5]), (len(index), 2, 2)).copy()
        for row, part in lost:
            (uv if part == "uv" else cov)[row] = np.nan
        return ViewMeasurement(view, R_w_b, o_b_w, uv, cov, np.asarray(index))

    def model(index):
        return np.array([shape.c_tip_mm if k < 0 else shape.c_markers_mm[k] for k in index])

    cases = [
        ((measurement(front, [-1, 0, n - 1]), measurement(side, [n - 1, -1])), False),
        ((measurement(front, [n - 1, -1, 0], [(1, "uv")]), measurement(side, [-1])), True),
        ((measurement(front, [-1, 0], [(0, "cov"), (1, "uv")]), measurement(side, [0, -1])), True),
    ]
    for views, partial in cases:
        groups, is_partial = observation_groups(expansion, Observation(0.0, q, views=views), q)
        assert is_partial is partial
        kept = []
        for m in views:
            finite = np.isfinite(m.uv).all(axis=1) & np.isfinite(m.cov).all(axis=(1, 2))
            if finite.any():
                kept.append((m, finite))
        assert len(groups.parts) == len(kept)
        for (view, C, R, o), (m, finite) in zip(groups.parts, kept, strict=True):
            assert view is m.view
            assert np.array_equal(C, model(m.point_index[finite]))
            assert np.array_equal(R, R_w_b) and np.array_equal(o, o_b_w)
        assert np.array_equal(groups.z[0], np.concatenate([m.uv[f] for m, f in kept]))
        assert np.array_equal(groups.R[0], np.concatenate([m.cov[f] for m, f in kept]))
        assert groups.present.all() and np.array_equal(groups.q[0], q)
    nothing = (measurement(front, [-1], [(0, "uv")]),)
    assert observation_groups(expansion, Observation(0.0, q, views=nothing), q)[0] is None
    bad = measurement(front, [-1, 0])
    for view, message in (
        (replace(bad, point_index=np.array([-1, n])), "point_index must be -1"),
        (replace(bad, point_index=np.array([-2, 0])), "point_index must be -1"),
        (replace(bad, point_index=np.array([-1])), "2 points, 2 covariances and 1 point"),
    ):
        with pytest.raises(ValueError, match=message):
            observation_groups(expansion, Observation(0.0, q, views=(view,)), q)


def test_preparing_the_expansion_changes_no_number_and_ignores_joints_not_finite():
    """ShapeExpansion.prepare computes the node a frame at q will use (the live loop's
    priming): the frame's expansion is then the same, bit for bit, as without it."""
    from tracker.estimators.deviation import ShapeExpansion

    catheter = default_catheter()
    q = np.array([[0.3, 0.612345, -0.40321]])
    prepared, fresh = ShapeExpansion(catheter), ShapeExpansion(catheter)
    prepared.prepare(np.array([0.3, np.nan, 0.1]))
    prepared.prepare(np.array([0.3, 0.5, np.inf]))
    assert not prepared._nodes
    prepared.prepare(q[0])
    assert len(prepared._nodes) == 1
    for a, b in zip(prepared.expanded(q), fresh.expanded(q), strict=True):
        assert np.array_equal(a, b)
    assert prepared._nodes.keys() == fresh._nodes.keys()


def test_a_prepared_expansion_is_taken_once_and_only_for_exactly_its_joints():
    """The expansion prepared at q (the frame's joints, while the worker segments) is what
    the next expanded(q) returns, bit for bit what it computes, once; any other q, or a
    batch, is computed as before; joints not finite prepare nothing."""
    from tracker.estimators.deviation import ShapeExpansion

    catheter = default_catheter()
    q = np.array([[0.3, 0.612345, -0.40321]])
    near = q + np.array([[0.0, 1e-12, 0.0]])
    prepared, fresh = ShapeExpansion(catheter), ShapeExpansion(catheter)
    prepared.prepare(q[0])
    held = prepared._prepared
    got = prepared.expanded(q)
    assert got[0] is held[1] and got[1] is held[2]  # taken, not computed again
    again = prepared.expanded(q)
    assert again[0] is not got[0]  # once only
    for a, b, c in zip(got, again, fresh.expanded(q), strict=True):
        assert np.array_equal(a, c) and np.array_equal(b, c)
    prepared.prepare(q[0])
    for a, b in zip(prepared.expanded(near), fresh.expanded(near), strict=True):
        assert np.array_equal(a, b)  # not the prepared q: computed, and the right numbers
    assert prepared._prepared is None  # dropped by that call: never taken later
    prepared.prepare(q[0])
    batch = np.concatenate([q, near])
    for a, b in zip(prepared.expanded(batch), fresh.expanded(batch), strict=True):
        assert np.array_equal(a, b)
    prepared.prepare(q[0])
    held = prepared._prepared
    prepared.prepare(q[0].copy())  # the same joints again (a catheter held still): kept
    assert prepared._prepared is held
    prepared.prepare(np.array([0.3, np.nan, 0.1]))  # not finite: nothing, the last dropped
    assert prepared._prepared is None


def test_a_new_filter_has_every_frame_kinds_update_rules_ready():
    """The update's rules and gate tables of every kind of frame the catheter's points make
    (3-D with and without a velocity, points missing, points in one view only) are worked
    out when the filter is made: none is left to a frame (the live loop's first frame paid
    about 1 ms for them, scipy's quantiles)."""
    from replay.simulation.simulator import NoiseSettings, Scene, simulate_frames, sinusoidal
    from tracker.estimators import ukf_core
    from tracker.reconstruction import Reconstructor

    catheter, rig = default_catheter(), default_pinhole_rig(400.0, 2500.0)
    scene = Scene(catheter, rig, np.eye(3), np.array([0.0, 0.0, -15.0]))
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.3, 0.1, 0.1], [3, 3, 3], 3.0)
    noise = NoiseSettings(sigma=0.5, dropout_probability=0.2)
    frames = simulate_frames(scene, trajectory, 1.0, noise, np.random.default_rng(4))
    observations = Reconstructor(catheter, rig, np.eye(3), scene.o_b_w_mm).observe_batch(frames)
    estimator = BendingPlaneUKF(catheter)
    bank = estimator._bank
    made = set(bank._rules)
    misses = ukf_core._gate_table.cache_info().misses
    kinds = set()
    for observation in observations:
        estimator.step(observation)
        kinds.add((observation.tip_b_mm is not None and np.isfinite(observation.tip_b_mm).all(),
                   observation.velocity_b_mm_s is not None, bool(observation.views)))  # fmt: skip
    assert len(kinds) >= 4  # every kind of frame came
    assert set(bank._rules) == made
    assert ukf_core._gate_table.cache_info().misses == misses
