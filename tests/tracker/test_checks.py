"""The input checks every estimator's observations go through (tracker.estimators.checks),
rule by rule: the phrase each bad input gets, the order in which the rules run, and that any
layout or dtype of the arrays is checked by the compiled kernel without compiling again."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tracker.estimators import check_kernels
from tracker.estimators.checks import observation_problem
from tracker.types import Flag, Observation

I3 = np.eye(3)
GOOD = Observation(
    time_s=1.0, q=np.array([0.1, 0.5, 0.2]), q_dot=np.array([0.2, 0.0, 0.1]),
    tip_b_mm=np.array([1.0, 2.0, 30.0]), tip_cov_b=0.01 * I3,
    markers_b_mm=np.array([[1.0, 2.0, 20.0], [0.0, 1.0, 10.0]]),
    markers_cov_b=np.stack([0.01 * I3] * 2), velocity_b_mm_s=np.array([1.0, 0.0, 0.0]),
    velocity_cov_b=4.0 * I3, velocity_tip_cov_b=0.1 * I3,
)  # fmt: skip
JOINTS = "joint values missing, not finite or beyond the robot's ranges"
RATES = "joint rates not finite or beyond the robot's ranges"
TIP = "tip not finite or beyond the catheter's reach"
TIP_COV = "tip covariance not positive definite or out of range"
MARKERS = "markers not 2 finite points within the catheter's reach"
MARKERS_COV = "marker covariance not positive definite or out of range"
VELOCITY = "velocity or its covariance unusable"
CROSS = "velocity-tip cross-covariance not finite"
DECORRELATED = (
    "velocity-tip cross-covariance too large: the velocity's covariance given the tip is not"
    " positive definite"
)
NAN3 = np.full(3, np.nan)
SKEW = I3 + np.triu(np.ones((3, 3)), 1)
JOINT = 0.01 * np.eye(6)
JOINT[0, 3] = JOINT[3, 0] = 0.02  # the two markers' blocks fine, the joint matrix not

CASES = [
    ("good", {}, None),
    ("lists of ints", dict(q=[0, 1, 2], tip_b_mm=[1, 2, 30], tip_cov_b=np.eye(3, dtype=int).tolist()), None),
    ("read-only, strided", dict(tip_b_mm=np.repeat([1.0, 2.0, 30.0], 2)[::2],
                                tip_cov_b=np.asfortranarray(0.01 * I3)), None),
    ("no tip found", dict(tip_b_mm=NAN3, tip_cov_b=None), None),
    ("q NaN", dict(q=np.array([np.nan, 0.5, 0.2])), JOINTS),
    ("q beyond range", dict(q=np.array([0.0, 1e3, 0.2])), JOINTS),
    ("q of 2", dict(q=np.zeros(2)), JOINTS),
    ("q_dot inf", dict(q_dot=np.array([0.0, np.inf, 0.0])), RATES),
    ("q_dot of 4", dict(q_dot=np.zeros(4)), RATES),
    ("tip partly NaN", dict(tip_b_mm=np.array([1.0, np.nan, 2.0])), TIP),
    ("tip 1e10", dict(tip_b_mm=np.full(3, 1e10)), TIP),
    ("tip of 2", dict(tip_b_mm=np.zeros(2)), TIP),
    ("tip cov missing", dict(tip_cov_b=None), TIP_COV),
    ("tip cov skew", dict(tip_cov_b=SKEW), TIP_COV),
    ("tip cov tiny", dict(tip_cov_b=1e-30 * I3), TIP_COV),
    ("tip cov huge", dict(tip_cov_b=1e300 * I3), TIP_COV),
    ("tip cov text", dict(tip_cov_b="identity"), TIP_COV),
    ("markers of 3", dict(markers_b_mm=np.zeros((3, 3))), MARKERS),
    ("marker partly NaN", dict(markers_b_mm=np.array([[1.0, 2.0, 20.0], [np.nan, 1.0, 1.0]])), MARKERS),
    ("marker cov zero", dict(markers_cov_b=np.zeros((2, 3, 3))), MARKERS_COV),
    ("marker cov of a lost marker ignored",
     dict(markers_b_mm=np.array([[1.0, 2.0, 20.0], NAN3]),
          markers_cov_b=np.stack([0.01 * I3, np.zeros((3, 3))])), None),
    ("marker cov shape", dict(markers_cov_b=np.zeros((4, 4))), "marker covariance of shape (4, 4)"),
    ("joint marker cov", dict(markers_cov_b=0.01 * np.eye(6)), None),
    ("joint marker cov not positive", dict(markers_cov_b=JOINT), MARKERS_COV),
    ("joint, one marker found: its block",
     dict(markers_b_mm=np.array([NAN3, [0.0, 1.0, 10.0]]), markers_cov_b=JOINT), None),
    ("joint, one marker found, bad block",
     dict(markers_b_mm=np.array([NAN3, [0.0, 1.0, 10.0]]), markers_cov_b=np.zeros((6, 6))),
     MARKERS_COV),
    ("velocity 1e300", dict(velocity_b_mm_s=np.full(3, 1e300)), VELOCITY),
    ("velocity cov zero", dict(velocity_cov_b=np.zeros((3, 3))), VELOCITY),
    ("velocity of 2", dict(velocity_b_mm_s=np.zeros(2)), VELOCITY),
    ("cross inf", dict(velocity_tip_cov_b=np.full((3, 3), np.inf)), CROSS),
    ("cross of another shape, NaN", dict(velocity_tip_cov_b=np.full((2, 2), np.nan)), CROSS),
    # Sv - C S^-1 C^T: 4 I - 0.2^2 / 0.01 I = 0 (0.1 I above: 3 I).
    ("cross too large", dict(velocity_tip_cov_b=0.2 * I3), DECORRELATED),
    ("cross too large, no tip: not used", dict(velocity_tip_cov_b=0.2 * I3, tip_b_mm=NAN3), None),
    # The rules run in order: the first broken one is named.
    ("q and tip", dict(q=np.array([np.nan, 0.0, 0.0]), tip_b_mm=np.zeros(2)), JOINTS),
    ("tip cov and markers", dict(tip_cov_b=SKEW, markers_b_mm=np.zeros((3, 3))), TIP_COV),
    ("markers and velocity", dict(markers_cov_b=np.zeros((2, 3, 3)), velocity_b_mm_s=np.zeros(2)),
     MARKERS_COV),
    ("joint markers and velocity", dict(markers_cov_b=JOINT, velocity_cov_b=np.zeros((3, 3))),
     MARKERS_COV),
]  # fmt: skip


@pytest.mark.parametrize(("name", "change", "problem"), CASES, ids=[c[0] for c in CASES])
def test_each_rule_names_its_problem(name, change, problem):
    observation = dataclasses.replace(GOOD, **change)
    for value in change.values():
        if isinstance(value, np.ndarray):
            value.flags.writeable = False  # recorded arrays are often read-only
    assert observation_problem(observation, 2) == problem


def test_any_input_is_checked_without_compiling_again():
    for _, change, _ in CASES:
        observation_problem(dataclasses.replace(GOOD, **change), 2)
    assert len(check_kernels.check_buffer.signatures) == 1


def test_a_cross_covariance_too_large_is_a_skipped_step_not_an_error():
    """A velocity whose covariance given the tip is not one (the UKF would raise on it) is a
    skipped step of every filter, and the next good frame is stepped."""
    from models.catheter import default_catheter
    from tracker.estimators import make_estimator

    catheter = default_catheter()
    n = len(catheter.marker_arclengths_mm)
    good = dataclasses.replace(
        GOOD, markers_b_mm=GOOD.markers_b_mm[:n], markers_cov_b=GOOD.markers_cov_b[:n]
    )
    bad = dataclasses.replace(good, time_s=2.0, velocity_tip_cov_b=0.2 * I3)
    for name in ("ukf", "grid"):
        estimator = make_estimator(name, catheter)
        estimator.step(good)
        if name == "ukf":
            with pytest.raises(ValueError, match="not positive definite"):
                make_estimator(name, catheter).inner.step(bad)  # unchecked: the UKF raises
        assert estimator.step(bad).flags & Flag.INVALID_INPUT, name
        assert estimator.skipped == {DECORRELATED: 1}, name
        after = estimator.step(dataclasses.replace(good, time_s=3.0))
        assert not after.flags & Flag.INVALID_INPUT and len(estimator.skipped) == 1, name


def test_a_checked_estimator_copies_and_pickles_and_steps_on_the_same():
    """A checked estimator is copied (a fork of a filter) and pickled (to a worker process)
    whole: the copies step on to the original's estimates, bit for bit."""
    import copy
    import pickle

    from replay.simulation.sources import simulated_session
    from tracker.estimators import make_estimator
    from tracker.reconstruction import Reconstructor

    session = simulated_session(duration_s=1.5, frame_rate_hz=20.0, noise=0.1, seed=5)
    scene = session.scene
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    observations = [reconstructor.observe(frame) for frame in session.frames]
    original = make_estimator("ukf", scene.catheter)
    for observation in observations[:10]:
        original.step(observation)
    twins = [copy.deepcopy(original), pickle.loads(pickle.dumps(original))]
    for observation in observations[10:]:
        want = original.step(observation)
        assert want.valid
        for twin in twins:
            got = twin.step(observation)
            assert (got.delta_L_rad, got.std_rad, got.flags) == (
                want.delta_L_rad, want.std_rad, want.flags
            )
