"""Datagram layouts and the UDP receivers/sender, over real loopback sockets."""

from __future__ import annotations

import math
import socket
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.tracker.test_joints import (
    PROPERTY_SETTINGS,
    assert_same_sample,
    query_times,
    sample_by_interpolation,
)
from tracker.io.datagrams import (
    ESTIMATE_STRUCT,
    JOINT_MAGIC,
    JOINT_STRUCT,
    MARKER_MAGIC,
    DatagramError,
    JointFlags,
    JointPacket,
    SegmentedMarkers,
    decode_estimate,
    decode_joints,
    decode_markers,
    encode_estimate,
    encode_joints,
    encode_markers,
    encode_segmented,
    marker_datagram_size,
)
from tracker.io.joints import JointHistory, JointStatus
from tracker.io.limits import joint_sample_in_range, joints_in_range
from tracker.io.udp import EstimateSender, JointReceiver, MarkerReceiver
from tracker.types import Estimate, Flag

LOOPBACK = "127.0.0.1"


def ramp_q(t):
    """A linear joint trajectory: exact under linear interpolation."""
    q_dot = np.array([0.5, -0.2, 0.3])
    return np.array([0.1, 0.2, -0.3]) + q_dot * t, q_dot


@pytest.fixture
def sender():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        yield sock


