"""The trial-batched UKF is BendingPlaneUKF, run on many trials at once.

Both step the same rules (tracker.estimators.ukf_core.FilterBank); these tests check that the
batched layout (a leading trial axis, padding, masks, one shape expansion for all trials)
changes nothing. Every test draws seeded random trials that exercise the rules (bent and
near-straight frames, 0.1 to 5 mm of anisotropic noise, moving joints with a
finite-difference velocity, outliers, missing points, a tip deflection the model does not
know, a 90 degree torsion step), steps ``BendingPlaneUKF`` through each trial's observations,
and requires the batched filter to agree to 1e-9 rad in delta_L and std, with identical flags
and rejection counts.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from models.catheter import default_catheter
from models.rotations import rotate_z, wrap_angle
from tracker.estimators.ukf import BendingPlaneUKF, UKFSettings
from tracker.estimators.ukf_batch import finite_difference_velocity, run_ukf_batch
from tracker.estimators.ukf_core import FilterBank
from tracker.types import Flag, Observation, velocity_from_positions

DELTA_2 = [0.0, np.pi / 2]
DT_S = 0.05
TOLERANCE_RAD = 1e-9


def random_trials(catheter, rng, n_trials=120, n_frames=24):
    """Seeded trials covering the filter's branches; arrays as the studies hold them.

    Returns time (T,), q and q_dot (B, T, 3), tips (B, T, 3), markers (B, T, M, 3) and their
    covariances (B, T, 3, 3) and (B, T, M, 3, 3).
    """
    n_markers = len(catheter.marker_arclengths_mm)
    time = np.arange(n_frames) * DT_S
    t = time[None, :, None]
    # Bent configurations, moving: q_r turns at up to 1.5 rad/s, q_p and q_d at up to 0.4 mm/s.
    q0 = np.column_stack(
        [rng.uniform(-np.pi, np.pi, n_trials), rng.uniform(-1.2, 1.2, (n_trials, 2))]
    )
    q_dot = np.column_stack(
        [rng.uniform(-1.5, 1.5, n_trials), rng.uniform(-0.4, 0.4, (n_trials, 2))]
    )
    q_dot[rng.random(n_trials) < 0.2] = 0.0  # some trials hold still
    q = q0[:, None, :] + q_dot[:, None, :] * t
    q_dot = np.broadcast_to(q_dot[:, None, :], q.shape).copy()
    # Near-straight stretches (uninformative frames), also at the start of some trials.
    for i in np.flatnonzero(rng.random(n_trials) < 0.35):
        start = rng.integers(0, n_frames - 4)
        stop = start + rng.integers(2, 10)
        q[i, start:stop, 1:] = rng.normal(0.0, 1e-5, (min(stop, n_frames) - start, 2))
        q_dot[i, start:stop, 1:] = 0.0
    # True torsion: a random walk, with a 90 degree step in some trials.
    delta_L = rng.uniform(-np.pi, np.pi, (n_trials, 1)) + np.cumsum(
        rng.normal(0.0, 0.01, (n_trials, n_frames)), axis=1
    )
    for i in np.flatnonzero(rng.random(n_trials) < 0.3):
        delta_L[i, rng.integers(3, n_frames - 4) :] += np.pi / 2 * rng.choice([-1, 1])
    # A tip deflection by contact the model does not see (persistent model mismatch).
    q_true = q.copy()
    deflected = rng.random(n_trials) < 0.3
    q_true[deflected, :, 2] += rng.uniform(0.3, 1.5, (deflected.sum(), 1))
    # Noise 0.1 to 5 mm, anisotropic, each trial in its own axes.
    sigma = np.exp(rng.uniform(np.log(0.1), np.log(5.0), n_trials))
    axes = np.linalg.qr(rng.normal(size=(n_trials, 3, 3)))[0]
    cov = sigma[:, None, None] ** 2 * (axes * [1.0, 0.7, 0.4]) @ np.swapaxes(axes, 1, 2)
    cov = np.broadcast_to(cov[:, None], (n_trials, n_frames, 3, 3))
    root = np.linalg.cholesky(cov)
    shape = catheter.shape_vectors(q_true)
    angle = q_true[..., 0] + delta_L
    tips = rotate_z(shape.c_tip_mm, angle)
    tips = tips + (root @ rng.normal(size=(n_trials, n_frames, 3, 1)))[..., 0]
    markers = rotate_z(shape.c_markers_mm, angle[..., None])
    noise = root[:, :, None] @ rng.normal(size=(n_trials, n_frames, n_markers, 3, 1))
    markers = markers + noise[..., 0]
    # Outliers: a wrong segmentation moves the tip by 10 to 40 mm in about 4 % of the frames.
    outlier = rng.random((n_trials, n_frames)) < 0.04
    direction = rng.normal(size=(outlier.sum(), 3))
    direction *= rng.uniform(10.0, 40.0, (len(direction), 1)) / np.linalg.norm(
        direction, axis=1, keepdims=True
    )
    tips[outlier] += direction
    # Missing points: a tip or a marker not segmented in about 3 % of the frames.
    tips[rng.random((n_trials, n_frames)) < 0.03] = np.nan
    markers[rng.random((n_trials, n_frames, n_markers)) < 0.03] = np.nan
    markers_cov = np.broadcast_to(cov[:, :, None], (n_trials, n_frames, n_markers, 3, 3))
    return time, q, q_dot, tips, cov, markers, markers_cov


def observations(trial, time, q, q_dot, tips, cov, markers, markers_cov, velocity=True):
    """One trial's observations, built as TrialData.observations builds them."""
    out = []
    for k in range(time.size):
        extra = {}
        if velocity and k > 0 and np.isfinite(tips[trial, k - 1 : k + 1]).all():
            v, cov_v, cross = velocity_from_positions(
                tips[trial, k], cov[trial, k], tips[trial, k - 1], cov[trial, k - 1],
                float(time[k] - time[k - 1]),
            )  # fmt: skip
            extra = dict(velocity_b_mm_s=v, velocity_cov_b=cov_v, velocity_tip_cov_b=cross)
        out.append(
            Observation(
                time_s=float(time[k]),
                q=q[trial, k],
                q_dot=q_dot[trial, k],
                tip_b_mm=tips[trial, k],
                tip_cov_b=cov[trial, k],
                markers_b_mm=markers[trial, k],
                markers_cov_b=markers_cov[trial, k],
                **extra,
            )
        )
    return out


