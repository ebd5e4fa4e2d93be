"""A filter's run through a sequence of frames is its steps one by one, to the last bit.

``BendingPlaneUKF.run`` assembles the groups of every frame at once and steps the usual
frames in one compiled loop (tracker.estimators.ukf_run), handing every other frame to
``step``; ``CheckedEstimator.run`` checks frame by frame and passes the accepted frames on
between skipped ones. On seeded trials that go through every rule (starts, restarts, added
hypotheses, outliers, missing points, model mismatch), with every settings variant, and on
a sequence of what a lab feeds a filter (joint covariances, frames without a velocity, a
cross-covariance or rates, without a tip, with nothing found, at the same time stamp,
garbage), the run must give the steps' estimates, flags, NIS, counts, innovations and
final state, bit for bit, and raise where the steps raise.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from models.catheter import default_catheter
from tests.tracker.test_ukf_batch import SETTINGS, observations, random_trials
from tracker.estimators import make_estimator
from tracker.estimators.ukf import BendingPlaneUKF
from tracker.estimators.ukf_core import FilterBank


def rows(estimates):
    """Every field of the estimates, floats as arrays (NaN compared as equal bits)."""
    out = []
    for e in estimates:
        numbers = [e.time_s, e.delta_L_rad, e.std_rad, e.q_r_rad, e.informative_radius_mm,
                   math.nan if e.nis is None else e.nis]  # fmt: skip
        innovation = None if e.innovation is None else tuple(np.asarray(e.innovation).tolist())
        out.append((np.array(numbers), e.flags.value, e.nis is None, e.nis_dof,
                    e.rejected_outliers, innovation))  # fmt: skip
    return out


def assert_same(steps, runs):
    assert len(steps) == len(runs)
    for k, (a, b) in enumerate(zip(rows(steps), rows(runs), strict=True)):
        assert np.array_equal(a[0], b[0], equal_nan=True), (k, a, b)
        assert a[1:] == b[1:], (k, a, b)


def assert_same_state(a: BendingPlaneUKF, b: BendingPlaneUKF):
    for name in ("x", "P", "log_weight", "active", "time_s", "q", "noise_scale",
                 "mismatch_scale", "rejected", "bad_run", "tip_fused"):  # fmt: skip
        assert np.array_equal(getattr(a._bank, name), getattr(b._bank, name), equal_nan=True)


@pytest.fixture
def compiled_count(monkeypatch):
    """How many frames the compiled loop stepped, and how often it handed a frame back to
    the general path after stepping some (its state put back: the path the run resumes
    from)."""
    count = [0, 0]
    real = FilterBank.run_3d

    def counted(self, frames, start, out):
        stop = real(self, frames, start, out)
        count[0] += stop - start
        count[1] += start < stop < frames.regular.size
        return stop

    monkeypatch.setattr(FilterBank, "run_3d", counted)
    return count


@pytest.mark.parametrize("name", sorted(SETTINGS))
def test_a_run_is_the_steps_one_by_one(name, compiled_count):
    catheter = default_catheter(np.pi / 2)
    data = random_trials(catheter, np.random.default_rng(7 + sum(map(ord, name))), n_trials=30)
    stepped, ran = (
        BendingPlaneUKF(catheter, SETTINGS[name]),
        BendingPlaneUKF(catheter, SETTINGS[name]),
    )
    total = 0
    for i in range(30):
        frames = observations(i, *data)
        stepped.reset()
        ran.reset()
        assert_same([stepped.step(o) for o in frames], ran.run(frames))
        assert_same_state(stepped, ran)
        total += len(frames)
    # Most frames go through the compiled loop (with a large process noise every frame
    # restarts from its closed form: none of them, test_ukf_step.py).
    if name != "large process noise":
        assert compiled_count[0] > 0.5 * total, (compiled_count[0], total)
        assert compiled_count[1] > 0, "no frame handed back to the general path mid-run"


def lab_sequence(catheter, seed=3):
    """One trial's frames with what a lab feeds the filter in between."""
    data = random_trials(catheter, np.random.default_rng(seed), n_trials=4, n_frames=60)
    frames = observations(1, *data)
    n = len(catheter.marker_arclengths_mm)
    for k in range(4, 60, 6):
        o = frames[k]
        blocks = np.zeros((3 * n, 3 * n))
        for m in range(n):
            blocks[3 * m : 3 * m + 3, 3 * m : 3 * m + 3] = o.markers_cov_b[m]
        frames[k] = replace(o, markers_cov_b=blocks)  # a joint marker covariance
    frames[7] = replace(frames[7], velocity_b_mm_s=None, velocity_cov_b=None)
    frames[13] = replace(frames[13], velocity_tip_cov_b=None)
    frames[19] = replace(frames[19], q_dot=None)
    frames[25] = replace(frames[25], tip_b_mm=None, tip_cov_b=None)
    frames[31] = replace(frames[31], markers_b_mm=np.full((n, 3), np.nan))
    frames[37] = replace(frames[37], tip_b_mm=np.full(3, np.nan),
                         markers_b_mm=np.full((n, 3), np.nan))  # fmt: skip
    frames[43] = replace(frames[43], time_s=frames[42].time_s)  # the same time stamp
    frames[49] = replace(frames[49], markers_b_mm=frames[49].markers_b_mm + 25.0)  # outliers
    frames[53] = replace(frames[53], velocity_b_mm_s=np.full(3, np.nan))
    return frames


