"""A frame's work at a real-time priority (tracker/live/priority.py): the thread raised to
SCHED_FIFO inside, as it was outside, nothing inherited by threads started meanwhile, and a
refusal said once; the live loop's step and the segmentation worker's frames use it."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from replay.simulation.sources import simulated_session
from tracker.estimators import make_estimator
from tracker.live.loop import LiveTracker
from tracker.live.priority import PRIORITY, FramePriority
from tracker.live.sinks import MemorySink
from tracker.reconstruction import Reconstructor

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setscheduler"), reason="scheduling policies are Linux's"
)
RESET = getattr(os, "SCHED_RESET_ON_FORK", 0)


def policy(tid: int = 0) -> int:
    return os.sched_getscheduler(tid) & ~RESET


def permitted() -> bool:
    """Whether this process may use SCHED_FIFO (root, CAP_SYS_NICE or an rtprio limit)."""
    return FramePriority().start()


def refuse(monkeypatch):
    def refused(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refused)


def test_inside_the_thread_is_real_time_and_threads_started_there_are_not():
    """Where this process may use SCHED_FIFO (as root, or with CAP_SYS_NICE or an rtprio
    limit; CI runs as root); elsewhere the refusal is what the next test checks."""
    if not permitted():
        priority = FramePriority()
        with priority:
            assert policy() == os.SCHED_OTHER
        assert priority.refused
        return
    before = policy(), os.sched_getparam(0).sched_priority
    started = {}

    def child():
        started["policy"] = policy()

    with FramePriority() as priority:
        assert priority.enabled and priority.refused is None
        assert policy() == os.SCHED_FIFO
        assert os.sched_getparam(0).sched_priority == PRIORITY
        thread = threading.Thread(target=child)
        thread.start()
        thread.join()
    assert started["policy"] == os.SCHED_OTHER  # not inherited
    assert (policy(), os.sched_getparam(0).sched_priority) == before


def test_a_thread_with_a_real_time_policy_of_its_own_keeps_it():
    """A tracker started with ``chrt -f 20``: its frames are not lowered to priority 1."""
    if not permitted():
        pytest.fail("this test needs SCHED_FIFO: run as root or with an rtprio limit")
    own = {}

    def thread():
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(20))
        with FramePriority():
            own["inside"] = policy(), os.sched_getparam(0).sched_priority
        own["after"] = policy(), os.sched_getparam(0).sched_priority

    worker = threading.Thread(target=thread)
    worker.start()
    worker.join()
    assert own["inside"] == own["after"] == (os.SCHED_RR, 20)


def test_off_or_refused_it_changes_nothing_and_a_refusal_is_said_once(monkeypatch):
    with FramePriority(enabled=False):
        assert policy() == os.SCHED_OTHER
    said = []
    priority = FramePriority(report=said.append)
    refuse(monkeypatch)
    assert not priority.start()
    for _ in range(3):
        with priority:
            assert policy() == os.SCHED_OTHER
    assert len(said) == 1 and "ordinary priority" in said[0]
    assert "not permitted" in priority.refused
    assert not priority.enabled


class Waiting:
    """A thread that waits (blocked) until told to end, and its native id."""

    def __init__(self):
        self.done = threading.Event()
        self.thread = threading.Thread(target=self.done.wait)
        self.thread.start()

    @property
    def id(self) -> int:
        return self.thread.native_id

    def end(self):
        self.done.set()
        self.thread.join()
        # join returns before the system's thread has quite gone (its id still takes a
        # priority for a moment): wait until it has.
        deadline = time.monotonic() + 5.0
        while os.path.exists(f"/proc/self/task/{self.id}") and time.monotonic() < deadline:
            time.sleep(0.001)


def test_held_threads_are_real_time_until_released_and_others_are_left_alone():
    """``hold`` raises the calling thread (0) and other threads by their native ids; a
    thread with a real-time policy of its own, an ended one and None are left as they are;
    ``release`` puts back exactly those it raised."""
    if not permitted():
        pytest.fail("this test needs SCHED_FIFO: run as root or with an rtprio limit")
    waiting, own, ended = Waiting(), Waiting(), Waiting()
    ended_id = ended.id
    ended.end()
    os.sched_setscheduler(own.id, os.SCHED_RR, os.sched_param(20))
    priority = FramePriority()
    assert priority.start()
    try:
        priority.hold([0, waiting.id, own.id, ended_id, None])
        assert set(priority.held) == {0, waiting.id}
        assert policy() == policy(waiting.id) == os.SCHED_FIFO
        assert os.sched_getparam(waiting.id).sched_priority == PRIORITY
        priority.hold([0, waiting.id])  # held already: nothing changes
        assert set(priority.held) == {0, waiting.id}
        priority.release()
        assert priority.held == ()
        assert policy() == policy(waiting.id) == os.SCHED_OTHER
        assert (policy(own.id), os.sched_getparam(own.id).sched_priority) == (os.SCHED_RR, 20)
        priority.release()  # nothing held: nothing to do
        assert policy() == os.SCHED_OTHER
    finally:
        priority.release()
        waiting.end()
        own.end()



def test_a_frame_s_step_carries_on_its_thread_s_hold_without_a_gap(monkeypatch):
    """The loop's step entered while its thread is held (its wait for the frame) takes the
    hold over: the thread is never put back to the ordinary policy in between (an ordinary
    thread that is ready takes the processor in that moment, for milliseconds), the other
    held threads are put back by ``release``, and the thread is put back when the step
    ends."""
    if not permitted():
        pytest.fail("this test needs SCHED_FIFO: run as root or with an rtprio limit")
    waiting = Waiting()
    calls = []
    set_policy = os.sched_setscheduler

    def recorded(thread_id, policy_, param):
        calls.append((thread_id, policy_ & ~getattr(os, "SCHED_RESET_ON_FORK", 0)))
        return set_policy(thread_id, policy_, param)

    priority = FramePriority()
    try:
        assert priority.start()
        monkeypatch.setattr(os, "sched_setscheduler", recorded)
        priority.hold([0, waiting.id])
        assert calls == [(0, os.SCHED_FIFO), (waiting.id, os.SCHED_FIFO)]
        with priority:
            priority.release()  # the others: the wait is over
            assert policy() == os.SCHED_FIFO and policy(waiting.id) == os.SCHED_OTHER
            assert priority.held == ()
        assert calls[2:] == [(waiting.id, os.SCHED_OTHER), (0, os.SCHED_OTHER)]
        assert policy() == os.SCHED_OTHER
        with priority:  # not held: raised on entry, put back on exit
            assert policy() == os.SCHED_FIFO
        assert calls[4:] == [(0, os.SCHED_FIFO), (0, os.SCHED_OTHER)]
    finally:
        monkeypatch.undo()
        priority.release()
        set_policy(0, os.SCHED_OTHER, os.sched_param(0))
        waiting.end()

def test_off_or_refused_a_hold_raises_nothing(monkeypatch):
    waiting = Waiting()
    try:
        off = FramePriority(enabled=False)
        off.hold([0, waiting.id])
        assert off.held == () and policy() == policy(waiting.id) == os.SCHED_OTHER
        said = []
        priority = FramePriority(report=said.append)
        refuse(monkeypatch)
        priority.hold([0, waiting.id])
        assert priority.held == () and not priority.enabled and len(said) == 1
        assert policy(waiting.id) == os.SCHED_OTHER
    finally:
        waiting.end()


class PolicySink(MemorySink):
    """Also records the scheduling policy of the thread that hands it each frame (the
    loop's)."""

    name = "policy"

    def __init__(self):
        super().__init__()
        self.policies = []

    def handle(self, *args, **kwargs):
        self.policies.append(policy())
        super().handle(*args, **kwargs)


def run_loop(realtime: bool, report=None, pin: bool = True):
    session = simulated_session(duration_s=0.5, frame_rate_hz=20.0, noise=0.1, seed=3)
    scene = session.scene
    sink = PolicySink()
    tracker = LiveTracker(
        Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        make_estimator("ukf", scene.catheter), [sink], realtime=realtime, pin=pin,
        report=report or (lambda line: None),
    )  # fmt: skip
    summary = tracker.run(session.frames, handle_signals=False)
    assert sink.closed and len(sink.results) == len(sink.policies)
    return summary, sink.policies


def test_the_loop_steps_each_frame_at_real_time_priority_and_then_lets_go(monkeypatch):
    """With a processor of its own (pinned), where permitted; not otherwise."""
    if len(os.sched_getaffinity(0)) < 2:
        pytest.fail("this test needs two processors, for the loop to have one of its own")
    allowed = permitted()
    summary, policies = run_loop(realtime=True)
    assert len(policies) == summary.frames_processed == 10
    assert summary.realtime is allowed
    assert set(policies) == {os.SCHED_FIFO if allowed else os.SCHED_OTHER}
    assert policy() == os.SCHED_OTHER  # the run is over
    for realtime, pin in ((False, True), (True, False)):
        summary, policies = run_loop(realtime=realtime, pin=pin)
        assert summary.realtime is None and set(policies) == {os.SCHED_OTHER}
    said = []
    refuse(monkeypatch)
    summary, policies = run_loop(realtime=True, report=said.append)
    assert summary.realtime is False and set(policies) == {os.SCHED_OTHER}
    assert sum("ordinary priority" in line for line in said) == 1
    assert any("frames at a real-time priority: no" in line for line in summary.lines())


def _worker_policies(realtime: bool, frames: int = 40) -> set[int]:
    """The segmentation worker's scheduling policies seen while it segments ``frames``
    pairs (its main thread's, read from /proc as often as the sampler can)."""
    from tests.tracker.segmentation_common import flickering_scene
    from tracker.vision.parallel import ParallelPairSegmenter

    catheter, scene, renderer = flickering_scene(3, 0.3)
    rng = np.random.default_rng(3)
    pairs = [renderer.render(np.array([0.2 * k, 0.6, 0.5]), 0.4, rng).images for k in range(4)]
    seen: set[int] = set()
    with ParallelPairSegmenter(
        catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds,
        realtime=realtime,
    ) as segmenter:  # fmt: skip
        assert segmenter.parallel
        stat = f"/proc/{segmenter._process.pid}/stat"
        done = threading.Event()

        def sample():
            while not done.is_set():
                with open(stat) as f:
                    seen.add(int(f.read().rsplit(")", 1)[1].split()[38]))  # policy
                time.sleep(0)

        sampler = threading.Thread(target=sample)
        sampler.start()
        try:
            for k in range(frames):
                segmenter.segment(pairs[k % 4])
        finally:
            done.set()
            sampler.join()
    return seen


def test_the_worker_segments_each_frame_at_real_time_priority():
    fifo = os.SCHED_FIFO
    if permitted():
        assert fifo in _worker_policies(True)
    assert fifo not in _worker_policies(False)


def _worker_waiting_after_a_rehearsal(realtime: bool) -> tuple[set[str], set[int]]:
    """The worker's states and scheduling policies, read from /proc for 60 ms once it has
    segmented a frame and rehearsed (polling for the next frame, if it does, for 1 s)."""
    from tests.tracker.segmentation_common import flickering_scene
    from tracker.vision.parallel import ParallelPairSegmenter

    catheter, scene, renderer = flickering_scene(3, 0.3)
    images = renderer.render(np.array([0.2, 0.6, 0.5]), 0.4, np.random.default_rng(3)).images
    states: set[str] = set()
    policies: set[int] = set()
    with ParallelPairSegmenter(
        catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds,
        realtime=realtime, worker_poll_s=1.0,
    ) as segmenter:  # fmt: skip
        assert segmenter.parallel
        segmenter.segment(images)
        segmenter.rehearse(images)
        time.sleep(0.1)  # the rehearsal done
        stat = f"/proc/{segmenter._process.pid}/stat"
        until = time.monotonic() + 0.06
        while time.monotonic() < until:
            with open(stat) as f:
                fields = f.read().rsplit(")", 1)[1].split()
            states.add(fields[0])
            policies.add(int(fields[38]))
            time.sleep(0.001)
        segmenter.segment(images)  # and it still answers
    return states, policies


def test_the_worker_waits_for_the_frame_blocked_at_real_time_priority():
    """Where permitted, the worker sleeps at SCHED_FIFO until the request wakes it (ahead of
    ordinary threads on its processor); without it, it polls at the ordinary priority."""
    if permitted():
        states, policies = _worker_waiting_after_a_rehearsal(True)
        assert policies == {os.SCHED_FIFO}
        assert states == {"S"}
    states, policies = _worker_waiting_after_a_rehearsal(False)
    assert policies == {os.SCHED_OTHER}
    assert "R" in states  # polling