def reference(catheter, settings, data, velocity=True):
    """BendingPlaneUKF stepped trial by trial: (delta_L, std, flags, nis, rejected), (B, T)."""
    ukf = BendingPlaneUKF(catheter, settings)
    n, frames = data[3].shape[:2]
    delta = np.full((n, frames), np.nan)
    std = np.full((n, frames), np.nan)
    flags = np.zeros((n, frames), dtype=int)
    nis = np.full((n, frames), np.nan)
    rejected = np.zeros((n, frames), dtype=int)
    for i in range(n):
        ukf.reset()
        for k, observation in enumerate(observations(i, *data, velocity=velocity)):
            e = ukf.step(observation)
            delta[i, k], std[i, k], flags[i, k] = e.delta_L_rad, e.std_rad, e.flags.value
            nis[i, k] = np.nan if e.nis is None else e.nis
            rejected[i, k] = e.rejected_outliers
    return delta, std, flags, nis, rejected


def batched(catheter, settings, data, velocity=True):
    time, q, q_dot, tips, cov, markers, markers_cov = data
    kwargs = {}
    if velocity:
        v, cov_v, cross = finite_difference_velocity(time, tips, cov)
        kwargs = dict(velocity_b_mm_s=v, velocity_cov_b=cov_v, velocity_tip_cov_b=cross)
    return run_ukf_batch(
        catheter, settings, time, q, q_dot, tips, cov, markers, markers_cov, **kwargs
    )


def assert_agree(result, expected):
    delta, std, flags, nis, rejected = expected
    np.testing.assert_array_equal(result.flags, flags)
    np.testing.assert_array_equal(result.valid, np.isfinite(delta))
    np.testing.assert_array_equal(result.rejected_outliers, rejected)
    valid = np.isfinite(delta)
    assert np.all(np.abs(wrap_angle(result.delta_L_rad[valid] - delta[valid])) <= TOLERANCE_RAD)
    np.testing.assert_allclose(result.std_rad[valid], std[valid], rtol=0, atol=TOLERANCE_RAD)
    np.testing.assert_array_equal(np.isfinite(result.nis), np.isfinite(nis))
    np.testing.assert_allclose(result.nis, nis, rtol=1e-7, atol=1e-9)


