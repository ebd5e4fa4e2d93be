"""The online loop against the clock: a slow sink or a full queue, a source faster than the
loop or failing in its thread, frames stamped far ahead or on a restarted clock, estimator
errors and unusable frames, the CSV sink, paced sources, the loop stepped by hand, and the
latency's medians by third of a run (a loop falling behind)."""

from __future__ import annotations

import dataclasses
import math
import threading
import types

import numpy as np
import pytest

from replay.simulation.sources import SimulatedSource
from tests.tracker import live_common
from tests.tracker.live_common import reconstructor_of
from tracker.estimators import make_estimator
from tracker.io.udp import EstimateSender
from tracker.live.loop import LiveTracker, run_live
from tracker.live.sinks import CSV_COLUMNS, CsvSink, LiveStatus, MemorySink, QueuedSink
from tracker.live.sources import ImageSet, PacedSource
from tracker.live.summary import LatencyRecorder, LiveSummary
from tracker.types import Estimate

# Fixtures shared with test_live.py: pytest finds them under these names.
noisy_session = live_common.noisy_session
controller = live_common.controller


# ------------------------------------------------------------------------ real time
class FakeClock:
    """A monotonic clock that moves 0.1 ms at every reading, and when told (thread-safe)."""

    def __init__(self):
        self.now = 0.0
        self._lock = threading.Lock()

    def __call__(self):
        with self._lock:
            self.now += 1e-4
            return self.now

    def advance_to(self, time_s):
        with self._lock:
            self.now = max(self.now, time_s)

    def advance(self, seconds):
        with self._lock:
            self.now += seconds


class SlowSink:
    """Takes 200 ms of the clock per frame; its first frame waits until it is released."""

    name = "slow"

    def __init__(self, clock):
        self.clock = clock
        self.started, self.release = threading.Event(), threading.Event()
        self.times = []
        self.closed = False

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE):
        self.started.set()
        self.release.wait(10.0)
        self.clock.advance(0.2)
        self.times.append(frame.time_s)

    def close(self):
        self.closed = True


class Camera:
    """Frames stamped on the fake clock at their exposure time (like triggered cameras)."""

    time_is_monotonic = True

    def __init__(self, frames, clock, after_first=None, at_end=None):
        self.frames, self.clock = frames, clock
        self.after_first, self.at_end = after_first, at_end

    def __iter__(self):
        for k, frame in enumerate(self.frames):
            self.clock.advance_to(frame.time_s)
            yield frame
            if k == 0 and self.after_first is not None:
                self.after_first()
        if self.at_end is not None:
            self.at_end()


def test_a_slow_sink_neither_delays_the_estimates_nor_keeps_every_frame(noisy_session, controller):
    """A sink that takes 200 ms a frame, behind a queue of 4: the estimate datagrams leave
    as fast as without it, and the frames it could not take are dropped and counted.

    Deterministic: the fake clock moves only when read (0.1 ms) and when the sink works;
    the sink's first frame waits until the camera has delivered every frame, and the camera
    delivers the second one only once the sink has started on the first."""
    frames = noisy_session.frames[:30]
    clock = FakeClock()
    slow = SlowSink(clock)
    queued = QueuedSink(slow, capacity=4)
    camera = Camera(
        frames, clock, after_first=lambda: slow.started.wait(10.0), at_end=slow.release.set
    )
    summary = run_live(
        camera,
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [EstimateSender(controller.address), queued],
        handle_signals=False,
        monotonic=clock,
    )
    controller.receive_estimates()
    latency_ms = 1e3 * np.array([m.latency_s for m in controller.estimates])
    assert len(latency_ms) == summary.frames_processed == len(frames)
    assert np.percentile(latency_ms, 99) <= 5.0
    # The sink took the first frame, then the newest four that its queue held.
    assert slow.times == [frames[0].time_s] + [f.time_s for f in frames[-4:]] and slow.closed
    assert queued.dropped == summary.sink_dropped["slow"] == len(frames) - 5
    assert summary.sink_stalls["slow"] == 0
    assert clock.now > 5 * 0.2  # the sink did take its 200 ms a frame
    assert any("sink slow fell behind: 25 frames dropped" in line for line in summary.lines())


def test_a_recording_sink_behind_a_full_queue_waits_and_loses_nothing(noisy_session):
    frames = noisy_session.frames[:12]
    reports = []
    release = threading.Event()

    class Stuck(MemorySink):
        name = "stuck"

        def handle(self, *args, **kwargs):
            release.wait(10.0)  # until the loop has had to wait for room
            super().handle(*args, **kwargs)

    def report(line):
        reports.append(line)
        release.set()

    stuck = Stuck()
    queued = QueuedSink(stuck, capacity=2, keep_all=True, report=report)
    summary = run_live(
        frames,
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [queued],
        handle_signals=False,
    )
    assert [r.frame.time_s for r in stuck.results] == [f.time_s for f in frames]
    assert queued.dropped == 0 and summary.sink_stalls["stuck"] == queued.stalls >= 1
    assert len(reports) == 1 and reports[0].startswith("WARNING: sink stuck cannot keep up")


