"""Bad input and faults (issue 14), the streams: datagrams and estimator inputs.

- a joint or marker datagram: dropped and counted by reason, the good ones around it kept;
- an estimator input: a one-line ValueError or a flagged step, and the filter unharmed after
  it (the next steps as if the bad one had not come).
"""

from __future__ import annotations

import dataclasses
import math
import socket
import struct
import time

import numpy as np
import pytest

from replay.simulation.sources import simulated_session
from tests.faults_common import P, _joints
from tracker.estimators import make_estimator
from tracker.io.datagrams import (
    ESTIMATE_STRUCT,
    JOINT_STRUCT,
    MARKER_MAGIC,
    VERSION,
    JointFlags,
    encode_joints,
    encode_markers,
)
from tracker.io.udp import CLOCK_JUMP_SAMPLES, JointReceiver, MarkerReceiver
from tracker.reconstruction import Reconstructor


# ------------------------------------------------------------------------------- datagrams
def _joint_datagram(k: int, time_s: float | None = None) -> bytes:
    """Good datagram k: 1 kHz samples from t = 1000 s on the sender's clock."""
    t = 1000.0 + k * 1e-3 if time_s is None else time_s
    values, rates = _joints([k * 1e-3])
    return encode_joints(k, t, values[0], rates[0])


def _raw_joint(k: int, *, magic=None, version=VERSION, flags=0, values=None) -> bytes:
    q, q_dot = _joints([k * 1e-3])
    doubles = values or [1000.0 + k * 1e-3, *q[0], *q_dot[0]]
    return JOINT_STRUCT.pack(magic or 0x564A5443, version, flags, k, 0, *doubles)


def _with(k: int, index: int, value: float, flags: int = 0) -> bytes:
    q, q_dot = _joints([k * 1e-3])
    doubles = [1000.0 + k * 1e-3, *q[0], *q_dot[0]]
    doubles[index] = value
    return _raw_joint(k, values=doubles, flags=flags)


JOINT_FAULTS = [
    # (name, bad datagram sent after good datagram 50, the counter it goes to)
    ("truncated", _joint_datagram(51)[:40], "size"),
    ("one byte too long", _joint_datagram(51) + b"\x00", "size"),
    ("empty", b"", "size"),
    ("bad magic", _raw_joint(51, magic=0x12345678), "magic"),
    ("bad version", _raw_joint(51, version=7), "version"),
    ("time NaN", _with(51, 0, math.nan), "non-finite"),
    ("q_r inf", _with(51, 1, math.inf), "non-finite"),
    ("q_p NaN", _with(51, 2, math.nan), "non-finite"),
    ("rate NaN without NO_RATES", _with(51, 4, math.nan), "non-finite"),
    ("q_r 1e300", _with(51, 1, 1e300), "range"),
    ("q_p -1e300", _with(51, 2, -1e300), "range"),
    ("q_d 1000 mm", _with(51, 3, 1e3), "range"),
    ("q_r rate 1e300", _with(51, 4, 1e300), "range"),
    ("q_r 1e300 with NO_RATES", _with(51, 1, 1e300, int(JointFlags.NO_RATES)), "range"),
    ("time 1e300", _with(51, 0, 1e300), "range"),
    ("stamped 1e6 s ahead", _joint_datagram(51, time_s=1e6), "time"),
    ("stamped 10 s ahead", _joint_datagram(51, time_s=1010.0), "time"),
    ("stamped 1e6 s back", _joint_datagram(51, time_s=-1e6 + 1000.0), "stale"),
    ("a repeat", _joint_datagram(50), "duplicate"),
    ("an old sequence", _joint_datagram(20), "stale"),
    ("a marker datagram", encode_markers(51, 1000.0, (np.ones((2, 2)),) * 2, (1.0, 1.0)), "magic"),
    ("an estimate datagram", ESTIMATE_STRUCT.pack(0x53455443, 1, 0, 51, 0, *[0.0] * 6), "magic"),
    ("72 random bytes", np.random.default_rng(0).bytes(72), "magic"),
    ("72 zero bytes", bytes(72), "magic"),
]


@pytest.mark.parametrize(("name", "bad", "reason"), JOINT_FAULTS, ids=[c[0] for c in JOINT_FAULTS])
def test_joint_datagram_faults_are_counted_and_the_stream_goes_on(name, bad, reason):
    receiver = JointReceiver(port=None, clock="aligned")
    good = [_joint_datagram(k) for k in range(100)]
    for k, data in enumerate(good):
        arrival = 5.0 + k * 1e-3
        receiver.add_datagram(data, arrival)
        if k == 50:
            assert receiver.add_datagram(bad, arrival) == 0
    counts = receiver.counts
    assert counts.received == 101 and counts.accepted == 100, counts
    dropped = {"stale": counts.stale, "duplicate": counts.duplicate, **counts.malformed}
    assert dropped == {"stale": 0, "duplicate": 0, reason: 1} | (
        {reason: 1} if reason in ("stale", "duplicate") else {}
    ), dropped
    np.testing.assert_allclose(receiver.sample_times(), 5.0 + np.arange(100) * 1e-3, atol=1e-9)
    sample = receiver.sample(5.0 + 0.0985)
    assert sample.usable and np.allclose(sample.q, _joints([0.0985])[0][0], atol=1e-6)


