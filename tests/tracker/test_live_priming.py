"""The live loop's work off the critical path: the region of interest predicted for the next
frame, the frame pace and the priming just before a frame is due (tracker/live/pacing.py)."""

from __future__ import annotations

import math
import os
import socket
import types

import cv2
import numpy as np
import pytest

from replay.simulation.sources import session_joints, simulated_session
from tracker.estimators import make_estimator
from tracker.io.datagrams import encode_joints
from tracker.io.udp import JointReceiver
from tracker.live.loop import PRIME_LEAD_S, PRIME_WAIT_S, ROI_POINTS, LiveTracker
from tracker.live.pacing import PRIME_FIRST_S, PRIME_SPREADS, FramePace
from tracker.live.sinks import MemorySink
from tracker.live.sources import ImageSet
from tracker.reconstruction import Reconstructor

LOOPBACK = "127.0.0.1"
JOINT_RATE_HZ = 1000


@pytest.fixture(scope="module")
def session():
    return simulated_session(duration_s=1.0, frame_rate_hz=20.0, noise=0.1, seed=3)


class StandInSegmenter:
    """Returns the points of the frame whose index the images carry; keeps every region."""

    def __init__(self, frames):
        self.frames = frames
        self.regions = []

    def segment(self, images, predicted_px=None):
        self.regions.append(
            None if predicted_px is None else tuple(np.copy(p) for p in predicted_px)
        )
        frame = self.frames[int(images[0][0, 0])]
        return types.SimpleNamespace(uv=frame.uv, cov=frame.cov)


def images_of(session, k):
    """An image pair standing for frame ``k`` (its index in every pixel)."""
    return ImageSet(session.frames[k].time_s, (np.full((2, 2), k), np.full((2, 2), k)))


class Joints:
    """A joint receiver fed by hand with the session's motion at 1 kHz, over loopback."""

    def __init__(self):
        self.receiver = JointReceiver(port=0, clock="sender")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.next = 0

    rates = True  # False: datagrams without rates (NO_RATES), the receiver derives them

    def send_until(self, time_s):
        while self.next / JOINT_RATE_HZ <= time_s + 1e-9:
            t = self.next / JOINT_RATE_HZ
            q, q_dot = session_joints(t)
            self.sock.sendto(
                encode_joints(self.next, t, q, q_dot if self.rates else None),
                self.receiver.address,
            )
            self.next += 1

    def close(self):
        self.sock.close()


@pytest.fixture
def joints():
    j = Joints()
    yield j
    j.close()


def loop_of(session, joints, segmenter, memory):
    scene = session.scene
    return LiveTracker(
        Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        make_estimator("ukf", scene.catheter),
        [memory],
        joints=joints.receiver,
        segmenter=segmenter,
        max_time_jump_s=1e9,
    )


def region_at(session, q, delta_L_rad):
    """The catheter's points at these joints and delta_L in every view, px (mm here)."""
    scene = session.scene
    arclengths = np.linspace(0.0, scene.catheter.length_mm, ROI_POINTS)
    points_b = scene.catheter.backbone(q, delta_L_rad, arclengths)
    points_w = points_b @ np.asarray(scene.R_w_b).T + np.asarray(scene.o_b_w_mm)
    return tuple(view.project(points_w) for view in scene.rig.views)


def step(tracker, session, joints, k, received_s):
    joints.send_until(session.frames[k].time_s + 0.002)
    return tracker.step(images_of(session, k), received_s)


# ----------------------------------------------------------------------------- pace
def test_the_pace_is_the_median_interval_and_a_dropped_frame_does_not_change_it():
    pace = FramePace(window=5)
    assert pace.period_s is None and pace.next_time_s is None and pace.due_s() == math.inf
    pace.add(1.00, 10.0)
    assert pace.period_s is None and pace.due_s() == math.inf
    for time_s, received_s in [(1.05, 10.05), (1.10, 10.10), (1.20, 10.21)]:  # 1.15 dropped
        pace.add(time_s, received_s)
    assert pace.period_s == pytest.approx(0.05)
    assert pace.next_time_s == pytest.approx(1.25)
    assert pace.due_s() == pytest.approx(10.26)
    assert pace.due_s(speed=2.0) == pytest.approx(10.235)  # a stream played twice as fast
    assert pace.due_s(speed=None) == math.inf  # no pace: never due
    pace.add(1.20, 10.3)  # not later: no interval
    assert pace.period_s == pytest.approx(0.05)
    pace.reset()
    assert pace.period_s is None and pace.due_s() == math.inf


# ------------------------------------------------------------------ region of interest
def test_the_region_of_the_next_frame_is_predicted_after_the_estimate_is_sent(session, joints):
    """Frame k+1 is segmented around the model at frame k's estimate and frame k's joints
    moved on by their rates over one period; before a period is known, or for a frame far
    from the time predicted for, the segmenter gets no region (it uses its own)."""
    segmenter, memory = StandInSegmenter(session.frames), MemorySink()
    tracker = loop_of(session, joints, segmenter, memory)
    for k in range(6):
        step(tracker, session, joints, k, received_s=float(k))
    assert segmenter.regions[:2] == [None, None]  # no estimate yet, then no period yet
    for k in range(2, 6):
        last = memory.results[k - 1]
        assert last.estimate.valid
        dt = session.frames[k].time_s - last.frame.time_s
        expected = region_at(
            session, last.frame.q + last.frame.q_dot * dt, last.estimate.delta_L_rad
        )
        for got, want in zip(segmenter.regions[k], expected, strict=True):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        # ... and that is close to the catheter at the frame's own joints.
        actual = region_at(session, memory.results[k].frame.q, last.estimate.delta_L_rad)
        for got, want in zip(segmenter.regions[k], actual, strict=True):
            assert np.max(np.abs(got - want)) < 0.05  # mm in this orthographic rig
    step(tracker, session, joints, 8, received_s=8.0)  # two frames dropped: 3 periods later
    assert segmenter.regions[-1] is None
    tracker.close()