class LiveImages:
    """A live source (own thread, newest only) of image sets that stand for frames: the
    images carry the index of the frame whose points the fake segmenter returns."""

    live = True

    def __init__(self, frames, script):
        self.frames, self.script = frames, script

    def images(self, k):
        return ImageSet(self.frames[k].time_s, (np.full((2, 2), k), np.full((2, 2), k)))

    def __iter__(self):
        yield from self.script(self)


class GatedSegmenter:
    """Returns the points of the frame the images stand for; waits for ``proceed``."""

    def __init__(self, frames):
        self.frames = frames
        self.entered, self.proceed = threading.Event(), threading.Event()
        self.calls = []

    def segment(self, images, predicted_px=None):
        k = int(images[0][0, 0])
        self.calls.append(k)
        self.entered.set()
        self.proceed.wait(10.0)
        frame = self.frames[k]
        return types.SimpleNamespace(uv=frame.uv, cov=frame.cov)


def test_a_source_faster_than_the_loop_gets_only_its_newest_pair_processed(noisy_session):
    """Pairs 1-5 come while the loop segments pair 0: it then takes pair 5 only; 1-4 are
    dropped and counted (events, not timing, decide the order)."""
    frames = noisy_session.frames[:6]
    segmenter = GatedSegmenter(frames)

    def script(source):
        yield source.images(0)
        segmenter.entered.wait(10.0)  # the loop is busy with pair 0
        for k in range(1, 6):
            yield source.images(k)
        segmenter.proceed.set()

    memory, reports = MemorySink(), []
    summary = run_live(
        LiveImages(frames, script),
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [memory],
        segmenter=segmenter,
        report=reports.append,
        handle_signals=False,
    )
    assert segmenter.calls == [0, 5]
    assert [r.frame.time_s for r in memory.results] == [frames[0].time_s, frames[5].time_s]
    assert summary.frames_superseded == summary.frames_dropped == 4
    assert summary.frames_received == summary.frames_processed == 2
    assert any("only the newest is processed" in line for line in reports)


def test_a_live_source_that_fails_in_its_thread_fails_the_run_after_the_clean_up(
    noisy_session,
):
    class Broken:
        live = True
        closed = False

        def __iter__(self):
            yield noisy_session.frames[0]
            raise OSError("camera unplugged")

        def close(self):
            self.closed = True

    source, memory = Broken(), MemorySink()
    with pytest.raises(OSError, match="camera unplugged"):
        run_live(
            source,
            reconstructor_of(noisy_session),
            make_estimator("ukf", noisy_session.scene.catheter),
            [memory],
            handle_signals=False,
        )
    assert memory.closed and source.closed


def test_one_frame_stamped_far_ahead_does_not_stop_the_stream(noisy_session, controller):
    """A frame stamped 1e6 s ahead (a damaged marker datagram) is dropped and counted; the
    frames after it are processed and every estimate datagram goes out."""
    frames = noisy_session.frames[:20]
    bogus = dataclasses.replace(frames[9], time_s=frames[9].time_s + 1e6)
    memory, reports = MemorySink(), []
    summary = run_live(
        frames[:10] + [bogus] + frames[10:],
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [EstimateSender(controller.address), memory],
        report=reports.append,
        handle_signals=False,
    )
    controller.receive_estimates()
    assert summary.frames_processed == summary.frames_valid == 20
    assert summary.frames_bad_time == {"too far ahead of the stream": 1}
    assert summary.frames_out_of_order == 0 and summary.frames_dropped == 1
    assert [m.sequence for m in controller.estimates] == list(range(20))
    assert all(m.valid for m in controller.estimates) and len(reports) == 1


def test_a_sender_whose_clock_restarts_is_followed_after_a_few_frames(noisy_session):
    frames = noisy_session.frames[:20]
    restarted = [dataclasses.replace(f, time_s=f.time_s - 100.0) for f in frames[10:]]
    memory, reports = MemorySink(), []
    summary = run_live(
        frames[:10] + restarted,
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),  # raises on time going back
        [memory],
        report=reports.append,
        handle_signals=False,
    )
    # Four frames behind the stream are dropped, the fifth makes the new time base.
    assert summary.frames_out_of_order == 4 and summary.time_rebases == 1
    assert summary.frames_processed == 16 and summary.estimator_errors == 0
    assert [r.frame.time_s for r in memory.results[10:]] == [f.time_s for f in restarted[4:]]
    assert any("new time base" in line for line in reports)


class FlakyEstimator:
    name = "flaky"

    def __init__(self):
        self.calls = 0

    def reset(self):
        """It keeps no state."""

    def step(self, observation):
        self.calls += 1
        if self.calls % 2 == 0:
            raise np.linalg.LinAlgError("covariance not positive definite")
        return Estimate(observation.time_s, 0.1, 0.01, float(observation.q[0]))