def test_a_sender_clock_jump_restarts_the_history_instead_of_freezing_it():
    """A controller whose clock jumps (sequence going on) is followed after a few samples."""
    receiver = JointReceiver(port=None, clock="aligned")
    for k in range(200):
        jump = 1e6 if k >= 100 else 0.0
        receiver.add_datagram(_joint_datagram(k, time_s=1000.0 + k * 1e-3 + jump), 5 + k * 1e-3)
    counts = receiver.counts
    assert counts.restarts == 1 and counts.malformed == {} and counts.accepted == 200
    assert len(receiver) == 200 - 100
    assert receiver.newest.sequence == 199 and CLOCK_JUMP_SAMPLES < 100


def test_a_first_datagram_stamped_far_ahead_does_not_freeze_the_stream():
    """With no history to judge it by, the first datagram is kept; the good ones that follow
    agree with each other, not with it, and take over after a few samples."""
    receiver = JointReceiver(port=None, clock="aligned")
    receiver.add_datagram(_joint_datagram(0, time_s=1e6), 5.0)
    for k in range(1, 100):
        receiver.add_datagram(_joint_datagram(k), 5.0 + k * 1e-3)
    assert receiver.counts.restarts == 1 and receiver.newest.sequence == 99
    assert len(receiver) == 99 and receiver.sample_times()[-1] == pytest.approx(5.099)
    assert receiver.sample(5.0985).usable


def test_a_flood_of_garbage_is_counted_and_the_good_datagrams_kept():
    receiver = JointReceiver(port=None)
    rng = np.random.default_rng(2)
    for k in range(100):
        for _ in range(100):
            receiver.add_datagram(rng.bytes(int(rng.integers(0, 100))), 5 + k * 1e-3)
        receiver.add_datagram(_joint_datagram(k), 5 + k * 1e-3)
    assert receiver.counts.accepted == 100 and receiver.counts.malformed_total == 10_000


def _marker_datagram(k: int) -> bytes:
    """Good marker datagram k: both views, 20 fps from t = 1000 s."""
    return encode_markers(k, 1000.0 + 0.05 * k, (np.full((P, 2), 100.0 + k),) * 2, (1.0, 1.0))


def _marker_head(n_points=P, views=2, magic=MARKER_MAGIC, version=VERSION, time_s=1000.0) -> bytes:
    head = struct.pack("<IHHIHHd", magic, version, 0, 9, n_points, views, time_s)
    return head + np.full(views * n_points * 3, 1.0).astype("<f8").tobytes()


def _bad_row(value: float, column: int) -> bytes:
    rows = np.full((2, P, 3), 1.0)
    rows[0, 0, column] = value
    head = struct.pack("<IHHIHHd", MARKER_MAGIC, VERSION, 0, 9, P, 2, 1000.0)
    return head + rows.astype("<f8").tobytes()


MARKER_FAULTS = [
    ("shorter than a header", b"CTMK", "size"),
    ("one byte too long", _marker_datagram(9) + b"\x00", "size"),
    ("bad magic", _marker_head(magic=0x11111111), "magic"),
    ("bad version", _marker_head(version=3), "version"),
    ("no points", _marker_head(n_points=0)[:24], "points"),
    ("65 points", _marker_head(n_points=65), "points"),
    ("one view", _marker_head(views=1), "views"),
    ("nine views", _marker_head(views=9), "views"),
    ("points unlike the catheter's", _marker_head(n_points=P + 1), "points"),
    ("views unlike the rig's", _marker_head(views=3), "views"),
    ("time NaN", _marker_head(time_s=math.nan), "non-finite"),
    ("time 1e300", _marker_head(time_s=1e300), "range"),
    ("u inf", _bad_row(math.inf, 0), "non-finite"),
    ("v 1e300", _bad_row(1e300, 1), "range"),
    ("sigma 0", _bad_row(0.0, 2), "sigma"),
    ("sigma negative", _bad_row(-1.0, 2), "sigma"),
    ("sigma NaN on a present point", _bad_row(math.nan, 2), "non-finite"),
    ("sigma 1e300", _bad_row(1e300, 2), "range"),
    ("a joint datagram", _joint_datagram(3), "magic"),
]


@pytest.fixture(scope="module")
def markers_socket():
    with (
        MarkerReceiver(port=0, n_points=P, n_views=2) as receiver,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender,
    ):
        yield receiver, sender