SETTINGS = {
    "default": UKFSettings(),
    "position only": UKFSettings(use_velocity=False),
    "independent velocity": UKFSettings(velocity_is_finite_difference=False),
    "exact model, no heavy tail": UKFSettings(
        joint_error_mm=0.0, gain_error=0.0, joint_error_white_mm=0.0, outlier_probability=0.0
    ),
    "conservative start, no mismatch restart": UKFSettings(
        initial_std_rad=0.2, reacquire_after_rejections=0, process_noise_rad2_s=0.05
    ),
    # A std that outgrows reacquire_std_rad in a frame or two: restarts from the closed form,
    # and up to the cap in near-straight stretches.
    "large process noise": UKFSettings(process_noise_rad2_s=10.0),
    "rate state, noise scale": UKFSettings(include_rate=True, estimate_noise=True),
    "wide sigma points, one hypothesis": UKFSettings(
        alpha=0.5, beta=0.0, kappa=6.0, max_hypotheses=1
    ),
}


def seed_of(delta_2, name):
    return round(100 * delta_2) + sum(map(ord, name))


EVENTS = ("start", "reacquire", "spawn", "mismatch restart", "predict repaired")


@cache
def reference_run(name, delta_2):
    """Seeded trials for one settings variant, BendingPlaneUKF's estimates on them, and the
    rules they went through (shared by the tests below)."""
    catheter = default_catheter(delta_2)
    data = random_trials(catheter, np.random.default_rng(seed_of(delta_2, name)))
    seen = set()
    closed_form, spawn, step = FilterBank._closed_form, FilterBank._spawn, FilterBank.step

    def spy_closed_form(self, frame, M, scale, first, all_wide, spawn_mask, *rest):
        flags = rest[-2]
        before = self.initialised.copy()
        closed_form(self, frame, M, scale, first, all_wide, spawn_mask, *rest)
        if np.any(first & self.initialised & ~before):
            seen.add("start")
        if np.any(all_wide & ((flags & Flag.HELD.value) == 0)):
            seen.add("reacquire")
        if np.any((flags & Flag.MODEL_MISMATCH.value) != 0):
            seen.add("mismatch restart")

    def spy_step(self, *args, **kwargs):
        result = step(self, *args, **kwargs)
        # The compiled predict repairs what it cannot factorise and marks it not ok.
        if not self._factor_ok.all():
            seen.add("predict repaired")
        return result

    def spy_spawn(self, *args):
        seen.add("spawn")
        return spawn(self, *args)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(FilterBank, "_closed_form", spy_closed_form)
        patch.setattr(FilterBank, "_spawn", spy_spawn)
        patch.setattr(FilterBank, "step", spy_step)
        expected = reference(catheter, SETTINGS[name], data)
    flags = expected[2]
    for flag in (Flag.UNINFORMATIVE, Flag.OUTLIER_REJECTED, Flag.HELD, Flag.PARTIAL,
                 Flag.NOT_INITIALISED, Flag.MODEL_MISMATCH):  # fmt: skip
        if np.any((flags & flag.value) != 0):
            seen.add(flag.name)
    return catheter, data, expected, frozenset(seen)


@pytest.mark.parametrize("delta_2", DELTA_2)
@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_batched_filter_is_the_ukf_trial_by_trial(delta_2, name):
    catheter, data, expected, _ = reference_run(name, delta_2)
    assert_agree(batched(catheter, SETTINGS[name], data), expected)


def test_the_live_step_is_a_batch_of_one_trial():
    """The live filter's step (a bank of one, its views-not-gathers path) equals
    run_ukf_batch with one trial, trial by trial, on the random trials (outliers, missing
    points, restarts, jump hypotheses)."""
    catheter, data, expected, _ = reference_run("default", 0.0)
    time, rest = data[0], data[1:]
    flags = expected[2]
    # The trials with a restart, a rejected outlier or a missing point, and a few others.
    eventful = np.flatnonzero(
        np.any((flags & (Flag.OUTLIER_REJECTED | Flag.PARTIAL | Flag.HELD).value) != 0, axis=1)
    )
    trials = np.union1d(eventful[:24], np.arange(4))
    for i in trials:
        one = batched(catheter, SETTINGS["default"], (time, *(a[i : i + 1] for a in rest)))
        assert_agree(one, tuple(a[i : i + 1] for a in expected))