# ---------------------------------------------------------------------------- priming
def test_priming_drains_the_joints_predicts_the_region_and_pauses_the_sinks(session, joints):
    """Once per frame, a lead before it is due: the joints received are drained, the region
    is predicted from the newest of them, and the queued sinks pause until the frame comes
    or is a lead late. The frame is then segmented around that region."""
    segmenter, memory = StandInSegmenter(session.frames), MemorySink()
    tracker = loop_of(session, joints, segmenter, memory)
    for k in range(3):
        step(tracker, session, joints, k, received_s=10.0 + 0.05 * k)
    due_s = 10.15
    assert tracker.pace.due_s() == pytest.approx(due_s)
    joints.send_until(session.frames[3].time_s - 0.001)  # the controller streams on
    received = tracker.joints.counts.received
    assert not tracker.prime(due_s - 2 * PRIME_LEAD_S - PRIME_FIRST_S)  # too early
    assert tracker.idle.is_set() and tracker.joints.counts.received == received

    assert tracker.prime(due_s - 0.5 * PRIME_LEAD_S)
    assert not tracker.idle.is_set()  # the sinks pause
    assert tracker.joints.counts.received > received  # drained
    last = memory.results[-1]
    newest = tracker.joints.sample(session.frames[3].time_s)
    q = newest.q + newest.q_dot * newest.age_s
    primed = region_at(session, q, last.estimate.delta_L_rad)
    assert not tracker.prime(due_s)  # once per frame
    assert not tracker.idle.is_set()
    assert not tracker.prime(due_s + 0.5 * PRIME_WAIT_S)  # a little late: still waited for
    assert not tracker.idle.is_set()
    assert not tracker.prime(due_s + 2 * PRIME_WAIT_S)  # the frame is late...
    assert tracker.idle.is_set()  # ...the sinks work meanwhile

    tracker.step(images_of(session, 3), due_s + 2 * PRIME_WAIT_S)
    for got, want in zip(segmenter.regions[3], primed, strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert tracker.idle.is_set()
    assert not tracker._primed  # the next frame will be primed again
    tracker.close()


def policy_of(thread_id: int) -> int:
    """A thread's scheduling policy (0: the calling one), without SCHED_RESET_ON_FORK."""
    return os.sched_getscheduler(thread_id) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)


class PolicyOf(MemorySink):
    """Records, as each frame is handed over, the scheduling policy of the loop's thread and
    of another thread."""

    def __init__(self, thread_id):
        super().__init__()
        self.thread_id, self.policies = thread_id, []

    def handle(self, *args, **kwargs):
        self.policies.append((policy_of(0), policy_of(self.thread_id)))
        super().handle(*args, **kwargs)


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux's policies")
def test_the_loop_and_its_capture_thread_wait_for_a_primed_frame_at_its_priority(
    session, joints
):
    """From the priming until the frame is taken, or one lead past its due time, the loop's
    thread and the capture thread are at SCHED_FIFO (a frame that comes then wakes them at
    once); the capture thread is put back as the frame's step starts, the loop's after it."""
    import threading

    from tracker.live.priority import FramePriority

    if not FramePriority().start():
        pytest.fail("this test needs SCHED_FIFO: run as root or with an rtprio limit")
    ordinary, fifo = os.SCHED_OTHER, os.SCHED_FIFO
    done = threading.Event()
    capture = threading.Thread(target=done.wait, daemon=True)
    capture.start()
    memory = PolicyOf(capture.native_id)
    tracker = loop_of(session, joints, StandInSegmenter(session.frames), memory)
    tracker._capture = types.SimpleNamespace(thread_id=capture.native_id, dropped=0)
    tracker._priority.start()  # as run() does with the loop pinned
    try:
        for k in range(3):
            step(tracker, session, joints, k, received_s=10.0 + 0.05 * k)
        assert {p for pair in memory.policies for p in pair} == {fifo, ordinary}
        assert [p[1] for p in memory.policies] == [ordinary] * 3
        assert policy_of(0) == policy_of(capture.native_id) == ordinary
        due_s = 10.15
        joints.send_until(session.frames[3].time_s - 0.001)
        assert tracker.prime(due_s - 0.5 * PRIME_LEAD_S)
        assert policy_of(0) == policy_of(capture.native_id) == fifo
        assert not tracker.prime(due_s)  # still waiting for it
        assert policy_of(capture.native_id) == fifo
        step(tracker, session, joints, 3, received_s=due_s)
        assert memory.policies[-1] == (fifo, ordinary)  # the step's own priority
        assert policy_of(0) == policy_of(capture.native_id) == ordinary
        # A frame that does not come: put back PRIME_WAIT_S past its due time.
        due_s = 10.20
        joints.send_until(session.frames[4].time_s - 0.001)
        assert tracker.prime(due_s - 0.5 * PRIME_LEAD_S)
        assert policy_of(capture.native_id) == fifo
        assert not tracker.prime(due_s + 2 * PRIME_WAIT_S)
        assert policy_of(0) == policy_of(capture.native_id) == ordinary
    finally:
        tracker._priority.release()
        done.set()
        capture.join()
        tracker.close()


def test_priming_prepares_the_estimator_s_model_at_the_frame_s_joints(session, joints):
    """The shape expansion's node of the frame's joints (six shape evaluations) is computed
    in the priming, from the joints moved on to the frame's time: the frame's own step
    computes none. The filter's state is unchanged by it."""
    segmenter, memory = StandInSegmenter(session.frames), MemorySink()
    tracker = loop_of(session, joints, segmenter, memory)
    for k in range(3):
        step(tracker, session, joints, k, received_s=10.0 + 0.05 * k)
    due_s = 10.15
    joints.send_until(session.frames[3].time_s - 0.001)
    ukf = tracker.estimator.inner
    nodes = ukf._expansion._nodes
    before, state, P = set(nodes), ukf._bank.x.copy(), ukf._bank.P.copy()
    assert tracker.prime(due_s - 0.5 * PRIME_LEAD_S)
    primed = set(nodes) - before
    assert len(primed) == 1
    np.testing.assert_array_equal(ukf._bank.x, state)
    np.testing.assert_array_equal(ukf._bank.P, P)
    step(tracker, session, joints, 3, received_s=due_s)
    assert set(nodes) - before == primed  # the step found its node ready
    assert memory.results[-1].estimate.valid
    tracker.close()