@pytest.mark.parametrize(
    ("name", "bad", "reason"), MARKER_FAULTS, ids=[c[0] for c in MARKER_FAULTS]
)
def test_marker_datagram_faults_are_counted_and_the_good_ones_kept(
    markers_socket, name, bad, reason
):
    receiver, sender = markers_socket
    before = dict(receiver.counts.malformed)
    accepted = receiver.counts.accepted
    for data in (_marker_datagram(1), bad, _marker_datagram(2)):
        sender.sendto(data, receiver.address)
    got = []
    deadline = time.monotonic() + 5.0
    while len(got) < 2 and time.monotonic() < deadline:
        got += receiver.receive(0.1)
    assert [round(m.time_s, 6) for m in got] == [1000.05, 1000.1]
    assert receiver.counts.accepted == accepted + 2
    after = receiver.counts.malformed
    assert {k: after[k] - before.get(k, 0) for k in after if after[k] != before.get(k, 0)} == {
        reason: 1
    }


# ------------------------------------------------------------------------ estimator inputs
@pytest.fixture(scope="module")
def observations():
    s = simulated_session(duration_s=2.5, seed=1)
    scene = s.scene
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    return scene.catheter, reconstructor.observe_batch(s.frames)


K = 30  # the bad observation replaces this one
I3 = np.eye(3)
ESTIMATOR_FAULTS = [
    # Only the cases the UKF already handles; the rest are the estimator API's own work.
    ("tip covariance zero", dict(tip_cov_b=np.zeros((3, 3)))),
    ("tip covariance singular", dict(tip_cov_b=np.diag([1.0, 0.0, 0.0]))),
    ("tip covariance negative", dict(tip_cov_b=-I3)),
    ("tip covariance NaN", dict(tip_cov_b=np.full((3, 3), np.nan))),
    ("tip 1e10 mm", dict(tip_b_mm=np.full(3, 1e10))),
    ("tip 1e300 mm", dict(tip_b_mm=np.full(3, 1e300))),
    ("tip inf", dict(tip_b_mm=np.array([np.inf, 0.0, 0.0]))),
    ("joint value NaN", dict(q=np.array([np.nan, 0.5, 0.2]))),
    ("time NaN", dict(time_s=np.nan)),
    ("time before the last frame", dict(time_s=-1.0)),
    ("marker covariance zero", "markers_cov_b"),
    ("markers 1e10 mm", "markers_b_mm"),
    ("markers of the wrong shape", dict(markers_b_mm=np.zeros((5, 3)))),
    ("tip covariance tiny", dict(tip_cov_b=1e-30 * I3)),
    ("tip covariance huge", dict(tip_cov_b=1e300 * I3)),
    ("tip covariance not symmetric", dict(tip_cov_b=I3 + np.triu(np.ones((3, 3)), 1))),
    ("q_r 1e300", dict(q=np.array([1e300, 0.5, 0.2]))),
    ("q_dot 1e300", dict(q_dot=np.array([0.0, 1e300, 0.0]))),
    ("q_dot NaN", dict(q_dot=np.array([np.nan, 0.0, 0.0]))),
    ("velocity 1e300", dict(velocity_b_mm_s=np.full(3, 1e300))),
    ("velocity covariance zero", dict(velocity_cov_b=np.zeros((3, 3)))),
    ("time equal to the last frame", "same time"),
    ("time 1e9 s ahead", "far future"),
]


def _bad_observation(observation, change, previous=None):
    if change == "markers_cov_b":
        change = dict(markers_cov_b=np.zeros_like(observation.markers_cov_b))
    elif change == "markers_b_mm":
        change = dict(markers_b_mm=np.full_like(observation.markers_b_mm, 1e10))
    elif change == "same time":
        change = dict(time_s=previous.time_s)
    elif change == "far future":
        change = dict(time_s=observation.time_s + 1e9)
    return dataclasses.replace(observation, **change)


def _run(catheter, sequence):
    estimator = make_estimator("ukf", catheter)
    out = []
    for observation in sequence:
        try:
            out.append(estimator.step(observation))
        except ValueError as error:
            out.append(error)
    return out


@pytest.fixture(scope="module")
def reference(observations):
    """The UKF on the frames without the K-th (the bad one, skipped)."""
    catheter, obs = observations
    return _run(catheter, obs[:K] + obs[K + 1 :])


@pytest.mark.parametrize(("name", "change"), ESTIMATOR_FAULTS, ids=[c[0] for c in ESTIMATOR_FAULTS])
def test_estimator_input_faults_are_flagged_and_do_not_poison_the_filter(
    observations, reference, name, change
):
    catheter, obs = observations
    out = _run(catheter, obs[:K] + [_bad_observation(obs[K], change, obs[K - 1])] + obs[K + 1 :])
    step = out[K]
    if isinstance(step, ValueError):
        assert "\n" not in str(step)
    else:
        assert step.flags or not step.valid, step
    later, expected = out[K + 1 :], reference[K:]
    assert not any(isinstance(e, Exception) for e in later), later
    assert all(e.valid for e in later[5:])
    error = np.array([e.delta_L_rad - r.delta_L_rad for e, r in zip(later, expected, strict=True)])
    assert np.max(np.abs(error)) < 0.02  # rad: the filter goes on as if the frame was skipped