def test_the_random_trials_exercise_the_rules():
    """The agreement tests' data and settings go through every rule of the filter."""
    seen = set()
    for name in ("default", "large process noise"):
        for delta_2 in DELTA_2:
            seen |= reference_run(name, delta_2)[3]
    wanted = set(EVENTS) - {"predict repaired"} | {
        "UNINFORMATIVE", "OUTLIER_REJECTED", "HELD", "PARTIAL", "NOT_INITIALISED",
        "MODEL_MISMATCH",
    }  # fmt: skip
    assert wanted <= seen, sorted(wanted - seen)


def test_both_measurement_sizes_occur():
    """With the velocity (after a frame whose tip was not fused) and without it."""
    catheter, data, _, _ = reference_run("default", 0.0)
    result = batched(catheter, UKFSettings(), data)
    dofs = set(np.unique(result.nis_dof[result.nis_dof > 0]).tolist())
    full = 3 * (1 + len(catheter.marker_arclengths_mm))
    assert {full, full + 3} <= dofs


def test_trials_without_velocity_and_shared_arguments():
    """No velocity at all, shared time and one covariance for every trial, as in the studies."""
    catheter = default_catheter()
    time, q, q_dot, tips, cov, markers, markers_cov = random_trials(
        catheter, np.random.default_rng(3), n_trials=40
    )
    cov = np.broadcast_to(np.diag([1.0, 1.0, 0.5]), cov.shape)
    markers_cov = np.broadcast_to(np.diag([1.0, 1.0, 0.5]), markers_cov.shape)
    data = (time, q, q_dot, tips, cov, markers, markers_cov)
    expected = reference(catheter, UKFSettings(), data, velocity=False)
    result = run_ukf_batch(
        catheter, UKFSettings(), time, q, q_dot, tips, np.diag([1.0, 1.0, 0.5]), markers,
        np.diag([1.0, 1.0, 0.5]),
    )  # fmt: skip
    assert_agree(result, expected)


def test_finite_difference_velocity_is_velocity_from_positions():
    rng = np.random.default_rng(2)
    time = np.cumsum(rng.uniform(0.01, 0.1, 6))
    tips = rng.normal(size=(4, 6, 3))
    cov = rng.normal(size=(4, 6, 3, 3))
    v, cov_v, cross = finite_difference_velocity(time, tips, cov)
    assert np.isnan(v[:, 0]).all() and np.isnan(cov_v[:, 0]).all() and np.isnan(cross[:, 0]).all()
    for i in range(4):
        for k in range(1, 6):
            expected = velocity_from_positions(
                tips[i, k], cov[i, k], tips[i, k - 1], cov[i, k - 1], float(time[k] - time[k - 1])
            )
            for got, want in zip((v[i, k], cov_v[i, k], cross[i, k]), expected, strict=True):
                np.testing.assert_array_equal(got, want)


def test_bad_inputs_are_clear_errors():
    catheter = default_catheter()
    time, q, q_dot, tips, cov, markers, markers_cov = random_trials(
        catheter, np.random.default_rng(0), n_trials=2, n_frames=8
    )
    settings = UKFSettings()
    with pytest.raises(ValueError, match="time order"):
        run_ukf_batch(catheter, settings, time[::-1], q, q_dot, tips, cov, markers, markers_cov)
    with pytest.raises(ValueError, match="not positive definite"):
        run_ukf_batch(catheter, settings, time, q, q_dot, tips, -cov, markers, markers_cov)
    with pytest.raises(ValueError, match="markers_b_mm must have shape"):
        run_ukf_batch(catheter, settings, time, q, q_dot, tips, cov, markers[:, :, :0], cov)
    with pytest.raises(ValueError, match="together"):
        run_ukf_batch(catheter, settings, time, q, q_dot, tips, cov, markers, None)


def test_sigma_point_settings_change_the_result():
    """Guard against a test that passes because the settings are ignored."""
    catheter = default_catheter()
    data = random_trials(catheter, np.random.default_rng(5), n_trials=20)
    a = batched(catheter, UKFSettings(), data)
    b = batched(catheter, replace(UKFSettings(), alpha=0.5, kappa=6.0), data)
    both = a.valid & b.valid
    assert np.nanmax(np.abs(a.std_rad[both] - b.std_rad[both])) > 1e-6