# ------------------------------------------------------------------------------ layouts
def test_joint_datagram_round_trip_and_layout():
    data = encode_joints(7, 1.25, [0.1, 0.2, 0.3], [1.0, 2.0, 3.0])
    assert len(data) == JOINT_STRUCT.size == 72
    assert data[:4] == b"CTJV" and struct.unpack_from("<I", data)[0] == JOINT_MAGIC
    # Every double starts at a multiple of 8 bytes.
    assert struct.unpack_from("<d", data, 16)[0] == 1.25
    assert struct.unpack_from("<d", data, 24)[0] == 0.1
    assert struct.unpack_from("<d", data, 64)[0] == 3.0
    packet = decode_joints(data)
    assert packet.sequence == 7 and packet.time_s == 1.25
    np.testing.assert_array_equal(packet.q, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(packet.q_dot, [1.0, 2.0, 3.0])
    assert packet.flags == JointFlags.NONE


def test_joint_datagram_without_rates():
    packet = decode_joints(encode_joints(1, 0.0, [0.0, 0.1, 0.2]))
    assert packet.flags & JointFlags.NO_RATES
    assert np.all(np.isnan(packet.q_dot))


def test_joint_datagram_without_rates_carries_nan_rates_whatever_was_sent():
    data = JOINT_STRUCT.pack(JOINT_MAGIC, 1, 0xFFFF, 3, 0, 0.5, 0.1, 0.2, 0.3, 1e300, 2.0, 3.0)
    packet = decode_joints(data)  # unknown flag bits are ignored; the rate fields are not read
    assert packet.flags is JointFlags.NO_RATES and packet.q == (0.1, 0.2, 0.3)
    assert all(math.isnan(r) for r in packet.q_dot)


def test_one_joint_sample_is_range_checked_by_the_rule_for_many():
    """The decoder's per-datagram check in plain floats is joints_in_range's rule."""
    rng = np.random.default_rng(3)
    special = [0.0, 100.0, -100.0, np.nextafter(100.0, 200.0), 1e4, 1e5, 1e300, np.inf, np.nan]
    q = rng.choice(special, (400, 3))
    q_dot = rng.choice(special, (400, 3))
    for rates in (q_dot, None):
        expected = joints_in_range(q, rates)
        got = [
            joint_sample_in_range(tuple(q[k]), None if rates is None else tuple(rates[k]))
            for k in range(len(q))
        ]
        np.testing.assert_array_equal(got, expected)
    assert expected.any() and not expected.all()


@pytest.mark.parametrize(
    "data, reason",
    [
        (encode_joints(1, 0.0, [0, 0, 0], [0, 0, 0])[:40], "size"),  # truncated
        (encode_joints(1, 0.0, [0, 0, 0], [0, 0, 0]) + b"\0", "size"),
        (b"\x01\x02\x03", "size"),
        (b"G" * 72, "magic"),
        (struct.pack("<IHHII7d", JOINT_MAGIC, 2, 0, 1, 0, *[0.0] * 7), "version"),
        (encode_joints(1, 0.0, [0, math.nan, 0], [0, 0, 0]), "non-finite"),
        (encode_joints(1, math.inf, [0, 0, 0], [0, 0, 0]), "non-finite"),
        (encode_joints(1, 0.0, [0, 0, 0], [0, math.inf, 0]), "non-finite"),
    ],
)
def test_joint_decoder_rejects_with_a_reason(data, reason):
    with pytest.raises(DatagramError) as info:
        decode_joints(data)
    assert info.value.reason == reason


def test_estimate_datagram_round_trip():
    estimate = Estimate(
        time_s=3.5, delta_L_rad=0.4, std_rad=0.01, q_r_rad=2.0, flags=Flag.PARTIAL | Flag.HELD
    )
    data = encode_estimate(9, estimate, latency_s=0.002, status=0b101)
    assert len(data) == ESTIMATE_STRUCT.size == 64 and data[:4] == b"CTES"
    message = decode_estimate(data)
    assert message.sequence == 9 and message.time_s == 3.5
    assert message.delta_L_rad == 0.4 and message.std_rad == 0.01 and message.q_r_rad == 2.0
    assert message.delta_1_rad == pytest.approx(estimate.delta_1_rad)
    assert message.latency_s == 0.002
    assert Flag(message.estimator_flags) == Flag.PARTIAL | Flag.HELD
    assert message.status == 0b101 and message.valid

    invalid = Estimate(3.6, math.nan, math.nan, 2.0, Flag.NO_MEASUREMENT)
    message = decode_estimate(encode_estimate(10, invalid, 0.001))
    assert not message.valid and math.isnan(message.delta_1_rad)
    with pytest.raises(DatagramError):
        decode_estimate(data[:-1])


def test_marker_datagram_round_trip_with_missing_points():
    uv_f = np.array([[1.0, 2.0], [np.nan, np.nan], [5.0, 6.0]])
    uv_s = np.array([[7.0, 8.0], [9.0, 10.0], [11.0, 12.0]])
    data = encode_markers(4, 0.5, (uv_f, uv_s), ([0.5, 0.5, 2.0], 1.5))
    assert len(data) == marker_datagram_size(3) == 24 + 48 * 3
    assert struct.unpack_from("<I", data)[0] == MARKER_MAGIC
    markers = decode_markers(data, n_points=3)
    assert markers.sequence == 4 and markers.time_s == 0.5
    np.testing.assert_array_equal(markers.uv[0], uv_f)
    np.testing.assert_array_equal(markers.uv[1], uv_s)
    np.testing.assert_allclose(markers.cov[0][2], 4.0 * np.eye(2))
    np.testing.assert_allclose(markers.cov[1][0], 2.25 * np.eye(2))
    assert np.all(np.isnan(markers.cov[0][1]))
    again = decode_markers(encode_segmented(markers))
    np.testing.assert_allclose(again.cov[0][[0, 2]], markers.cov[0][[0, 2]])


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda d: d[:-8], "size"),
        (lambda d: d[:10], "size"),
        (lambda d: b"XXXX" + d[4:], "magic"),
        (lambda d: d[:12] + struct.pack("<H", 0) + d[14:], "points"),
        (lambda d: d[:40] + struct.pack("<d", -1.0) + d[48:], "sigma"),
        (lambda d: d[:24] + struct.pack("<d", math.inf) + d[32:], "non-finite"),
    ],
)
def test_marker_decoder_rejects_with_a_reason(mutate, reason):
    data = encode_markers(1, 0.0, (np.ones((3, 2)), np.ones((3, 2))), (1.0, 1.0))
    with pytest.raises(DatagramError) as info:
        decode_markers(mutate(data))
    assert info.value.reason == reason


def test_marker_datagram_with_three_views():
    uv = [np.full((3, 2), float(k)) for k in range(3)]
    data = encode_markers(7, 1.25, uv, (0.5, 1.0, 2.0))
    assert len(data) == marker_datagram_size(3, 3) == 24 + 72 * 3
    markers = decode_markers(data, n_points=3, n_views=3)
    assert len(markers.uv) == 3
    np.testing.assert_array_equal(markers.uv[2], uv[2])
    np.testing.assert_allclose(markers.cov[2][0], 4.0 * np.eye(2))
    with pytest.raises(DatagramError, match="the rig has 2"):
        decode_markers(data, n_views=2)


def test_marker_decoder_checks_the_point_count():
    data = encode_markers(1, 0.0, (np.ones((2, 2)), np.ones((2, 2))), (1.0, 1.0))
    with pytest.raises(DatagramError, match="catheter has 3"):
        decode_markers(data, n_points=3)