def test_an_estimator_error_gives_an_invalid_flagged_estimate(noisy_session):
    memory, reports = MemorySink(), []
    summary = run_live(
        noisy_session.frames[:6],
        reconstructor_of(noisy_session),
        FlakyEstimator(),
        [memory],
        report=reports.append,
        handle_signals=False,
    )
    assert summary.frames_processed == 6 and summary.estimator_errors == 3
    flagged = [bool(r.status & LiveStatus.ESTIMATOR_ERROR) for r in memory.results]
    assert flagged == [False, True] * 3
    assert all(not r.estimate.valid for r in memory.results if r.status)
    assert len(reports) == 1


def test_unusable_frames_are_dropped_and_reported_once(noisy_session):
    bad = [dataclasses.replace(f, uv=(f.uv[0][:-1], f.uv[1])) for f in noisy_session.frames[:3]]
    reports = []
    summary = run_live(
        bad + noisy_session.frames[3:6],
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        report=reports.append,
        handle_signals=False,
    )
    assert summary.frames_rejected == 3 and summary.frames_processed == 3
    assert len(reports) == 1 and "uv[front]" in reports[0]


def test_csv_sink_and_max_frames(noisy_session, tmp_path):
    path = tmp_path / "estimates.csv"
    summary = run_live(
        noisy_session.frames,
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [CsvSink(path)],
        max_frames=15,
        handle_signals=False,
    )
    assert summary.stop_reason == "max frames" and summary.frames_processed == 15
    lines = path.read_text().splitlines()
    assert lines[0].split(",") == list(CSV_COLUMNS) and len(lines) == 16
    row = dict(zip(CSV_COLUMNS, lines[-1].split(","), strict=True))
    assert float(row["time_s"]) == noisy_session.frames[14].time_s
    assert float(row["delta_L_true_rad"]) == noisy_session.frames[14].delta_L_true_rad


def test_paced_source_releases_items_at_real_time(noisy_session):
    clock = {"now": 100.0}
    sleeps = []

    def sleep(seconds):
        sleeps.append(seconds)
        clock["now"] += seconds

    source = PacedSource(
        noisy_session.frames[:5], speed=2.0, monotonic=lambda: clock["now"], sleep=sleep
    )
    assert [f.time_s for f in source] == [f.time_s for f in noisy_session.frames[:5]]
    np.testing.assert_allclose(sleeps, [0.025] * 4)  # 20 Hz frames at twice real time
    with pytest.raises(ValueError, match="speed"):
        PacedSource([], speed=0.0)
    stripped = list(SimulatedSource(noisy_session.frames[:2], speed=None, joints=False))
    assert not hasattr(stripped[0], "q") and stripped[1].sequence == 1


def test_loop_object_can_be_stepped_by_hand(noisy_session):
    tracker = LiveTracker(
        reconstructor_of(noisy_session), make_estimator("ukf", noisy_session.scene.catheter)
    )
    result = tracker.step(noisy_session.frames[0])
    assert result.estimate.valid and result.status == LiveStatus.NONE
    assert tracker.step(noisy_session.frames[0]) is None  # same time again: dropped
    tracker.close()
    assert math.isfinite(tracker.summary.latency_ms["p50"])


def test_the_latency_recorder_keeps_its_ring_in_order_and_gives_each_thirds_median():
    recorder = LatencyRecorder(capacity=4)
    for k in range(2):
        recorder.add(1e-3 * (k + 1))
    assert all(math.isnan(ms) for ms in recorder.thirds_ms())  # fewer than three
    summary = LiveSummary(latency_thirds_ms=recorder.thirds_ms())
    assert not any("third" in line for line in summary.lines())  # no line of NaNs
    for k in range(2, 6):
        recorder.add(1e-3 * (k + 1))
    # Six added to a ring of four: the last four, oldest first.
    np.testing.assert_allclose(recorder.values(), 1e-3 * np.array([3.0, 4.0, 5.0, 6.0]))
    # Thirds of four, as numpy splits them: (3, 4), (5,), (6,) ms.
    np.testing.assert_allclose(recorder.thirds_ms(), [3.5, 5.0, 6.0])


@pytest.mark.parametrize("lag_per_frame_s", [0.0, 0.01])
def test_a_loop_that_falls_behind_shows_it_in_the_latency_of_each_third(
    noisy_session, lag_per_frame_s
):
    """Each frame handed over ``lag_per_frame_s`` later than the one before, after its
    release: the summary's medians by third rise by that times the frames between the
    thirds' middles; handed over as they come, they stay flat."""
    clock = FakeClock()
    tracker = LiveTracker(
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        monotonic=clock,
    )
    frames = noisy_session.frames[:30]
    for k, frame in enumerate(frames):
        clock.advance_to(frame.time_s + k * lag_per_frame_s)
        assert tracker.step(frame, received_s=frame.time_s) is not None
    tracker.close()
    first, middle, last = tracker.summary.latency_thirds_ms
    # Thirds of ten frames: their middles are ten frames apart.
    assert middle - first == pytest.approx(1e3 * 10 * lag_per_frame_s, abs=0.5)
    assert last - middle == pytest.approx(1e3 * 10 * lag_per_frame_s, abs=0.5)
    line = next(x for x in tracker.summary.lines() if "in each third of the run" in x)
    assert f"{first:.2f} / {middle:.2f} / {last:.2f} ms" in line