@pytest.mark.parametrize("rates", [True, False])
def test_joints_held_for_late_datagrams_are_moved_on_at_their_rates(session, joints, rates):
    """A frame whose newest joint datagram is older than the image (the controller late by
    a few ms) takes the newest values moved on at their rates to the image time: within
    the motion's second order of the truth, where the values held would be off by the rate
    times the delay; also from a controller that sends no rates (the receiver's, from the
    values). Past the hold (20 ms) the frame is flagged and predicts only."""
    from tracker.live.sinks import LiveStatus

    joints.rates = rates
    segmenter, memory = StandInSegmenter(session.frames), MemorySink()
    tracker = loop_of(session, joints, segmenter, memory)
    for k in range(3):
        step(tracker, session, joints, k, received_s=10.0 + 0.05 * k)
    for k, late_s in ((3, 0.008), (4, 0.015), (5, 0.030)):
        t = session.frames[k].time_s
        joints.send_until(t - late_s)
        result = tracker.step(images_of(session, k), 10.0 + 0.05 * k)
        newest_s = (joints.next - 1) / JOINT_RATE_HZ
        truth = session_joints(t)[0]
        held = session_joints(newest_s)[0]
        if late_s <= 0.02:
            assert not result.status
            error = np.abs(result.frame.q - truth).max()
            assert error < 0.01 * np.abs(held - truth).max()
        else:
            assert result.status & LiveStatus.JOINTS_EXTRAPOLATED
            np.testing.assert_allclose(result.frame.q, held, rtol=0, atol=1e-12)
    tracker.close()


def test_without_a_pace_or_with_priming_off_the_loop_never_primes(session, joints):
    segmenter, memory = StandInSegmenter(session.frames), MemorySink()
    tracker = loop_of(session, joints, segmenter, memory)
    step(tracker, session, joints, 0, received_s=1.0)
    assert not tracker.prime(1.049) and tracker.idle.is_set()  # one frame: no period
    step(tracker, session, joints, 1, received_s=1.05)
    tracker.prime_lead_s = None
    assert not tracker.prime(1.099) and tracker.idle.is_set()
    tracker.close()


class SettingsSink(MemorySink):
    """Records OpenCV's thread count and the processors of the loop's thread."""

    name = "settings"

    def __init__(self):
        super().__init__()
        self.cv_threads = []
        self.cpus = []

    def handle(self, *args, **kwargs):
        self.cv_threads.append(cv2.getNumThreads())
        if hasattr(os, "sched_getaffinity"):
            self.cpus.append(os.sched_getaffinity(0))
        super().handle(*args, **kwargs)


def test_a_run_takes_opencv_to_one_thread_and_leaves_the_sinks_free(session, joints):
    """During the run OpenCV uses one thread and the loop's thread a processor of its own
    (two or more allowed); afterwards both are back, and the sinks are not left paused by a
    priming for a frame that never came."""
    segmenter, sink = StandInSegmenter(session.frames), SettingsSink()
    tracker = loop_of(session, joints, segmenter, sink)
    before = cv2.getNumThreads()
    cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    joints.send_until(session.frames[4].time_s + 0.002)

    def source():
        for k in range(4):
            yield images_of(session, k)
        tracker.idle.clear()  # as a priming would leave it
        yield None

    tracker.run(source(), handle_signals=False)
    assert sink.cv_threads == [1] * 4
    assert cv2.getNumThreads() == before
    if cpus is not None:
        assert sink.cpus == [{max(cpus)} if len(cpus) > 1 else cpus] * 4
        assert os.sched_getaffinity(0) == cpus
    assert tracker.idle.is_set()


# ------------------------------------------------------------------------- rehearsal
class RehearsingSegmenter(StandInSegmenter):
    """A stand-in that also rehearses: records what it was given and takes ``took_s`` of
    the loop's clock (or raises ``fails``)."""

    def __init__(self, frames, clock, took_s=0.004, fails=None):
        super().__init__(frames)
        self.clock, self.took_s, self.fails = clock, took_s, fails
        self.rehearsed = []

    def rehearse(self, images, predicted_px=None):
        if self.fails is not None:
            raise self.fails
        self.rehearsed.append((int(images[0][0, 0]), predicted_px))
        self.clock.now += self.took_s


class Clock:
    now = 10.0

    def __call__(self):
        return self.now


def rehearsing_loop(session, joints, segmenter, clock, report=print, estimator=None):
    scene = session.scene
    return LiveTracker(
        Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        estimator or make_estimator("ukf", scene.catheter), [MemorySink()],
        joints=joints.receiver, segmenter=segmenter, max_time_jump_s=1e9, monotonic=clock,
        report=report,
    )  # fmt: skip


def step_at(tracker, session, joints, clock, k):
    """Frame ``k`` (its images) arriving at 10 s + k frame periods of the loop's clock."""
    clock.now = 10.0 + 0.05 * k
    return step(tracker, session, joints, k, received_s=clock.now)


