"""Rehearsals: the live loop runs the last frame's reconstruction and estimator step again
just before the next frame is due (``LiveTracker.prime``) so that their code and data are
in the caches; a rehearsal must change nothing that the next frame's step sees."""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np
import pytest

from replay.simulation.sources import simulated_session
from tracker.estimators import make_estimator
from tracker.estimators.checks import MAX_TIME_STEP_S, CheckedEstimator
from tracker.reconstruction import Reconstructor
from tracker.types import Flag, Observation

FIELDS = ("delta_L_rad", "std_rad", "flags", "nis", "nis_dof", "rejected_outliers")


@pytest.fixture(scope="module")
def session():
    return simulated_session(duration_s=4.0, frame_rate_hz=20.0, noise=0.3, seed=11)


def damaged(frames):
    """The session's frames with what a lab gives: a marker missing in one view, a frame
    with one view lost, a NaN point (each a different path through the steps)."""
    frames = list(frames)
    for k in range(7, len(frames), 9):
        uv = [u.copy() for u in frames[k].uv]
        uv[k % 2][1] = np.nan  # one marker not found in one view
        frames[k] = dataclasses.replace(frames[k], uv=tuple(uv))
    for k in range(12, len(frames), 23):
        uv = [u.copy() for u in frames[k].uv]
        uv[1][:] = np.nan  # the second view lost
        frames[k] = dataclasses.replace(frames[k], uv=tuple(uv))
    return frames


def reconstructor_of(session):
    scene = session.scene
    return Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)


def same_observation(a: Observation, b: Observation) -> None:
    for field in dataclasses.fields(Observation):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=field.name)
        elif isinstance(x, tuple):
            assert len(x) == len(y)
            for u, v in zip(x, y, strict=True):
                assert type(u) is type(v)
                if dataclasses.is_dataclass(u):
                    for f in dataclasses.fields(u):
                        p, q = getattr(u, f.name), getattr(v, f.name)
                        if isinstance(p, np.ndarray):
                            np.testing.assert_array_equal(p, q, err_msg=f.name)
        else:
            assert x == y or (x != x and y != y), field.name


def test_a_rehearsed_reconstruction_changes_nothing(session):
    """Each frame observed after the last one was rehearsed at its time gives exactly the
    observation it gives without (its finite-difference velocity from the last frame, not
    from the rehearsal); a frame the reconstruction refuses is rehearsed without a raise."""
    frames = damaged(session.frames)
    plain, rehearsed = reconstructor_of(session), reconstructor_of(session)
    velocities = 0
    for k, frame in enumerate(frames):
        if k:
            rehearsed.rehearse(dataclasses.replace(frames[k - 1], time_s=frame.time_s))
        want, got = plain.observe(frame), rehearsed.observe(frame)
        same_observation(got, want)
        velocities += got.velocity_b_mm_s is not None
    assert velocities > len(frames) // 2  # the velocity path was taken
    # A point short in every view (the model's tip and markers expected).
    wrong = dataclasses.replace(
        frames[0], uv=tuple(u[:1] for u in frames[0].uv), cov=tuple(c[:1] for c in frames[0].cov)
    )
    with pytest.raises(ValueError):
        plain.observe(wrong)
    rehearsed.rehearse(wrong)


def run_estimators(session, observations, rehearse: bool, prepare_first: bool):
    """The loop's order for each frame: (prepare at its joints), the last frame rehearsed at
    its time, (prepare), its step; the estimates and the filter's state after each."""
    ukf = make_estimator("ukf", session.scene.catheter)
    inner = ukf.inner
    out = []
    for k, observation in enumerate(observations):
        if prepare_first:
            inner.prepare(observation.q)
        if rehearse and k:
            held = inner._expansion.held
            ukf.rehearse(dataclasses.replace(observations[k - 1], time_s=observation.time_s))
            assert inner._expansion.held is held  # what prepare computed is still there
        if not prepare_first:
            inner.prepare(observation.q)
        estimate = ukf.step(observation)
        bank = inner._bank
        out.append((estimate, bank.x.copy(), bank.P.copy(), bank.log_weight.copy(),
                    bank.active.copy(), inner.hypotheses))  # fmt: skip
    return out


