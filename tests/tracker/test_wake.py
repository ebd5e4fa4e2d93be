"""The processors kept awake while the live loop runs (tracker.live.wake): the PM QoS
request written and held for the run only, and a machine that does not permit it."""

from __future__ import annotations

import struct

import pytest

from tests.tracker import live_common
from tests.tracker.live_common import reconstructor_of
from tracker.estimators import make_estimator
from tracker.live.loop import LiveTracker
from tracker.live.sinks import MemorySink
from tracker.live.summary import LiveSummary
from tracker.live.wake import WakeLatency

noisy_session = live_common.noisy_session


def test_the_bound_is_written_held_and_lifted(tmp_path):
    path = tmp_path / "cpu_dma_latency"
    path.write_bytes(b"")
    wake = WakeLatency(max_us=7, path=path)
    assert not wake.held
    assert wake.hold() and wake.held
    assert wake.hold()  # already held: nothing written again
    assert path.read_bytes() == struct.pack("=i", 7)
    wake.release()
    assert not wake.held
    wake.release()  # twice: nothing to do
    with pytest.raises(ValueError, match="max_us"):
        WakeLatency(max_us=-1)


@pytest.mark.parametrize("where", ["missing", "directory"])
def test_a_machine_that_does_not_permit_it_is_told_once(tmp_path, where):
    path = tmp_path / "nothing here" if where == "missing" else tmp_path
    reports = []
    wake = WakeLatency(path=path, report=reports.append)
    assert not wake.hold() and not wake.held
    assert len(reports) == 1 and str(path) in reports[0] and "--no-keep-awake" in reports[0]
    assert wake.problem == reports[0]
    wake.release()  # nothing held: nothing to lift


class HeldDuringFrames(MemorySink):
    """Records, at each frame, whether the loop's bound was in force."""

    def __init__(self):
        super().__init__()
        self.tracker = None
        self.held = []

    def handle(self, frame, observation, estimate, latency_s, status):
        super().handle(frame, observation, estimate, latency_s, status)
        self.held.append(self.tracker.wake.held)


@pytest.mark.parametrize("permitted", [True, False])
def test_the_loop_holds_the_bound_for_its_run_only(noisy_session, tmp_path, permitted):
    path = tmp_path / "cpu_dma_latency"
    if permitted:
        path.write_bytes(b"")
    sink = HeldDuringFrames()
    reports = []
    tracker = LiveTracker(
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [sink],
        report=reports.append,
        keep_awake=True,
    )
    sink.tracker = tracker
    tracker.wake.path = path
    summary = tracker.run(noisy_session.frames, max_frames=5, handle_signals=False)
    assert summary.frames_processed == 5
    assert sink.held == [permitted] * 5
    assert not tracker.wake.held  # lifted with the run
    assert summary.kept_awake is permitted
    awake = [line for line in summary.lines() if "kept awake" in line]
    assert awake == [
        "  processors kept awake between frames: "
        + ("yes" if permitted else "no (frames may start cold)")
    ]
    assert sum("sleep deeply" in message for message in reports) == (0 if permitted else 1)


def test_a_loop_not_asked_says_nothing(noisy_session):
    tracker = LiveTracker(
        reconstructor_of(noisy_session), make_estimator("ukf", noisy_session.scene.catheter)
    )
    assert tracker.wake is None
    summary = tracker.run(noisy_session.frames, max_frames=2, handle_signals=False)
    assert summary.kept_awake is None
    assert not any("kept awake" in line for line in summary.lines())
    assert LiveSummary(kept_awake=False).lines()[-1].endswith("frames may start cold)")


def test_elsewhere_than_linux_nothing_is_tried_or_reported(tmp_path, monkeypatch):
    path = tmp_path / "cpu_dma_latency"
    path.write_bytes(b"")
    monkeypatch.setattr("tracker.live.wake.sys.platform", "darwin")
    reports = []
    wake = WakeLatency(path=path, report=reports.append)
    assert not wake.hold() and not reports and "Linux" in wake.problem
    assert path.read_bytes() == b""