def test_priming_rehearses_the_last_frame_earlier_by_what_it_takes(session, joints):
    """The last frame's images are segmented again while priming, around the next frame's
    region, and the next priming starts earlier by the rehearsal's running time."""
    clock = Clock()
    segmenter = RehearsingSegmenter(session.frames, clock)
    tracker = rehearsing_loop(session, joints, segmenter, clock)
    for k in range(3):
        step_at(tracker, session, joints, clock, k)
    joints.send_until(session.frames[3].time_s - 0.001)
    clock.now = 10.15 - 0.5 * PRIME_LEAD_S
    assert tracker.prime(clock.now)
    (index, region), = segmenter.rehearsed
    assert index == 2  # the last frame's images
    for got, want in zip(region, tracker._region_for(session.frames[3].time_s), strict=True):
        np.testing.assert_array_equal(got, want)  # where the next frame is expected
    clock.now = 10.15
    step(tracker, session, joints, 3, received_s=clock.now)
    # The next frame is due at 10.20: primed a lead plus the rehearsal's 4 ms before.
    assert not tracker.prime(10.20 - PRIME_LEAD_S - 0.005)
    assert tracker.prime(10.20 - PRIME_LEAD_S - 0.0035)
    assert [i for i, _ in segmenter.rehearsed] == [2, 3]
    tracker.close()


class StreamingSegmenter(RehearsingSegmenter):
    """A rehearsal during which the controller streams on (``joints`` sent up to ``until_s``)."""

    def __init__(self, frames, clock, joints, until_s):
        super().__init__(frames, clock)
        self.joints, self.until_s = joints, until_s

    def rehearse(self, images, predicted_px=None):
        super().rehearse(images, predicted_px)
        self.joints.send_until(self.until_s)


def test_the_joints_that_come_while_priming_are_drained_before_the_frame(session, joints):
    """Priming drains the joints at its start and again at its end: the datagrams that came
    during the rehearsal (four or five of them live) are not left for the frame to decode."""
    clock = Clock()
    frame_s = session.frames[3].time_s
    segmenter = StreamingSegmenter(session.frames, clock, joints, frame_s - 0.001)
    tracker = rehearsing_loop(session, joints, segmenter, clock)
    for k in range(3):
        step_at(tracker, session, joints, clock, k)
    joints.send_until(frame_s - 0.004)
    clock.now = 10.15 - 0.5 * PRIME_LEAD_S
    assert tracker.prime(clock.now)
    assert len(segmenter.rehearsed) == 1  # the rehearsal ran, the controller streaming on
    newest = tracker.joints.sample(frame_s)
    assert newest.age_s == pytest.approx(0.001, abs=1e-9)  # its datagrams taken in
    assert tracker.joints.poll() == 0  # none left for the frame
    tracker.close()


class SettlingSegmenter(StandInSegmenter):
    """Keeps what the loop asks of it, in order, in ``calls`` (shared with the sink)."""

    def __init__(self, frames, calls):
        super().__init__(frames)
        self.calls = calls

    def segment(self, images, predicted_px=None, settle=True):
        self.calls.append(f"segment, settle={settle}")
        return super().segment(images, predicted_px)

    def settle(self):
        self.calls.append("settle")


class CallSink(MemorySink):
    def __init__(self, calls):
        super().__init__()
        self.calls = calls

    def handle(self, frame, observation, estimate, latency_s, status):
        self.calls.append("estimate sent")
        super().handle(frame, observation, estimate, latency_s, status)


def test_the_background_update_waits_until_the_estimate_has_left(session, joints):
    """A segmenter with ``settle()`` segments with ``settle=False`` and is settled after the
    sinks (the estimate sender first) had the frame: off the critical path."""
    calls = []
    tracker = loop_of(session, joints, SettlingSegmenter(session.frames, calls), CallSink(calls))
    for k in range(3):
        step(tracker, session, joints, k, received_s=None)
    assert calls == ["segment, settle=False", "estimate sent", "settle"] * 3
    tracker.close()


class OverlappingSegmenter(SettlingSegmenter):
    """Takes ``meanwhile`` as :class:`ParallelPairSegmenter` does: its own view, then the
    caller's work, then the view segmented elsewhere (not called with ``calls_it`` False)."""

    def __init__(self, frames, calls, calls_it=True):
        super().__init__(frames, calls)
        self.calls_it = calls_it

    def segment(self, images, predicted_px=None, settle=True, meanwhile=None):
        self.calls.append(f"own view, settle={settle}")
        if meanwhile is not None and self.calls_it:
            meanwhile()
        self.calls.append("other view")
        return StandInSegmenter.segment(self, images, predicted_px)


@pytest.mark.parametrize("calls_it", [True, False])
def test_the_joints_are_read_while_the_segmenter_waits_for_its_other_view(
    session, joints, calls_it
):
    """With a segmenter that takes ``meanwhile``, the joints are read, and the estimator's
    model prepared at them, between its own view and the other one's answer; the frames get
    the same joint values and estimates as with one that reads them after. One that never
    calls it gets them read after, as before."""
    calls, reference_calls = [], []
    receiver = joints.receiver
    sample = receiver.sample
    receiver.sample = lambda time_s: calls.append("joints") or sample(time_s)
    tracker = loop_of(
        session, joints, OverlappingSegmenter(session.frames, calls, calls_it), CallSink(calls)
    )
    prepared = []
    prepare = tracker.estimator.prepare
    tracker.estimator.prepare = lambda q: calls.append("model") or prepared.append(q) or prepare(q)
    reference_joints = Joints()
    reference = loop_of(
        session, reference_joints, SettlingSegmenter(session.frames, reference_calls),
        CallSink(reference_calls),
    )  # fmt: skip
    for k in range(4):
        got = step(tracker, session, joints, k, received_s=None)
        want = step(reference, session, reference_joints, k, received_s=None)
        np.testing.assert_array_equal(got.frame.q, want.frame.q)
        np.testing.assert_array_equal(got.frame.q_dot, want.frame.q_dot)
        assert got.estimate.delta_L_rad == want.estimate.delta_L_rad
        assert got.estimate.std_rad == want.estimate.std_rad
        if calls_it:  # the model prepared at the frame's own joints
            np.testing.assert_array_equal(prepared[-1], got.frame.q)
    inner = ["joints", "model", "other view"] if calls_it else ["other view", "joints"]
    assert calls == ["own view, settle=False", *inner, "estimate sent", "settle"] * 4
    tracker.close()
    reference.close()
    reference_joints.close()