# --------------------------------------------------------------------------- receiving
def test_joint_receiver_orders_counts_and_interpolates(sender):
    with JointReceiver(port=0, clock="sender", stale_after_s=0.05) as receiver:
        address = receiver.address
        assert address[0] == LOOPBACK
        times = np.arange(0, 50) * 1e-3
        for k, t in enumerate(times):
            sender.sendto(encode_joints(k, t, *ramp_q(t)), address)
            if k == 20:
                sender.sendto(encode_joints(20, t, *ramp_q(t)), address)  # duplicate
                sender.sendto(encode_joints(15, times[15], *ramp_q(times[15])), address)  # stale
                sender.sendto(b"garbage", address)
                sender.sendto(encode_joints(k, t, *ramp_q(t))[:30], address)  # truncated
        assert receiver.poll() == 50
        counts = receiver.counts
        assert (counts.received, counts.accepted) == (54, 50)
        assert (counts.duplicate, counts.stale, counts.malformed) == (1, 1, {"size": 2})
        assert receiver.newest.sequence == 49

        for t in (0.0, 0.0123, 0.02, 0.0487, 0.049):
            sample = receiver.sample(t)
            assert sample.status is JointStatus.OK
            q, q_dot = ramp_q(t)
            np.testing.assert_allclose(sample.q, q, atol=1e-12)
            np.testing.assert_allclose(sample.q_dot, q_dot, atol=1e-12)
        held = receiver.sample(0.049 + 0.03)
        assert held.status is JointStatus.HELD and held.age_s == pytest.approx(0.03)
        np.testing.assert_allclose(held.q, ramp_q(0.049)[0])
        assert receiver.sample(0.049 + 0.2).status is JointStatus.STALE
        assert receiver.sample(-0.01).status is JointStatus.CLAMPED
        assert receiver.sample(-1.0).status is JointStatus.STALE
        assert receiver.poll() == 0  # nothing pending: returns at once


def test_a_burst_is_drained_in_order_and_kept_in_blocks(sender):
    """Many pending datagrams: every one is taken, the history keeps the newest in order, and
    reading between datagrams or only at the end keeps the same samples."""
    with JointReceiver(port=0, clock="sender", history=100) as receiver:
        times = np.arange(300) * 1e-3
        for k, t in enumerate(times):
            sender.sendto(encode_joints(k, t, *ramp_q(t)), receiver.address)
        assert receiver.poll() == 300 and receiver.counts.accepted == 300
        assert len(receiver) == 100 and receiver.newest.sequence == 299
        np.testing.assert_allclose(receiver.sample_times(), times[200:])
        np.testing.assert_allclose(receiver.sample(0.25).q, ramp_q(0.25)[0], atol=1e-12)
    at_once = JointReceiver(port=None, clock="aligned", history=64)
    each = JointReceiver(port=None, clock="aligned", history=64)
    for k in range(500):
        data = encode_joints(k, k * 1e-3, *ramp_q(k * 1e-3))
        at_once.add_datagram(data, 7.0 + k * 1e-3)
        each.add_datagram(data, 7.0 + k * 1e-3)
        assert len(each) == min(k + 1, 64)  # a read between datagrams
    kept, kept_too = at_once.snapshot(), each.snapshot()
    for name in ("time_s", "q", "q_dot"):
        np.testing.assert_array_equal(getattr(kept, name), getattr(kept_too, name))


def test_joint_receiver_without_samples():
    with JointReceiver(port=0) as receiver:
        sample = receiver.sample(1.0)
        assert sample.status is JointStatus.NONE and not sample.usable
        assert np.all(np.isnan(sample.q))


def test_joint_history_is_bounded_and_stays_ordered():
    receiver = JointReceiver(port=None, clock="sender", history=100)
    for k in range(5000):
        t = k * 1e-3
        receiver.add(JointPacket(k, t, *ramp_q(t)), arrival_s=t)
    assert len(receiver) == 100
    times = receiver.sample_times()
    np.testing.assert_allclose(times, np.arange(4900, 5000) * 1e-3)
    np.testing.assert_allclose(receiver.sample(4.95).q, ramp_q(4.95)[0], atol=1e-12)
    assert receiver.sample(4.0).status is JointStatus.STALE  # older than the history


