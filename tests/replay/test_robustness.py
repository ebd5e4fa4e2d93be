"""The filter is never confidently wrong: simulated lab sessions with everything a lab meets.

Sessions (replay.robustness.simulate_lab_session) hold configurations with small joint
motion, some nearly straight, turn the base between them with torsion wind-up and play,
deviate the joints by contact per configuration, bend 5 % more than the model says, and have
3 % wrong and 3 % missing points per view. Seeds and settings are fixed, so every number is
deterministic; the thresholds are the issue's, not numbers copied from a run.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig
from models.rotations import wrap_angle
from replay.robustness import (
    LabSessionSettings,
    robustness_metrics,
    run_methods_on_session,
    simulate_lab_session,
)
from replay.simulation.simulator import (
    JointTrajectory,
    LabConditions,
    NoiseSettings,
    contact_joint_offsets,
    default_scene,
    simulate_frames,
    truth_catheter,
)
from tracker.estimators import make_estimator
from tracker.reconstruction import Reconstructor

METHODS = ("tip-position", "ukf", "ukf-position", "grid")
SESSIONS = [(seed, noise) for noise in (0.11, 0.3) for seed in (0, 1, 2)]


@cache
def session_metrics(seed: int, noise_mm: float):
    settings = LabSessionSettings(
        seed=seed, noise_mm=noise_mm, configurations=10, frames_per_configuration=50
    )
    session = simulate_lab_session(default_catheter(), settings)
    return run_methods_on_session(session, METHODS)[0]


# ---------------------------------------------------------------------------- metrics
def test_metrics_count_confidently_wrong_frames_and_configurations():
    errors = np.array([0.1, 40.0, -35.0, 50.0, np.nan, 1.0, 31.0])  # degrees
    std = np.array([1.0, 5.0, 9.0, 20.0, np.nan, 0.5, 2.0])
    configuration = np.array([0, 0, 1, 1, 1, -1, 2])
    scored = np.array([True, True, True, True, True, True, False])
    m = robustness_metrics("x", np.radians(errors), np.radians(std), configuration, scored)
    assert m.frames == 6 and m.valid == pytest.approx(5 / 6)
    # 40 (std 5) and -35 (std 9) are confidently wrong; 50 with std 20 is not; 31 not scored.
    assert m.confidently_wrong_frames == 2 and m.confidently_wrong_configurations == 2
    valid = np.array([0.1, 40.0, -35.0, 50.0, 1.0])
    s = np.array([1.0, 5.0, 9.0, 20.0, 0.5])
    assert m.rms_deg == pytest.approx(np.sqrt(np.mean(valid**2)))
    assert m.max_deg == pytest.approx(50.0)
    assert m.coverage_2sigma == pytest.approx(2 / 5)
    assert m.mean_nees == pytest.approx(np.mean((valid / s) ** 2))


# ---------------------------------------------------------------------------- simulation
def test_lab_conditions_are_validated_and_make_the_truth():
    with pytest.raises(ValueError, match="contact_joint_std_mm"):
        LabConditions(contact_joint_std_mm=-0.1)
    with pytest.raises(ValueError, match="outlier_probability"):
        LabConditions(outlier_probability=1.5)
    with pytest.raises(ValueError, match="model_scale_error"):
        LabConditions(model_scale_error=-1.0)
    catheter = default_catheter()
    truth = truth_catheter(catheter, 0.05)
    straight = np.array([0.0, 0.0, 0.0])
    np.testing.assert_allclose(truth.tip(straight), catheter.tip(straight), atol=1e-12)
    bent = np.array([0.0, 0.8, 0.0])
    angle = lambda c: np.arctan2(c.tip(bent)[0], c.tip(bent)[2])  # noqa: E731
    assert angle(truth) > angle(catheter)
    offsets = contact_joint_offsets(np.random.default_rng(0), 4000, 0.08)
    assert np.all(offsets[:, 0] == 0.0)
    assert np.std(offsets[:, 1:]) == pytest.approx(0.08, rel=0.05)
    noise = LabConditions(outlier_probability=0.03, dropout_probability=0.02).noise(0.2)
    assert noise == NoiseSettings(0.2, 0.03, 10.0, 0.02)


# ---------------------------------------------------------------------------- sessions
@pytest.mark.parametrize("seed, noise_mm", SESSIONS)
def test_no_method_of_the_filters_is_confidently_wrong_on_any_session(seed, noise_mm):
    metrics = session_metrics(seed, noise_mm)
    for name in ("ukf", "ukf-position", "grid"):
        assert metrics[name].confidently_wrong_configurations == 0, name
        assert metrics[name].valid > 0.99
    # The per-frame estimator is, which is what the filters are for.
    assert metrics["tip-position"].confidently_wrong_configurations > 0


@pytest.mark.parametrize("seed, noise_mm", SESSIONS)
def test_ukf_beats_tip_position_threefold_and_is_within_the_grid_filter(seed, noise_mm):
    metrics = session_metrics(seed, noise_mm)
    ukf = metrics["ukf"].rms_deg
    assert ukf <= metrics["tip-position"].rms_deg / 3
    assert ukf <= 1.2 * metrics["grid"].rms_deg


def test_velocity_fusion_does_not_raise_the_error():
    """The velocity is offered only after a frame whose tip was not used, has its own gate
    and its own model error: on no session is the RMS or the largest error with it above
    the one without it (to 0.1 %: where it is fused it moves a session's RMS by about
    1e-5)."""
    for seed, noise_mm in SESSIONS:
        metrics = session_metrics(seed, noise_mm)
        assert metrics["ukf"].rms_deg <= metrics["ukf-position"].rms_deg * 1.001
        assert metrics["ukf"].max_deg <= metrics["ukf-position"].max_deg * 1.001


def test_the_ukf_uncertainty_is_calibrated_over_the_sessions():
    """2-sigma coverage in [93 %, 97 %] and mean NEES in [0.7, 1.5], over all frames of all
    sessions. Errors are correlated within a configuration (a filter averages the frames of a
    hold), so one session of ten configurations has few independent errors: its coverage
    scatters by about +/-3 % around the calibrated value, and the band is tested on the
    pooled frames. (The per-session values are in the report of issue 11.)"""
    rows = [session_metrics(seed, noise_mm)["ukf"] for seed, noise_mm in SESSIONS]
    frames = np.array([r.frames * r.valid for r in rows])
    coverage = np.sum(frames * [r.coverage_2sigma for r in rows]) / frames.sum()
    nees = np.sum(frames * [r.mean_nees for r in rows]) / frames.sum()
    assert 0.93 <= coverage <= 0.97
    assert 0.7 <= nees <= 1.5


# ---------------------------------------------------------------------------- scenarios
def observe(catheter, frames):
    scene = default_scene(catheter, default_orthographic_rig())
    reconstructor = Reconstructor(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    return reconstructor.observe_batch(frames)


def trajectory(q_from, q_to, holds, move, q_r_turn=0.0, dt=0.05):
    """Hold q_from, move (smoothly, turning the base by q_r_turn), hold q_to."""
    q_from, q_to = np.asarray(q_from, float), np.asarray(q_to, float)
    x = np.arange(1, move + 1) / (move + 1)
    x = x * x * (3 - 2 * x)
    target = q_to + np.array([q_r_turn, 0.0, 0.0])
    q = np.vstack([np.tile(q_from, (holds[0], 1)), q_from + x[:, None] * (target - q_from),
                   np.tile(target, (holds[1], 1))])  # fmt: skip
    t = np.arange(q.shape[0]) * dt
    return JointTrajectory(t, q, np.gradient(q, t, axis=0))


@pytest.mark.parametrize("method, tolerance_deg", [("ukf", 2.0), ("ukf-position", 2.0),
                                                   ("grid", 5.0)])  # fmt: skip
def test_a_held_estimate_survives_a_deflected_nearly_straight_configuration(
    method, tolerance_deg
):
    """The issue's case: bent, then (base still) nearly straight, q_p 0.057 mm, q_d -0.001 mm,
    where a contact takes 0.06 mm off q_p (the tip 2.6 mm off the model), 0.11 mm noise. The
    base did not turn, so delta_L did not change: the estimate holds (the UKF to within 2
    degrees) for the 100 frames of the deflected hold and is never confidently wrong. (The
    grid keeps a little mass wherever a jump could have taken the torsion, which these
    ambiguous frames cannot rule out; it pulls its circular mean by a few degrees, with a
    std of tens.)"""
    catheter = default_catheter()
    traj = trajectory([0.4, 0.6, 0.3], [0.4, 0.057, -0.001], (40, 100), 20)
    offset = np.zeros((traj.time_s.size, 3))
    offset[60:, 1] = -0.06
    scene = default_scene(catheter, default_orthographic_rig())
    truth = 2.0
    frames = simulate_frames(scene, traj, truth, NoiseSettings(0.11), np.random.default_rng(3),
                             model_joint_offset=offset)  # fmt: skip
    tip_off = np.linalg.norm(catheter.tip(traj.q[-1]) - catheter.tip(traj.q[-1] + offset[-1]))
    assert tip_off == pytest.approx(2.6, abs=0.3)
    estimator = make_estimator(method, catheter)
    estimates = [estimator.step(o) for o in observe(catheter, frames)]
    errors = np.degrees(np.abs(wrap_angle(np.array([e.delta_L_rad for e in estimates]) - truth)))
    stds = np.degrees([e.std_rad for e in estimates])
    assert np.all(errors[20:] < tolerance_deg)
    assert not np.any((errors > 30) & (stds < 10))


@pytest.mark.parametrize("method", ["ukf", "grid"])
def test_a_torsion_step_after_a_base_rotation_is_followed_within_two_frames(method):
    """Bent; the base turns by 0.6 rad over 12 frames while the tip stays (the torsion winds
    up by the turn); then the stored torsion releases in one step of 90 degrees. Within two
    frames of the step the estimate covers the truth (3 std, and within 2 degrees), and it
    is never confidently wrong."""
    catheter = default_catheter()
    traj = trajectory([0.0, 0.7, 0.4], [0.0, 0.7, 0.4], (30, 30), 12, q_r_turn=0.6)
    truth = 1.0 - (traj.q[:, 0] - traj.q[0, 0])  # the tip stays: delta_L = -turn
    step = 45
    truth[step:] += math.pi / 2
    scene = default_scene(catheter, default_orthographic_rig())
    frames = simulate_frames(scene, traj, truth, NoiseSettings(0.2), np.random.default_rng(4))
    estimator = make_estimator(method, catheter)
    estimates = [estimator.step(o) for o in observe(catheter, frames)]
    errors = np.abs(wrap_angle(np.array([e.delta_L_rad for e in estimates]) - truth))
    stds = np.array([e.std_rad for e in estimates])
    settled = slice(step + 2, None)
    assert np.all(errors[settled] < 3 * stds[settled])
    assert np.all(np.degrees(errors[settled]) < 2.0)
    assert not np.any((np.degrees(errors) > 30) & (np.degrees(stds) < 10))