def test_joints_read_meanwhile_that_are_too_old_make_the_frame_predict_only(session, joints):
    """The joint stream stops after frame 1: frame 4, 0.1 s past its newest sample, reads
    them in the segmenter's wait as before, the estimator's model is not prepared at them,
    and the frame is predict-only and not valid, as when they are read after."""
    from tracker.live.sinks import PREDICT_ONLY

    calls = []
    receiver = joints.receiver
    sample = receiver.sample
    receiver.sample = lambda time_s: calls.append("joints") or sample(time_s)
    tracker = loop_of(
        session, joints, OverlappingSegmenter(session.frames, calls), CallSink(calls)
    )
    prepare = tracker.estimator.prepare
    tracker.estimator.prepare = lambda q: calls.append("model") or prepare(q)
    for k in range(2):
        assert step(tracker, session, joints, k, received_s=None).estimate.valid
    calls.clear()
    result = tracker.step(images_of(session, 4))  # no joint datagram since frame 1's
    assert calls == [
        "own view, settle=False", "joints", "other view", "estimate sent", "settle",
    ]  # fmt: skip
    assert result.status & PREDICT_ONLY
    assert not result.estimate.valid and np.isnan(result.estimate.delta_L_rad)
    assert tracker.summary.frames_stale_joints + tracker.summary.frames_extrapolated_joints == 1
    tracker.close()


def test_priming_starts_when_it_ends_a_lead_before_the_frame(session, joints):
    """The loop waits for a frame at most until priming must start: the priming's running
    time plus the lead before the frame is due, so that it never holds up the frame."""
    clock = Clock()
    segmenter = RehearsingSegmenter(session.frames, clock, took_s=0.004)
    tracker = rehearsing_loop(session, joints, segmenter, clock)
    assert tracker.wait_s(clock.now, 0.002) == 0.002  # no pace yet: the joints' poll
    for k in range(3):
        step_at(tracker, session, joints, clock, k)
    # Due at 10.15; the first priming's time is not known yet: taken as PRIME_FIRST_S.
    first_s = 10.15 - PRIME_LEAD_S - PRIME_FIRST_S
    assert tracker.wait_s(first_s - 0.004, 0.002) == 0.002
    assert tracker.wait_s(first_s - 0.0015, 0.002) == pytest.approx(0.0015)
    assert tracker.wait_s(first_s + 0.001, 0.002) == 0.0  # late for it: at once
    joints.send_until(session.frames[3].time_s - 0.001)
    assert not tracker.prime(first_s - 0.0001)
    clock.now = first_s + 1e-9
    assert tracker.prime(clock.now)
    assert tracker.wait_s(clock.now, 0.002) == 0.002  # primed: only the joints' poll
    clock.now = 10.15
    step(tracker, session, joints, 3, received_s=clock.now)
    # Due at 10.20, priming takes 4 ms: it starts 4 ms plus a lead before.
    start_s = 10.20 - PRIME_LEAD_S - 0.004
    assert tracker.wait_s(start_s - 0.001, 0.002) == pytest.approx(0.001)
    assert not tracker.prime(start_s - 0.0001)
    clock.now = start_s + 1e-9  # (rounding)
    assert tracker.prime(clock.now)
    assert clock.now == pytest.approx(10.20 - PRIME_LEAD_S)  # ended a lead before the frame
    tracker.close()


def test_a_priming_that_varies_starts_earlier_by_its_spread(session, joints):
    """Primings of 4 ms then 8 ms: the next starts the lead, their running mean (4.8 ms)
    and PRIME_SPREADS times their running deviation (0.8 ms) before the frame."""
    clock = Clock()
    segmenter = RehearsingSegmenter(session.frames, clock, took_s=0.004)
    tracker = rehearsing_loop(session, joints, segmenter, clock)
    for k in range(5):
        step_at(tracker, session, joints, clock, k)
        if k in (2, 3):
            joints.send_until(session.frames[k + 1].time_s - 0.001)
            clock.now = 10.0 + 0.05 * (k + 1) - 0.001  # just before the next frame
            assert tracker.prime(clock.now)
            segmenter.took_s = 0.008
    due_s = 10.25
    assert PRIME_SPREADS >= 1.0
    # Past the start the mean alone would give, less a deviation: priming is due already.
    assert tracker.wait_s(due_s - PRIME_LEAD_S - 0.0048 - 0.0008, 0.002) == 0.0
    start_s = due_s - PRIME_LEAD_S - 0.0048 - PRIME_SPREADS * 0.0008
    assert tracker.wait_s(start_s - 0.001, 0.002) == pytest.approx(0.001)
    assert not tracker.prime(start_s - 1e-6)
    clock.now = start_s + 1e-9
    assert tracker.prime(clock.now)
    tracker.close()


def test_a_rehearsal_that_fails_or_takes_too_long_is_left_out(session, joints):
    clock = Clock()
    segmenter = RehearsingSegmenter(session.frames, clock, fails=RuntimeError("boom"))
    lines = []
    tracker = rehearsing_loop(session, joints, segmenter, clock, lines.append)
    for k in range(3):
        step_at(tracker, session, joints, clock, k)
    joints.send_until(session.frames[3].time_s)
    assert tracker.prime(10.15 - 0.5 * PRIME_LEAD_S)  # primed all the same...
    assert not tracker.rehearse  # ...and no more rehearsals, said once
    assert [line for line in lines if "rehearsal" in line] == [
        "the segmentation's rehearsal failed and is off (boom)"
    ]
    clock.now = 10.15
    assert step(tracker, session, joints, 3, received_s=clock.now).estimate.valid
    tracker.close()


class StoppableSegmenter(RehearsingSegmenter):
    """A rehearsing stand-in that asks whether the frame has come half way through."""

    during = None  # called as the rehearsal starts (the controller streaming on)

    def rehearse(self, images, predicted_px=None, abandon=None):
        self.clock.now += 0.5 * self.took_s
        if self.during is not None:
            self.during()
        if abandon is not None and abandon():
            self.rehearsed.append((int(images[0][0, 0]), "stopped"))
            return False
        super().rehearse(images, predicted_px)
        self.clock.now -= 0.5 * self.took_s
        return True


