"""Joint values at image times (tracker.io.joints): one rule for live and for recordings."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from models.model_file import DEFAULT_MODEL_PATH
from models.pose import Pose
from models.rig_file import rig_toml
from replay.simulation.render import default_render_rig
from tracker.io.datagrams import JointPacket
from tracker.io.joints import RATE_WINDOW_S, JointHistory, JointSample, JointStatus
from tracker.io.recording import RecordingWriter, open_recording
from tracker.io.udp import JointReceiver
from tracker.types import Frame

PROPERTY_SETTINGS = dict(
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)


def wave(t):
    """A smooth joint motion and its rates."""
    t = np.asarray(t, dtype=float)
    q = np.column_stack([0.3 + 0.2 * np.sin(3 * t), 0.6 + 0.1 * t, -0.4 + 0.05 * np.cos(5 * t)])
    q_dot = np.column_stack([0.6 * np.cos(3 * t), np.full_like(t, 0.1), -0.25 * np.sin(5 * t)])
    return q, q_dot


def test_values_and_measured_rates_are_interpolated_linearly():
    t = np.arange(0.0, 1.0, 0.001)
    a, b = np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.25, -0.125])
    history = JointHistory(t, a + np.outer(t, b), np.tile(b, (t.size, 1)))
    times = np.array([0.0, 0.0004, 0.5, 0.7777, t[-1]])
    q, q_dot, gap_s = history.interpolate(times)
    np.testing.assert_allclose(q, a + np.outer(times, b), rtol=0, atol=1e-12)
    np.testing.assert_allclose(q_dot, np.tile(b, (times.size, 1)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(gap_s, [0.0, 0.001, 0.0, 0.001, 0.0], atol=1e-9)
    # at a sample: its values bit for bit
    np.testing.assert_array_equal(history.interpolate(t[123])[0][0], history.q[123])


def test_unmeasured_rates_are_the_slope_over_the_window_kept_inside_the_samples():
    t = np.arange(0.0, 1.0, 0.001)
    q, _ = wave(t)
    history = JointHistory(t, q)  # no rates
    times = np.array([0.0, 0.3, 0.6, t[-1]])
    _, q_dot, _ = history.interpolate(times)
    lo = np.clip(times - RATE_WINDOW_S / 2, t[0], t[-1] - RATE_WINDOW_S)
    hi = lo + RATE_WINDOW_S
    q_lo, _, _ = history.interpolate(lo)
    q_hi, _, _ = history.interpolate(hi)
    np.testing.assert_allclose(q_dot, (q_hi - q_lo) / RATE_WINDOW_S, rtol=0, atol=1e-9)
    # close to the true rates in the middle (the window is short against the motion)
    np.testing.assert_allclose(q_dot[1:3], wave(times[1:3])[1], rtol=0, atol=2e-3)
    # a single sample has no slope: rates 0
    single = JointHistory(t[:1], q[:1])
    np.testing.assert_array_equal(single.interpolate(0.5)[1], np.zeros((1, 3)))


def test_outside_the_history_the_end_samples_are_held():
    t = np.arange(1.0, 2.0, 0.01)
    q, q_dot = wave(t)
    history = JointHistory(t, q, q_dot)
    values, rates, gap_s = history.interpolate([0.5, 2.5])
    np.testing.assert_array_equal(values, q[[0, -1]])
    np.testing.assert_array_equal(rates, q_dot[[0, -1]])
    assert np.all(np.isinf(gap_s))
    assert history.sample(t[-1] + 0.05, stale_after_s=0.1).status is JointStatus.HELD
    assert history.sample(t[-1] + 0.5, stale_after_s=0.1).status is JointStatus.STALE
    assert history.sample(t[0] - 0.05, stale_after_s=0.1).status is JointStatus.CLAMPED
    assert history.sample(1.5, stale_after_s=0.1).status is JointStatus.OK
    empty = JointHistory(np.zeros(0), np.zeros((0, 3)))
    none = empty.sample(1.0, stale_after_s=0.1)
    assert none.status is JointStatus.NONE and math.isinf(none.age_s)
    assert np.all(np.isnan(none.q))


@pytest.mark.parametrize("rates", [True, False])
def test_live_receiver_and_recording_give_the_same_joint_values(tmp_path, rates):
    """The same joint samples, received live or read from a recording, give a frame the
    same joint values and rates."""
    t = np.arange(0.0, 1.0, 0.001)
    q, q_dot = wave(t)
    receiver = JointReceiver(port=None, clock="sender", history=t.size)
    for k in range(t.size):
        rate = q_dot[k] if rates else np.full(3, np.nan)
        receiver.add(JointPacket(k, float(t[k]), q[k], rate), arrival_s=0.0)
    frame_times = np.arange(0.0123, 0.98, 0.0479)
    path = tmp_path / "joints.mcap"
    P = 4
    uv = np.full((P, 2), 1.0)
    cov = np.tile(np.eye(2), (P, 1, 1))
    with RecordingWriter(
        path,
        model_toml=DEFAULT_MODEL_PATH.read_text(),
        rig_toml=rig_toml(default_render_rig(), Pose.identity()),
    ) as writer:
        writer.write_joints(t, q, q_dot if rates else None)
        for time_s in frame_times:
            writer.write_frame(Frame(time_s, np.zeros(3), None, (uv, uv), (cov, cov)))
    with open_recording(path) as recording:
        recorded = [x.frame for x in recording.frames()]
    assert len(recorded) == frame_times.size
    for frame in recorded:
        live = receiver.sample(frame.time_s)
        assert live.status is JointStatus.OK
        np.testing.assert_allclose(frame.q, live.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(frame.q_dot, live.q_dot, rtol=0, atol=1e-9)


# ------------------------------------------------------- one time: the array path, bit for bit
def sample_by_interpolation(
    history: JointHistory, time_s: float, stale_after_s: float, rate_window_s=RATE_WINDOW_S
) -> JointSample:
    """:meth:`JointHistory.sample` as it was before its single-time path: the array path
    (:meth:`JointHistory.interpolate`) at one time, then the status rule."""
    time_s = float(time_s)
    t = np.asarray(history.time_s, dtype=float)
    q, q_dot, _ = history.interpolate(time_s, rate_window_s)
    if t.size == 0:
        return JointSample(time_s, q[0], q_dot[0], JointStatus.NONE, math.inf)
    age = time_s - float(t[-1])
    if age > 0:
        status = JointStatus.HELD if age <= stale_after_s else JointStatus.STALE
    elif time_s < t[0]:
        early = float(t[0]) - time_s
        status = JointStatus.CLAMPED if early <= stale_after_s else JointStatus.STALE
    else:
        status = JointStatus.OK
    return JointSample(time_s, q[0], q_dot[0], status, age)


def assert_same_sample(got: JointSample, expected: JointSample) -> None:
    """Equal bit for bit: the same status, and the same bytes in every number (NaN and the
    sign of zero included)."""
    assert got.status is expected.status
    for name in ("time_s", "q", "q_dot", "age_s"):
        a, b = np.asarray(getattr(got, name)), np.asarray(getattr(expected, name))
        np.testing.assert_array_equal(a, b, err_msg=name)  # NaN where NaN
        assert a.shape == b.shape and a.tobytes() == b.tobytes(), name


def query_times(times_s, stale_after_s: float) -> np.ndarray:
    """At every sample and just off it, between neighbours, before the oldest and after the
    newest (within the timeout, at it, beyond it), far off, and not a time."""
    t = np.unique(np.asarray(times_s, dtype=float))
    special = [0.0, -1.0, 1e12, math.nan, math.inf, -math.inf]
    if t.size == 0:
        return np.array(special)
    stale = stale_after_s * np.array([0.5, 1.0, 2.0])
    return np.concatenate(
        [
            t,
            np.nextafter(t, math.inf),
            np.nextafter(t, -math.inf),
            (t[:-1] + t[1:]) / 2,
            t[:-1] + 0.1 * np.diff(t),
            t[0] - stale,
            t[-1] + stale,
            special,
        ]
    )


def random_rates(rng, n: int, kind: str) -> np.ndarray | None:
    """Measured rates, none, or some rows not measured (NaN rows, and rows with one NaN)."""
    if kind == "none":
        return None
    q_dot = rng.uniform(-3.0, 3.0, (n, 3))
    if kind == "some missing":
        q_dot[rng.random(n) < 0.4] = np.nan
        q_dot[rng.random(n) < 0.2, rng.integers(0, 3)] = np.nan
    return q_dot


@settings(max_examples=300, **PROPERTY_SETTINGS)
@given(
    steps_s=st.lists(st.sampled_from([0.0, 0.0, 1e-3, 2.5e-4, 0.011, 0.3, 1e-12]), max_size=12),
    start_s=st.sampled_from([0.0, -2.5, 1000.0, 1.7e9]),
    rates=st.sampled_from(["measured", "none", "some missing", "some missing"]),
    rate_window_s=st.sampled_from([RATE_WINDOW_S, 0.0, 1e-3, 1.0]),
    stale_after_s=st.sampled_from([0.1, 0.011]),
    seed=st.integers(0, 2**32 - 1),
)
def test_one_time_is_sampled_bit_for_bit_as_the_array_path_gives(
    steps_s, start_s, rates, rate_window_s, stale_after_s, seed
):
    """Random histories (repeated times, rates missing in some rows or all): the single-time
    path of JointHistory.sample gives what interpolate gives, bit for bit, at every kind of
    time, and so does interpolate of all those times at once."""
    rng = np.random.default_rng(seed)
    n = len(steps_s)
    t = start_s + np.cumsum(steps_s)
    history = JointHistory(t, rng.uniform(-1.0, 1.0, (n, 3)), random_rates(rng, n, rates))
    times = query_times(t, stale_after_s)
    q_all, q_dot_all, _ = history.interpolate(times, rate_window_s)
    for k, time_s in enumerate(times):
        got = history.sample(time_s, stale_after_s, rate_window_s)
        expected = sample_by_interpolation(history, time_s, stale_after_s, rate_window_s)
        assert_same_sample(got, expected)
        np.testing.assert_array_equal(got.q, q_all[k])
        np.testing.assert_array_equal(got.q_dot, q_dot_all[k])


def test_at_repeated_end_times_the_single_time_path_takes_the_array_paths_row():
    """Two samples at the newest time: held after it, the array path keeps the first of them
    (its bracket has no width); so must the single-time path."""
    t = np.array([0.0, 0.001, 0.002, 0.002])
    q = np.arange(12.0).reshape(4, 3)
    history = JointHistory(t, q, q + 100.0)
    for time_s in (0.002, 0.0025, 0.5, -0.5, 0.0015):
        got = history.sample(time_s, stale_after_s=0.1)
        assert_same_sample(got, sample_by_interpolation(history, time_s, 0.1))
    np.testing.assert_array_equal(history.sample(0.0025, 0.1).q, q[2])