def test_sequence_wraps_around_and_a_restart_clears_the_history():
    receiver = JointReceiver(port=None, clock="sender", restart_gap=100)
    top = 2**32
    for k, seq in enumerate([top - 2, top - 1, 0, 1]):
        assert receiver.add(JointPacket(seq, k * 1e-3, *ramp_q(k * 1e-3)), k * 1e-3) == 1
    assert receiver.add(JointPacket(top - 1, 0.01, *ramp_q(0.01)), 0.01) == 0  # behind: stale
    assert receiver.counts.stale == 1
    # The controller restarted: sequence and time start again.
    assert receiver.add(JointPacket(5, 0.0, *ramp_q(0.0)), 1.0) == 0  # within the gap: stale
    receiver.add(JointPacket(top - 500, 0.0, *ramp_q(0.0)), 1.0)
    assert receiver.counts.restarts == 1 and len(receiver) == 1


def test_time_that_does_not_increase_is_stale():
    receiver = JointReceiver(port=None, clock="sender")
    receiver.add(JointPacket(1, 1.0, *ramp_q(1.0)), 0.0)
    assert receiver.add(JointPacket(2, 1.0, *ramp_q(1.0)), 0.0) == 0
    assert receiver.counts.stale == 1


def test_rates_from_values_when_not_sent():
    receiver = JointReceiver(port=None, clock="sender")
    for k in range(100):
        t = k * 1e-3
        receiver.add_datagram(encode_joints(k, t, ramp_q(t)[0]), arrival_s=t)
    sample = receiver.sample(0.05)
    np.testing.assert_allclose(sample.q_dot, ramp_q(0.05)[1], atol=1e-9)


def test_aligned_clock_removes_the_offset_and_the_network_jitter():
    rng = np.random.default_rng(0)
    receiver = JointReceiver(port=None, clock="aligned")
    sender_times = np.arange(200) * 1e-3
    jitter = rng.exponential(2e-4, sender_times.size)
    jitter[17] = 0.0  # the fastest datagram fixes the offset
    for k, t in enumerate(sender_times):
        receiver.add(JointPacket(k, t, *ramp_q(t)), arrival_s=t + 100.0 + jitter[k])
    np.testing.assert_allclose(receiver.sample_times(), sender_times + 100.0, atol=1e-12)
    np.testing.assert_allclose(receiver.sample(100.1).q, ramp_q(0.1)[0], atol=1e-12)
    arrival = JointReceiver(port=None, clock="arrival")
    arrival.add(JointPacket(1, 0.5, *ramp_q(0.5)), arrival_s=42.0)
    assert arrival.sample_times()[0] == 42.0


CLOCKS = ("sender", "arrival", "aligned")


def check_samples_against_the_array_path(receivers: dict, rng, queries: int = 6) -> None:
    """Each clock's receiver samples at random times of every kind what the array path
    interpolates from the kept samples on that clock, bit for bit; the aligned clock's times
    are the sender's plus the smallest (arrival - sender) of the kept samples."""
    kept = receivers["sender"].snapshot()
    sender, arrival = kept.time_s, receivers["arrival"].sample_times()
    offset_s = float(np.min(arrival - sender)) if sender.size else 0.0
    times = {"sender": sender, "arrival": arrival, "aligned": sender + offset_s}
    for clock in CLOCKS:
        receiver = receivers[clock]
        history = JointHistory(times[clock], kept.q, kept.q_dot)
        candidates = query_times(times[clock], receiver.stale_after_s)
        for time_s in rng.choice(candidates, min(queries, candidates.size), replace=False):
            expected = sample_by_interpolation(history, time_s, receiver.stale_after_s)
            assert_same_sample(receiver.sample(time_s), expected)
    aligned = receivers["aligned"].sample_times()
    assert aligned.tobytes() == times["aligned"].tobytes()