class Capture:
    """What the loop asks of its capture thread: whether a frame waits in its slot."""

    waiting = False
    thread_id = None
    dropped = 0


def test_a_frame_that_comes_during_the_rehearsal_stops_it_and_goes_first(session, joints):
    """With a capture thread, the rehearsal is asked between its stages whether the frame
    has come, and stops when it has; a stopped priming is taken to have needed a lead more
    than it had (its own time cut short would start the next one later and later, and none
    at all would leave the timing as it was, stopped again and again), so that the next
    starts earlier."""
    clock = Clock()
    segmenter = StoppableSegmenter(session.frames, clock, took_s=0.004)
    tracker = rehearsing_loop(session, joints, segmenter, clock)
    tracker._capture = capture = Capture()
    for k in range(3):
        step_at(tracker, session, joints, clock, k)
    joints.send_until(session.frames[3].time_s - 0.001)
    capture.waiting = True  # the frame came while the loop primed itself
    segmenter.during = lambda: joints.send_until(session.frames[3].time_s)
    clock.now = 10.15 - 0.5 * PRIME_LEAD_S
    assert tracker.prime(clock.now)
    assert segmenter.rehearsed == [(2, "stopped")]
    assert tracker.joints.poll() == 1  # not drained once the frame waits: it goes first
    segmenter.during = None
    assert tracker.priming.mean_s == pytest.approx(0.002 + PRIME_LEAD_S)  # a lead more
    assert tracker._rehearsal_s == 0.0  # the rehearsal's own time: not taken
    clock.now = 10.15
    assert step(tracker, session, joints, 3, received_s=clock.now).estimate.valid
    # Stopped again: the priming's time goes up, and the next starts earlier.
    joints.send_until(session.frames[4].time_s - 0.001)
    first_start = tracker.priming.start_s(10.20, PRIME_LEAD_S)
    clock.now = first_start + 1e-9
    assert tracker.prime(clock.now)
    assert segmenter.rehearsed[-1] == (3, "stopped")
    clock.now = 10.20
    assert step(tracker, session, joints, 4, received_s=clock.now).estimate.valid
    assert tracker.priming.start_s(10.25, PRIME_LEAD_S) - 0.05 < first_start
    capture.waiting = False  # the next one comes after its priming, which runs whole
    joints.send_until(session.frames[5].time_s - 0.001)
    clock.now = tracker.priming.start_s(10.25, PRIME_LEAD_S) + 1e-9
    assert tracker.prime(clock.now)
    assert segmenter.rehearsed[-1][0] == 4
    assert tracker._rehearsal_s == pytest.approx(0.004)
    tracker.close()


def test_a_rehearsal_longer_than_a_fifth_of_the_period_is_skipped(session, joints):
    """On a machine too busy to spare it: tried again later, at most now and then."""
    clock = Clock()
    segmenter = RehearsingSegmenter(session.frames, clock, took_s=0.02)
    tracker = rehearsing_loop(session, joints, segmenter, clock)
    for k in range(8):
        step_at(tracker, session, joints, clock, k)
        joints.send_until(session.frames[k].time_s + 0.05)
        tracker.prime(clock.now + 0.05 - 0.5 * PRIME_LEAD_S)
    assert 1 <= len(segmenter.rehearsed) <= 2 and tracker.rehearse
    tracker.close()


def test_a_rehearsal_or_a_deferred_background_update_changes_nothing_in_the_segmenter():
    """Pairs segmented with a rehearsal of each before the next give the same points as
    without (the background model, its shift samples and the regions are untouched); so do
    pairs whose background update waits for ``settle()`` (the live loop's, once the estimate
    has left) or for the next frame, and the background models end the same."""
    from models.catheter import default_catheter
    from replay.simulation.render import ImagingNuisance, Renderer, default_render_rig
    from replay.simulation.simulator import default_scene
    from tracker.vision.pair import PairSegmenter

    catheter = default_catheter()
    scene = default_scene(catheter, default_render_rig())
    renderer = Renderer(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, seed=2,
                        nuisance=ImagingNuisance(gain_flicker=0.1, vibration_px=0.3))
    rng = np.random.default_rng(2)
    qs = np.column_stack([np.linspace(0, 1, 12), np.linspace(0.8, -0.6, 12), np.full(12, 0.7)])
    pairs = [renderer.render(q, 0.4, rng).images for q in qs]
    results, backgrounds = [], []
    stopped = []

    def stop_after(n):
        """Says the frame has come from its (n + 1)-th question on."""
        asked = iter(range(1000))
        return lambda: next(asked) >= n

    modes = ("plain", "rehearsed", "stopped part way", "settled after", "settled by the next frame")
    for mode in modes:
        segmenter = PairSegmenter(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm,
                                  renderer.backgrounds)
        out = []
        for k, images in enumerate(pairs):
            if mode == "stopped part way" and k:
                # Stopped at each of its stages in turn, then not at all.
                stopped.append(not segmenter.rehearse(pairs[k - 1], None, stop_after(k - 1)))
            elif mode != "plain" and k:
                segmenter.rehearse(pairs[k - 1])
                segmenter.rehearse(pairs[k - 1], (None, np.zeros((2, 2))))
            seg = segmenter.segment(images, settle=mode in ("plain", "rehearsed"))
            if mode == "settled after":
                segmenter.settle()
            out.append(np.concatenate([np.ravel(a) for a in (*seg.uv, *seg.cov)]))
        results.append(np.array(out))
        backgrounds.append(np.stack(segmenter.backgrounds))
    assert np.isfinite(results[0]).mean() > 0.9
    assert not np.array_equal(backgrounds[0], np.stack(renderer.backgrounds))  # updated
    assert any(stopped) and not all(stopped)
    for other, background in zip(results[1:], backgrounds[1:], strict=True):
        np.testing.assert_array_equal(results[0], other)
        np.testing.assert_array_equal(backgrounds[0], background)