@pytest.mark.parametrize("prepare_first", [False, True])
def test_a_rehearsed_estimator_step_changes_nothing(session, prepare_first):
    """Over a session with damaged frames (partial, one view, NaN, predict only, an
    outlier) from the first frame on, every estimate and the filter's whole state after
    each step are those of a filter never rehearsed, to the bit; whether the model was
    prepared at the frame's joints before the rehearsal or after."""
    recon = reconstructor_of(session)
    observations = [recon.observe(frame) for frame in damaged(session.frames)]
    for k in range(5, len(observations), 17):  # joints without markers: predict only
        observations[k] = Observation(time_s=observations[k].time_s, q=observations[k].q)
    k = 30  # a tip 4 mm off: an outlier
    observations[k] = dataclasses.replace(
        observations[k], tip_b_mm=observations[k].tip_b_mm + [4.0, 0.0, 0.0]
    )
    plain = run_estimators(session, observations, False, prepare_first)
    rehearsed = run_estimators(session, observations, True, prepare_first)
    seen = Flag.NONE
    for row in plain:
        seen |= row[0].flags
    assert Flag.PARTIAL in seen and Flag.NO_MEASUREMENT in seen  # the paths taken
    assert Flag.OUTLIER_REJECTED in seen
    for (a, *state_a), (b, *state_b) in zip(plain, rehearsed, strict=True):
        for field in FIELDS:
            x, y = getattr(a, field), getattr(b, field)
            assert x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y)), field
        for u, v in zip(state_a, state_b, strict=True):
            np.testing.assert_array_equal(u, v)


def stepped_filter(session, steps: int, frames: int):
    """A checked UKF stepped through the session's first ``steps`` observations, and the
    first ``frames`` observations."""
    recon = reconstructor_of(session)
    observations = [recon.observe(frame) for frame in session.frames[:frames]]
    ukf = make_estimator("ukf", session.scene.catheter)
    for observation in observations[:steps]:
        ukf.step(observation)
    return ukf, observations


def test_a_rehearsal_leaves_the_filter_s_own_arrays_in_place(session):
    """After a rehearsal the filter holds the very arrays it held before, of the same
    type, layout and contents (a copy of another layout would make the compiled step
    compile again, for seconds, on the next live frame)."""
    ukf, observations = stepped_filter(session, 6, 8)
    bank = ukf.inner._bank
    before = dict(vars(bank))
    contents = {k: v.copy() for k, v in before.items() if isinstance(v, np.ndarray)}
    types = {k: numba.typeof(v) for k, v in before.items() if isinstance(v, np.ndarray)}
    ukf.rehearse(dataclasses.replace(observations[6], time_s=observations[7].time_s))
    assert vars(bank).keys() == before.keys()
    for name, value in before.items():
        assert vars(bank)[name] is value, name
    for name, value in contents.items():
        np.testing.assert_array_equal(vars(bank)[name], value, err_msg=name)
        assert numba.typeof(vars(bank)[name]) == types[name], name


def test_a_rehearsal_the_step_refuses_is_ignored(session):
    """A rehearsal at a time before the filter's, or of an observation the checks refuse,
    raises nothing and changes nothing."""
    ukf, observations = stepped_filter(session, 5, 6)
    bank = ukf.inner._bank
    state = {k: v.copy() for k, v in vars(bank).items() if isinstance(v, np.ndarray)}
    ukf.rehearse(observations[2])  # before the filter's time
    ukf.inner.rehearse(observations[2])  # the same, past the checks
    nan = dataclasses.replace(observations[5], markers_b_mm=observations[5].markers_b_mm * np.nan)
    ukf.rehearse(nan)
    for name, value in state.items():
        np.testing.assert_array_equal(getattr(bank, name), value, err_msg=name)
    want, _ = stepped_filter(session, 5, 6)
    a, b = ukf.step(observations[5]), want.step(observations[5])
    assert [getattr(a, f) for f in FIELDS] == [getattr(b, f) for f in FIELDS]


class Spy:
    """An estimator that keeps what it is asked to rehearse."""

    def __init__(self):
        self.rehearsed = []

    def rehearse(self, observation):
        self.rehearsed.append(observation.time_s)

    def step(self, observation):
        raise AssertionError("a rehearsal must not step")


def test_the_checks_pass_on_only_a_rehearsal_the_step_would_accept(session):
    """The checked wrapper rehearses its estimator for an observation after the last
    accepted one that passes the checks; it neither rehearses nor records anything else."""
    recon = reconstructor_of(session)
    observations = [recon.observe(frame) for frame in session.frames[:3]]
    spy = Spy()
    checked = CheckedEstimator(spy, n_markers=len(session.scene.catheter.marker_arclengths_mm))
    checked._last_time_s = observations[1].time_s
    checked.rehearse(observations[0])  # before the last accepted
    checked.rehearse(observations[1])  # not after it
    checked.rehearse(dataclasses.replace(observations[2], time_s=math.nan))
    far = observations[1].time_s + 2.0 * MAX_TIME_STEP_S  # a step the checks would refuse
    checked.rehearse(dataclasses.replace(observations[2], time_s=far))
    checked.rehearse(dataclasses.replace(observations[2], q=observations[2].q * np.nan))
    assert spy.rehearsed == []
    checked.rehearse(observations[2])
    assert spy.rehearsed == [observations[2].time_s]
    assert checked._last_time_s == observations[1].time_s
    CheckedEstimator(object(), n_markers=1).rehearse(observations[2])  # none: nothing