def test_a_run_through_what_a_lab_feeds_is_the_steps(compiled_count):
    catheter = default_catheter(np.pi / 2)
    frames = lab_sequence(catheter)
    for settings in (SETTINGS["default"], SETTINGS["independent velocity"]):
        stepped, ran = BendingPlaneUKF(catheter, settings), BendingPlaneUKF(catheter, settings)
        assert_same([stepped.step(o) for o in frames], ran.run(frames))
        assert_same_state(stepped, ran)
    assert compiled_count[0] > len(frames)  # of the two runs
    assert compiled_count[1] > 0  # the odd frames went the general path between compiled ones


def test_a_run_raises_where_the_steps_raise():
    catheter = default_catheter(np.pi / 2)
    frames = lab_sequence(catheter)
    frames[30] = replace(frames[30], time_s=frames[29].time_s - 1.0)
    stepped, ran = BendingPlaneUKF(catheter), BendingPlaneUKF(catheter)
    with pytest.raises(ValueError, match="time order") as step_error:
        for o in frames:
            stepped.step(o)
    with pytest.raises(ValueError, match="time order") as run_error:
        ran.run(frames)
    assert str(step_error.value) == str(run_error.value)
    assert_same_state(stepped, ran)  # both stopped at the same frame


def garbage_sequence(catheter):
    frames = lab_sequence(catheter, seed=5)
    n = len(catheter.marker_arclengths_mm)
    frames[5] = replace(frames[5], time_s=math.nan)
    frames[9] = replace(frames[9], q=np.array([0.0, math.nan, 0.0]))
    frames[12] = replace(frames[12], markers_b_mm=np.zeros((n + 1, 3)))
    frames[15] = replace(frames[15], tip_cov_b=1e-30 * np.eye(3))
    frames[18] = replace(frames[18], time_s=frames[17].time_s - 5.0)  # backwards: skipped
    # A restarted clock: five frames stamped from zero again, then on from there.
    restart = frames[40].time_s
    return [replace(o, time_s=o.time_s - restart) if k >= 40 else o
            for k, o in enumerate(frames)]  # fmt: skip


@pytest.mark.parametrize("name", ["ukf", "ukf-position", "grid", "tip-position"])
def test_a_checked_run_is_the_checked_steps(name):
    catheter = default_catheter(np.pi / 2)
    frames = garbage_sequence(catheter)
    stepped, ran = make_estimator(name, catheter), make_estimator(name, catheter)
    steps = [stepped.step(o) for o in frames]
    assert_same(steps, ran.run(frames))
    assert stepped.skipped == ran.skipped
    assert stepped.skipped.get("clock restarted") == (1 if name != "tip-position" else None)
    assert sum(stepped.skipped.values()) >= (4 if name == "tip-position" else 5)