class ClockedSegmenter(StandInSegmenter):
    """Takes ``took_s`` of the loop's clock per pair."""

    def __init__(self, frames, clock, took_s):
        super().__init__(frames)
        self.clock, self.took_s = clock, took_s

    def segment(self, images, predicted_px=None):
        self.clock.now += self.took_s
        return super().segment(images, predicted_px)


class ClockedEstimator:
    """An estimator that takes ``took_s`` of the loop's clock per step."""

    def __init__(self, inner, clock, took_s):
        self.inner, self.clock, self.took_s = inner, clock, took_s

    def step(self, observation):
        self.clock.now += self.took_s
        return self.inner.step(observation)


def test_the_summary_says_where_the_time_of_a_frame_goes(session, joints):
    """Segmentation, joints and reconstruction, estimator: each stage's time per frame, in
    the summary and its lines, and they add up to the latency (the frame waited 0 here)."""
    clock = Clock()
    estimator = ClockedEstimator(make_estimator("ukf", session.scene.catheter), clock, 0.0005)
    segmenter = ClockedSegmenter(session.frames, clock, 0.002)
    tracker = rehearsing_loop(session, joints, segmenter, clock, estimator=estimator)
    for k in range(4):
        step_at(tracker, session, joints, clock, k)
    tracker.close()
    summary = tracker.summary
    assert list(summary.stage_ms) == ["segmentation", "joints and reconstruction", "estimator"]
    for name, want_ms in [("segmentation", 2.0), ("joints and reconstruction", 0.0),
                          ("estimator", 0.5)]:  # fmt: skip
        assert summary.stage_ms[name]["p50"] == pytest.approx(want_ms, abs=1e-6), name
        assert summary.stage_ms[name]["p99"] == pytest.approx(want_ms, abs=1e-6), name
    assert summary.latency_ms["p50"] == pytest.approx(2.5, abs=1e-6)
    line = next(line for line in summary.lines() if "time per stage" in line)
    assert "segmentation 2.00 / 2.00 ms" in line and "estimator 0.50 / 0.50 ms" in line



class SendingSink(MemorySink):
    """A first sink (the estimate sender's place) that takes ``took_s`` of the loop's clock."""

    def __init__(self, clock, took_s):
        super().__init__()
        self.clock, self.took_s = clock, took_s

    def handle(self, frame, observation, estimate, latency_s, status):
        super().handle(frame, observation, estimate, latency_s, status)
        self.clock.now += self.took_s


def test_the_latency_is_until_the_first_sink_has_sent(session, joints):
    """The first sink (the estimate sender) gets the latency up to it (what its datagram
    carries); the summary's latency, the result's and the later sinks' are until it has
    sent: here 2 ms of segmentation, 0.5 of estimator and 0.3 of sending."""
    clock = Clock()
    estimator = ClockedEstimator(make_estimator("ukf", session.scene.catheter), clock, 0.0005)
    tracker = rehearsing_loop(session, joints, ClockedSegmenter(session.frames, clock, 0.002),
                              clock, estimator=estimator)  # fmt: skip
    first, later = SendingSink(clock, 0.0003), MemorySink()
    tracker._sinks.clear()
    tracker.add_sink(first)
    tracker.add_sink(later)
    results = [step_at(tracker, session, joints, clock, k) for k in range(4)]
    tracker.close()
    assert [r.latency_s for r in first.results] == pytest.approx([0.0025] * 4, abs=1e-9)
    for got in ([r.latency_s for r in later.results], [r.latency_s for r in results],
                list(tracker.latency.values())):  # fmt: skip
        assert got == pytest.approx([0.0028] * 4, abs=1e-9)
    assert tracker.summary.latency_ms["p99"] == pytest.approx(2.8, abs=1e-6)

def test_a_loop_fed_markers_times_no_segmentation(session, joints):
    clock = Clock()
    tracker = rehearsing_loop(session, joints, None, clock)
    joints.send_until(session.frames[1].time_s + 0.002)
    for k in range(2):
        clock.now = 10.0 + 0.05 * k
        tracker.step(session.frames[k], received_s=clock.now)
    tracker.close()
    assert list(tracker.summary.stage_ms) == ["joints and reconstruction", "estimator"]


def test_a_background_update_that_fails_is_said_once_and_the_loop_goes_on(session, joints):
    class FailingSettle(StandInSegmenter):
        def segment(self, images, predicted_px=None, settle=True):
            return super().segment(images, predicted_px)

        def settle(self):
            raise RuntimeError("boom")

    lines = []
    memory = MemorySink()
    tracker = loop_of(session, joints, FailingSettle(session.frames), memory)
    tracker.report = lines.append
    results = [step(tracker, session, joints, k, received_s=None) for k in range(3)]
    assert all(r is not None and r.estimate.valid for r in results[1:])
    assert lines == ["a background update failed (boom)"]
    tracker.close()


def recording(calls: list, owner, name: str):
    """``owner.name`` that also appends (owner's type, name, argument) to ``calls``."""
    original = getattr(owner, name)

    def spy(item):
        calls.append((type(owner).__name__, name, item))
        return original(item)

    return spy


def primed_run(session, joints, rehearse: bool, calls: list | None = None, report=print,
               tune=None):  # fmt: skip
    """The session's frames through a loop primed before each, as live; its estimates.
    ``tune(tracker)`` is called once the loop is made."""
    memory = MemorySink()
    scene = session.scene
    tracker = LiveTracker(
        Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        make_estimator("ukf", scene.catheter), [memory], joints=joints.receiver,
        segmenter=StandInSegmenter(session.frames), max_time_jump_s=1e9, rehearse=rehearse,
        report=report,
    )  # fmt: skip
    if tune is not None:
        tune(tracker)
    if calls is not None:  # what the priming runs, in order
        for owner, name in ((tracker.reconstructor, "rehearse"), (tracker.estimator, "rehearse"),
                            (tracker.estimator.inner, "prepare")):  # fmt: skip
            setattr(owner, name, recording(calls, owner, name))
    for k in range(len(session.frames)):
        received_s = 10.0 + 0.05 * k
        joints.send_until(session.frames[k].time_s - 0.001)
        if k >= 2:  # once the pace is known
            assert tracker.prime(received_s - 0.5 * PRIME_LEAD_S)
        step(tracker, session, joints, k, received_s)
    tracker.close()
    return memory.results