@settings(max_examples=80, **PROPERTY_SETTINGS)
@given(
    history=st.sampled_from([2, 3, 8, 64]),
    events=st.lists(
        st.tuples(
            st.sampled_from(["rates", "rates", "rates", "no rates", "restart"]),
            st.sampled_from([1e-3, 1e-3, 2.5e-4, 0.05, 1e-9]),
            st.booleans(),  # sample after it
        ),
        max_size=60,
    ),
    sender_start_s=st.sampled_from([0.0, 1.0, 1.7e9]),
    arrival_start_s=st.sampled_from([100.0, 1e9]),
    seed=st.integers(0, 2**32 - 1),
)
def test_receiver_samples_bit_for_bit_what_the_array_path_interpolates(
    history, events, sender_start_s, arrival_start_s, seed
):
    """Random streams (jitter, datagrams without rates, restarts, times so close that the
    aligned clock rounds them together, histories that slide and wrap their rows), sampled
    between datagrams on every clock: exactly the previous JointHistory.sample semantics."""
    rng = np.random.default_rng(seed)
    receivers = {c: JointReceiver(port=None, clock=c, history=history) for c in CLOCKS}
    sequence, time_s = 0, sender_start_s
    for kind, step_s, check in events:
        if kind == "restart":  # far behind the newest: a restarted sender, history cleared
            sequence, time_s = (sequence - 5000) % 2**32, sender_start_s + rng.uniform(0, 1)
        else:
            sequence, time_s = sequence + 1, time_s + step_s
        jitter_s = rng.choice([0.0, rng.exponential(2e-4), rng.exponential(0.02)])
        q, q_dot = rng.uniform(-1.0, 1.0, 3), rng.uniform(-3.0, 3.0, 3)
        data = encode_joints(sequence, time_s, q, q_dot if kind == "rates" else None)
        for receiver in receivers.values():
            receiver.add_datagram(data, arrival_start_s + time_s + jitter_s)
        if check:
            check_samples_against_the_array_path(receivers, rng)
    check_samples_against_the_array_path(receivers, rng, queries=40)


def test_receiver_settings_are_checked():
    with pytest.raises(ValueError, match="clock"):
        JointReceiver(port=None, clock="wall")
    with pytest.raises(ValueError, match="history"):
        JointReceiver(port=None, history=1)


def test_port_in_use_is_one_clear_error():
    with JointReceiver(port=0) as first:
        port = first.address[1]
        with pytest.raises(OSError, match=f"127.0.0.1:{port}"):
            JointReceiver(port=port)


def test_estimate_sender_reaches_a_listener_and_never_raises():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as controller:
        controller.bind((LOOPBACK, 0))
        controller.settimeout(5.0)
        with EstimateSender(controller.getsockname()) as out:
            estimate = Estimate(1.0, 0.3, 0.02, 0.1)
            out.handle(None, None, estimate, 0.004, status=2)
            out.handle(None, None, estimate, 0.005)
            first = decode_estimate(controller.recv(128))
            second = decode_estimate(controller.recv(128))
        assert (first.sequence, second.sequence) == (0, 1)
        assert first.status == 2 and first.latency_s == 0.004 and first.delta_L_rad == 0.3
    reports = []
    with EstimateSender((LOOPBACK, 0), report=reports.append) as broken:  # port 0: EINVAL
        broken.send(estimate, 0.0)
        broken.send(estimate, 0.0)
        assert broken.errors == 2 and broken.sent == 0
    assert len(reports) == 1 and "127.0.0.1:0" in reports[0]


def test_marker_receiver_counts_bad_datagrams_and_joins_joints(sender):
    with MarkerReceiver(port=0, n_points=3) as markers, JointReceiver(
        port=0, clock="sender"
    ) as joints:
        for k in range(101):
            t = k * 1e-3
            sender.sendto(encode_joints(k, t, *ramp_q(t)), joints.address)
        uv = np.arange(6.0).reshape(3, 2)
        sender.sendto(encode_markers(0, 0.05, (uv, uv + 1), (0.5, 0.5)), markers.address)
        sender.sendto(b"not a marker datagram" * 8, markers.address)
        sender.sendto(encode_markers(1, 0.06, (uv[:2], uv[:2]), (0.5, 0.5)), markers.address)
        sender.sendto(encode_markers(2, 0.07, (uv, uv), (0.5, 0.5)), markers.address)
        frames = list(markers.frames(joints, idle_timeout_s=0.2))
        assert [f.time_s for f in frames] == [0.05, 0.07]
        np.testing.assert_allclose(frames[0].q, ramp_q(0.05)[0], atol=1e-12)
        np.testing.assert_array_equal(frames[0].uv[1], uv + 1)
        np.testing.assert_allclose(frames[0].cov[0], np.tile(0.25 * np.eye(2), (3, 1, 1)))
        assert markers.counts.malformed == {"magic": 1, "points": 1}
        assert markers.counts.accepted == 2


def test_segmented_markers_become_a_frame():
    uv = np.zeros((3, 2))
    cov = np.tile(np.eye(2), (3, 1, 1))
    frame = SegmentedMarkers(1.0, (uv, uv), (cov, cov)).frame([0.0, 0.1, 0.2], None)
    assert frame.time_s == 1.0 and frame.q_dot is None
    np.testing.assert_array_equal(frame.q, [0.0, 0.1, 0.2])