def test_priming_rehearses_the_last_frame_s_reconstruction_and_estimator_step(session):
    """Priming runs the last frame's reconstruction and estimator step again at the next
    frame's time, before the model is prepared at that frame's joints; the estimates are
    to the bit those of a loop that does not rehearse."""
    calls = []
    with_joints, without_joints = Joints(), Joints()
    try:
        rehearsed = primed_run(session, with_joints, True, calls)
        plain = primed_run(session, without_joints, False)
    finally:
        with_joints.close()
        without_joints.close()
    k = 3  # the priming for frame 3, after frame 2
    time_s = session.frames[k].time_s
    primed = [c for c in calls if c[1] == "rehearse" and abs(c[2].time_s - time_s) < 1e-9]
    (_, _, frame), (_, _, observation) = primed
    assert [c[0] for c in primed] == ["Reconstructor", "CheckedEstimator"]
    for got, want in zip(frame.uv, rehearsed[k - 1].frame.uv, strict=True):
        np.testing.assert_array_equal(got, want)  # the last frame's points...
    np.testing.assert_array_equal(observation.tip_b_mm, rehearsed[k - 1].observation.tip_b_mm)
    at = calls.index(primed[-1])
    assert calls[at + 1][1] == "prepare"  # ...then the model at the frame's joints
    assert sum(c[1] == "rehearse" for c in calls) == 2 * (len(session.frames) - 2)
    assert len(rehearsed) == len(plain) == len(session.frames)
    for a, b in zip(rehearsed, plain, strict=True):
        assert (a.estimate.delta_L_rad, a.estimate.std_rad, a.estimate.flags) == (
            b.estimate.delta_L_rad, b.estimate.std_rad, b.estimate.flags
        )


def test_a_rehearsal_of_the_steps_that_fails_is_said_once_and_left_out(session):
    """An estimator whose rehearsal raises (what a rehearsal must never do): the loop says
    so once, rehearses no more, and every frame's estimate is still that of a loop that
    never rehearsed."""
    said, calls, loops = [], [], []

    def broken(observation):
        calls.append(observation.time_s)
        raise RuntimeError("broken rehearsal")

    def tune(tracker):
        tracker.estimator.rehearse = broken
        loops.append(tracker)

    with_joints, without_joints = Joints(), Joints()
    try:
        results = primed_run(session, with_joints, True, report=said.append, tune=tune)
        plain = primed_run(session, without_joints, False)
    finally:
        with_joints.close()
        without_joints.close()
    assert len(calls) == 1 and not loops[0].rehearse_steps
    assert [m for m in said if "rehearsal" in m] == [
        "the estimator's rehearsal failed and is off (broken rehearsal)"
    ]
    assert len(results) == len(plain) == len(session.frames)
    for a, b in zip(results, plain, strict=True):
        assert (a.estimate.delta_L_rad, a.estimate.std_rad) == (
            b.estimate.delta_L_rad, b.estimate.std_rad
        )


def test_a_nominal_period_gives_the_second_frame_a_due_time_until_intervals_are_seen():
    """A source's own period (``period_s``) stands for the pace before two frames have
    been seen, so that the loop can prime for the second; from the first interval on, the
    frames' own intervals rule, and an unusable nominal period is ignored."""
    pace = FramePace(window=5, nominal_period_s=0.04)
    assert pace.period_s == pytest.approx(0.04) and pace.due_s() == math.inf  # no frame yet
    pace.add(1.00, 10.0)
    assert pace.next_time_s == pytest.approx(1.04) and pace.due_s() == pytest.approx(10.04)
    pace.add(1.05, 10.05)  # the stream's own period
    assert pace.period_s == pytest.approx(0.05) and pace.due_s() == pytest.approx(10.10)
    for nominal in (0.0, -0.05, math.nan, math.inf):
        assert FramePace(nominal_period_s=nominal).period_s is None


def test_the_loop_primes_for_the_second_frame_of_a_source_with_a_period(session, joints):
    """With the source's ``period_s`` the loop primes before the second frame (the joints
    sampled and the region predicted then); without it, not before the third."""
    primed_before = {}
    for period_s in (None, 0.05):
        tracker = loop_of(session, joints, StandInSegmenter(session.frames), MemorySink())
        tracker.pace.nominal_period_s = period_s
        primed = []
        for k in range(3):
            now = 100.0 + 0.05 * k  # the frames leave the source at 20 fps on this clock
            if k:
                primed.append(tracker.prime(now - 0.0005))  # just before the frame is due
            step(tracker, session, joints, k, received_s=now)
        primed_before[period_s] = primed
    assert primed_before[0.05] == [True, True]
    assert primed_before[None] == [False, True]


@pytest.mark.parametrize("live", [False, True])
def test_a_run_takes_the_source_s_period_for_its_pace(session, joints, live):
    """``run`` gives the pace the source's ``period_s`` (a live source's through its capture
    thread), and None for a source without one."""

    class Periodic:
        period_s = 0.04

        def __init__(self):
            self.live = live

        def __iter__(self):
            return iter(())

    tracker = loop_of(session, joints, StandInSegmenter(session.frames), MemorySink())
    tracker.run(Periodic(), handle_signals=False)
    assert tracker.pace.nominal_period_s == 0.04
    tracker = loop_of(session, joints, StandInSegmenter(session.frames), MemorySink())
    tracker.pace.nominal_period_s = 0.04
    tracker.run(iter(()), handle_signals=False)
    assert tracker.pace.nominal_period_s is None
