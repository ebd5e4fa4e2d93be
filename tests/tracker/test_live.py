"""The online loop end to end: a simulated controller on loopback UDP, and every fault; a
recorded live session replayed, a whole LiveSession, and Ctrl-C. The loop against the clock
(slow sinks, sources faster than it, time stamps gone wrong) is in test_live_real_time.py."""

from __future__ import annotations

import math
import os
import select
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import isotropic_covariance
from models.model_file import DEFAULT_MODEL_PATH
from models.pose import Pose
from models.rig_file import rig_toml
from models.rotations import wrap_angle
from replay.simulation.render import Renderer, default_render_rig
from replay.simulation.simulator import default_scene, point_arclengths
from replay.simulation.sources import RenderedSource, session_joints, simulated_session
from tests.tracker import live_common
from tests.tracker.live_common import JOINT_RATE_HZ, LOOPBACK, Controller, reconstructor_of
from tracker.estimators import make_estimator
from tracker.io.datagrams import SegmentedMarkers, encode_joints, encode_markers
from tracker.io.recording import RecordingWriter, open_recording
from tracker.io.udp import EstimateSender, JointReceiver, JointStreamer, MarkerReceiver
from tracker.live.loop import run_live
from tracker.live.session import LiveSession, SessionSettings
from tracker.live.sinks import LiveStatus, MemorySink, QueuedSink, RecordingSink
from tracker.live.sources import ImageSet, RecordingSource, UdpMarkerSource, VideoSource
from tracker.types import Flag
from tracker.vision.pair import PairSegmenter

REPO = Path(__file__).resolve().parents[2]

# Fixtures shared with test_live_real_time.py: pytest finds them under these names.
noisy_session = live_common.noisy_session
controller = live_common.controller


@pytest.fixture(scope="module")
def exact_session():
    """6 s at 20 Hz with negligible segmentation noise (1e-7 mm)."""
    return simulated_session(duration_s=6.0, frame_rate_hz=20.0, noise=1e-7, seed=0)


def controlled(frames, controller, joints, faults=True, stop_s=math.inf, resume_s=math.inf):
    """Frames released after the controller has sent the joints up to their time (+2 ms).

    Every tenth frame a garbage and a truncated datagram go along; the joint stream is
    silent between ``stop_s`` and ``resume_s``.
    """
    for k, frame in enumerate(frames):
        if frame.time_s < stop_s or frame.time_s >= resume_s:
            if frame.time_s >= resume_s and controller.next_sample / JOINT_RATE_HZ < resume_s:
                controller.next_sample = int(round(resume_s * JOINT_RATE_HZ))
            controller.send_joints_until(frame.time_s + 0.002, joints.address)
        if faults and k % 10 == 5:
            controller.sock.sendto(b"\xde\xad\xbe\xef" * 18, joints.address)
            controller.sock.sendto(encode_joints(0, 0.0, [0, 0, 0], [0, 0, 0])[:50], joints.address)
        yield frame
        controller.receive_estimates()


# ------------------------------------------------------------------- the closed loop
def test_closed_loop_over_udp_recovers_the_truth_exactly(exact_session, controller):
    """Joints at 1 kHz in, estimates out: without noise the closed form is exact."""
    session = exact_session
    with JointReceiver(port=0, clock="sender") as joints:
        memory = MemorySink()
        summary = run_live(
            controlled(session.frames, controller, joints),
            reconstructor_of(session),
            make_estimator("tip-position", session.scene.catheter),
            [EstimateSender(controller.address), memory],
            joints=joints,
            handle_signals=False,
        )
    controller.receive_estimates()
    n = len(session.frames)
    assert summary.frames_processed == summary.frames_valid == n
    assert summary.stop_reason == "source exhausted"
    assert summary.joints.malformed == {"magic": n // 10, "size": n // 10}
    assert summary.joints.accepted == controller.sequence
    received = controller.estimates
    assert [m.sequence for m in received] == list(range(n))
    times = np.array([m.time_s for m in received])
    np.testing.assert_array_equal(times, [f.time_s for f in session.frames])
    errors = wrap_angle(np.array([m.delta_L_rad for m in received]) - session.delta_L_true_rad)
    assert np.max(np.abs(errors)) < 1e-5
    delta_1 = session.trajectory.q[:, 0] + session.delta_L_true_rad
    assert np.max(np.abs(wrap_angle(np.array([m.delta_1_rad for m in received]) - delta_1))) < 1e-5
    assert all(m.valid and m.status == 0 and m.latency_s > 0 for m in received)
    # The frames carried the joints received over UDP, interpolated to the image times.
    q = np.array([r.frame.q for r in memory.results])
    np.testing.assert_allclose(q, session.trajectory.q, atol=1e-12)
    assert summary.latency_ms["p50"] > 0 and math.isfinite(summary.latency_ms["p99"])


class LiveMarkers:
    """Markers of the moving catheter 'captured' at 30 Hz, stamped with time.monotonic()."""

    time_is_monotonic = True

    def __init__(self, scene, start_s, duration_s, delta_L_rad, noise, seed):
        self.scene, self.start_s, self.duration_s = scene, start_s, duration_s
        self.delta_L_rad, self.noise = delta_L_rad, noise
        self.rng = np.random.default_rng(seed)

    def __iter__(self):
        scene = self.scene
        arclengths = np.asarray(point_arclengths(scene.catheter))
        cov = np.broadcast_to(isotropic_covariance(self.noise), (arclengths.size, 2, 2))
        tick = self.start_s
        while tick - self.start_s < self.duration_s:
            tick += 1 / 30
            time.sleep(max(0.0, tick - time.monotonic()))
            t = time.monotonic()
            q, _ = session_joints(t - self.start_s)
            points_b = scene.catheter.backbone(q, self.delta_L_rad, arclengths)
            points_w = points_b @ scene.R_w_b.T + scene.o_b_w_mm
            uv = [
                v.project(points_w) + self.noise * self.rng.standard_normal((arclengths.size, 2))
                for v in (scene.rig.views[0], scene.rig.views[1])
            ]
            yield SegmentedMarkers(t, (uv[0], uv[1]), (cov, cov))


def test_real_time_controller_at_1khz_and_ukf(noisy_session):
    """A controller thread streams joints at 1 kHz on the shared monotonic clock."""
    scene = noisy_session.scene
    delta_L = 2.0
    controller = Controller()  # receives the estimates
    start_s = time.monotonic()
    with (
        JointReceiver(port=0, clock="sender", stale_after_s=0.2) as joints,
        JointStreamer(joints.address, session_joints, 1000.0, start_s=start_s) as streamer,
    ):
        summary = run_live(
            LiveMarkers(scene, start_s, 2.0, delta_L, noise=0.3, seed=2),
            reconstructor_of(noisy_session),
            make_estimator("ukf", scene.catheter),
            [EstimateSender(controller.address)],
            joints=joints,
            handle_signals=False,
        )
    deadline = time.monotonic() + 5.0
    while len(controller.estimates) < summary.frames_processed and time.monotonic() < deadline:
        controller.receive_estimates()
        time.sleep(0.01)
    controller.close()
    assert not streamer._thread.is_alive()
    assert summary.frames_processed >= 30 and summary.frames_dropped == 0
    assert summary.frames_stale_joints == summary.frames_no_joints == 0
    assert 1000 < summary.joints.accepted <= streamer.sent  # it streams on until stopped
    received = controller.estimates
    assert len(received) == summary.frames_processed
    later = [m for m in received[len(received) // 2 :] if m.valid]
    errors = wrap_angle(np.array([m.delta_L_rad for m in later]) - delta_L)
    assert np.degrees(np.sqrt(np.mean(errors**2))) < 3.0
    # Latency is measured from the image time stamp on the monotonic clock.
    assert all(0 < m.latency_s < 1.0 for m in received)


# ------------------------------------------------------------------------------ faults
def test_a_joint_stream_that_stops_flags_frames_and_predicts_only(noisy_session, controller):
    session = noisy_session
    # The receiver's clock is the simulated controller's: its 2 s pause is 2 s for it too.
    simulated_now = lambda: controller.next_sample / JOINT_RATE_HZ  # noqa: E731
    with JointReceiver(
        port=0, clock="sender", stale_after_s=0.1, monotonic=simulated_now
    ) as joints:
        memory = MemorySink()
        summary = run_live(
            controlled(session.frames, controller, joints, faults=False, stop_s=3.0, resume_s=5.0),
            reconstructor_of(session),
            make_estimator("ukf", session.scene.catheter),
            [EstimateSender(controller.address), memory],
            joints=joints,
            handle_signals=False,
        )
    controller.receive_estimates()
    times = np.array([f.time_s for f in session.frames])
    # The last joints went with the last frame before 3 s (2 ms ahead of it); frames more
    # than 0.1 s after them and before 5 s have stale joints.
    newest_joint_s = times[times < 3.0].max() + 0.002
    expected_stale = (times - newest_joint_s > 0.1) & (times < 5.0)
    stale = np.array([bool(r.status & LiveStatus.STALE_JOINTS) for r in memory.results])
    np.testing.assert_array_equal(stale, expected_stale)
    assert summary.frames_stale_joints == expected_stale.sum() > 0
    for result, flagged in zip(memory.results, stale, strict=True):
        if flagged:
            assert result.observation.tip_b_mm is None  # the estimator saw no measurement
            assert Flag.NO_MEASUREMENT in result.estimate.flags
            assert not result.estimate.valid  # held by the UKF, but not for the controller
    # Frames past the newest sample by more than the hold (20 ms), not yet stale: flagged
    # extrapolated, predict only too.
    expected_held = (times - newest_joint_s > 0.02) & ~expected_stale & (times < 5.0)
    held = [bool(r.status & LiveStatus.JOINTS_EXTRAPOLATED) for r in memory.results]
    np.testing.assert_array_equal(held, expected_held)
    assert summary.frames_extrapolated_joints == expected_held.sum() == 2
    invalid = expected_stale | expected_held
    assert summary.frames_valid == len(session.frames) - invalid.sum()
    messages = controller.estimates
    # The stream goes on through the pause: every frame has its datagram, flagged and with
    # the valid bit clear while the joints are missing.
    assert [m.sequence for m in messages] == list(range(len(session.frames)))
    np.testing.assert_array_equal(
        [bool(m.status & LiveStatus.STALE_JOINTS) for m in messages], expected_stale
    )
    np.testing.assert_array_equal([m.valid for m in messages], ~invalid)
    # Tracking resumes with the joints.
    after = [r for r in memory.results if r.frame.time_s >= 5.0]
    assert after and all(Flag.NO_MEASUREMENT not in r.estimate.flags for r in after)


def test_frames_out_of_order_or_repeated_are_dropped(noisy_session):
    frames = noisy_session.frames[:10]
    shuffled = frames[:3] + [frames[1], frames[2]] + frames[3:6] + [frames[0]] + frames[6:]
    memory = MemorySink()
    summary = run_live(
        shuffled,
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),  # raises on time going back
        [memory],
        handle_signals=False,
    )
    assert summary.frames_received == 13 and summary.frames_processed == 10
    assert (summary.frames_out_of_order, summary.frames_duplicate) == (2, 1)
    assert summary.frames_dropped == 3 and summary.estimator_errors == 0
    assert [r.frame.time_s for r in memory.results] == [f.time_s for f in frames]


def test_frames_that_stop_end_the_loop_on_the_idle_timeout(noisy_session):
    scene = noisy_session.scene
    receiver = MarkerReceiver(port=0, n_points=1 + len(scene.catheter.marker_arclengths_mm))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as segmenter:
        for k, frame in enumerate(noisy_session.frames[:3]):
            data = encode_markers(k, frame.time_s, frame.uv, (0.3, 0.3))
            segmenter.sendto(data, receiver.address)
        segmenter.sendto(b"junk" * 40, receiver.address)
        memory = MemorySink()
        started = time.monotonic()
        summary = run_live(
            UdpMarkerSource(receiver, poll_s=0.02),
            reconstructor_of(noisy_session),
            make_estimator("ukf", scene.catheter),
            [memory],
            idle_timeout_s=0.3,
            handle_signals=False,
        )
    assert time.monotonic() - started < 10.0
    assert summary.stop_reason == "no frame for 0.3 s"
    assert summary.frames_processed == 3
    # Without a joint receiver the markers cannot be used: flagged, predict-only, no estimate.
    assert summary.frames_no_joints == 3 and summary.frames_valid == 0
    assert all(r.status == LiveStatus.NO_JOINTS for r in memory.results)
    assert summary.markers.malformed == {"magic": 1}
    with pytest.raises(ValueError, match="closed"):
        _ = receiver.address  # the loop closed the source


def test_a_camera_that_cannot_be_opened_is_one_clear_error(tmp_path):
    with pytest.raises(OSError, match="cannot open the front video '.*front.avi': no such file"):
        VideoSource([str(tmp_path / "front.avi"), str(tmp_path / "side.avi")])
    video = write_video(tmp_path / "ok.avi", [np.zeros((48, 64), np.uint8)] * 2)
    with pytest.raises(OSError, match="cannot open the side camera 97"):
        VideoSource([str(video), 97])  # no such device
    not_video = tmp_path / "notes.avi"
    not_video.write_text("not a video")
    with pytest.raises(OSError, match="cannot open the side video"):
        VideoSource([str(video), str(not_video)])


def write_video(path, images, fps=20.0):
    h, w = images[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, (w, h), False)
    assert writer.isOpened()
    for image in images:
        writer.write(image)
    writer.release()
    return path


@pytest.fixture(scope="module")
def rendered():
    """Rendered images of a short session, the renderer and its segmenter."""
    catheter = default_catheter()
    scene = default_scene(catheter, default_render_rig())
    session = simulated_session(1.0, 10.0, noise=0.0, catheter=catheter, rig=scene.rig)
    renderer = Renderer(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    segmenter = PairSegmenter(
        catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds
    )
    return session, renderer, segmenter


def test_images_are_segmented_in_the_loop(rendered, controller):
    session, renderer, segmenter = rendered
    memory = MemorySink()
    with JointReceiver(port=0, clock="sender") as joints:
        controller.send_joints_until(1.0, joints.address)
        summary = run_live(
            RenderedSource(renderer, session.frames, seed=4, speed=None),
            reconstructor_of(session),
            make_estimator("tip-position", session.scene.catheter),
            [memory],
            joints=joints,
            segmenter=segmenter,
            handle_signals=False,
        )
    assert summary.frames_processed == len(session.frames) == summary.frames_valid
    assert memory.results[0].frame.images[0].shape == (480, 640)
    errors = wrap_angle(
        np.array([r.estimate.delta_L_rad for r in memory.results]) - session.delta_L_true_rad
    )
    assert np.degrees(np.max(np.abs(errors))) < 3.0


def rendered_videos(rendered, folder, seed):
    """The session's pairs rendered, and written as two lossless video files (10 fps)."""
    session, renderer, _ = rendered
    rng = np.random.default_rng(seed)
    pairs = [renderer.render(f.q, f.delta_L_true_rad, rng).images for f in session.frames]
    front = write_video(folder / "front.avi", [p[0] for p in pairs], fps=10.0)
    side = write_video(folder / "side.avi", [p[1] for p in pairs], fps=10.0)
    return pairs, front, side


def test_video_files_through_segmentation_track_the_truth(rendered, tmp_path, controller):
    session, renderer, segmenter = rendered
    pairs, front, side = rendered_videos(rendered, tmp_path, 5)
    with VideoSource([str(front), str(side)]) as video:
        items = list(video)
    assert len(items) == len(pairs) and isinstance(items[0], ImageSet)
    assert not video.time_is_monotonic and not video.live  # every frame, as fast as it goes
    with VideoSource([str(front), str(side)], realtime=True) as paced:
        assert paced.live  # at its frame rate, like a camera: the loop takes the newest
    np.testing.assert_array_equal(items[3].images[1], pairs[3][1])  # lossless, grayscale
    np.testing.assert_allclose([i.time_s for i in items], [f.time_s for f in session.frames])
    with (
        VideoSource([str(front), str(side)]) as video,
        JointReceiver(port=0, clock="sender") as joints,
    ):
        controller.send_joints_until(1.0, joints.address)  # joints on the video's time base
        memory = MemorySink()
        summary = run_live(
            video,
            reconstructor_of(session),
            make_estimator("tip-position", session.scene.catheter),
            [memory],
            joints=joints,
            segmenter=segmenter,
            handle_signals=False,
        )
    assert summary.frames_processed == len(pairs) and summary.frames_stale_joints == 0
    errors = wrap_angle(
        np.array([r.estimate.delta_L_rad for r in memory.results]) - session.delta_L_true_rad
    )
    assert np.degrees(np.max(np.abs(errors))) < 3.0


def test_video_files_with_the_views_side_by_side_give_the_same_estimates(
    rendered, tmp_path, controller
):
    """``cathtrack track --video``'s loop with the segmentation worker (its default with two
    processors) estimates every frame as the loop segmenting both views itself, exactly."""
    from tracker.vision.parallel import ParallelPairSegmenter

    session, renderer, _ = rendered
    scene = session.scene
    pairs, front, side = rendered_videos(rendered, tmp_path, 6)
    args = (scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds)
    estimates = []
    for segmenter in (PairSegmenter(*args), ParallelPairSegmenter(*args)):
        with (
            segmenter,
            VideoSource([str(front), str(side)]) as video,
            JointReceiver(port=0, clock="sender") as joints,
        ):
            controller.next_sample = 0  # the same joints again
            controller.send_joints_until(1.0, joints.address)
            memory = MemorySink()
            summary = run_live(
                video,
                reconstructor_of(session),
                make_estimator("ukf", scene.catheter),
                [memory],
                joints=joints,
                segmenter=segmenter,
                handle_signals=False,
            )
        assert summary.frames_processed == len(pairs)
        estimates.append([(r.estimate.delta_L_rad, r.estimate.std_rad) for r in memory.results])
    assert isinstance(segmenter, ParallelPairSegmenter) and segmenter.worker_failure == "closed"
    assert segmenter.frames_here == 0 and segmenter.frames == len(pairs)  # all side by side
    assert np.isfinite(np.array(estimates)).all()
    assert estimates[0] == estimates[1]


def test_images_without_a_segmenter_are_a_clear_error(noisy_session):
    memory = MemorySink()
    images = [ImageSet(0.0, (np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.uint8)))]
    with pytest.raises(ValueError, match="no segmenter"):
        run_live(
            images,
            reconstructor_of(noisy_session),
            make_estimator("ukf", noisy_session.scene.catheter),
            [memory],
            handle_signals=False,
        )
    assert memory.closed


class BrokenSink:
    """Raises on its third frame (a viewer that went away, a full disk...)."""

    name = "broken"

    def __init__(self):
        self.calls = 0
        self.closed = False

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE):
        self.calls += 1
        if self.calls == 3:
            raise ConnectionResetError("viewer not running")

    def close(self):
        self.closed = True


@pytest.mark.parametrize("queued", [False, True], ids=["inline", "queued"])
def test_a_sink_that_raises_is_reported_once_and_disabled(noisy_session, queued):
    broken, memory, reports = BrokenSink(), MemorySink(), []
    sink = QueuedSink(broken, 64, report=reports.append) if queued else broken
    summary = run_live(
        noisy_session.frames[:20],
        reconstructor_of(noisy_session),
        make_estimator("ukf", noisy_session.scene.catheter),
        [sink, memory],
        report=reports.append,
        handle_signals=False,
    )
    assert broken.calls == 3 and broken.closed and memory.closed
    assert len(memory.results) == summary.frames_processed == 20
    assert summary.sink_failures == {"broken": "ConnectionResetError: viewer not running"}
    assert len(reports) == 1 and "broken" in reports[0] and "disabled" in reports[0]
    assert any("sink broken disabled" in line for line in summary.lines())


# ----------------------------------------------------------------- colleagues' sinks
def test_a_recorded_live_session_replays_to_the_same_estimates(exact_session, controller, tmp_path):
    """RecordingSink writes the raw joints and the frames; RecordingSource plays them back."""
    session = exact_session
    scene = session.scene
    path = tmp_path / "live.mcap"
    writer = RecordingWriter(
        path,
        model_toml=DEFAULT_MODEL_PATH.read_text(),
        rig_toml=rig_toml(scene.rig, Pose(scene.R_w_b, scene.o_b_w_mm)),
        point_unit="mm",
    )
    frames = session.frames[:40]
    with JointReceiver(port=0, clock="sender") as joints:
        live = MemorySink()
        run_live(
            controlled(frames, controller, joints, faults=False),
            reconstructor_of(session),
            make_estimator("tip-position", scene.catheter),
            [RecordingSink(writer, "tip-position", joints=joints), live],
            joints=joints,
            handle_signals=False,
        )
    replayed = MemorySink()
    source = RecordingSource(path, speed=None)
    assert len(source.recording) == len(frames)
    summary = run_live(
        source,
        reconstructor_of(session),
        make_estimator("tip-position", scene.catheter),
        [replayed],
        handle_signals=False,
    )
    assert summary.frames_processed == len(frames)
    np.testing.assert_allclose(
        [r.frame.time_s for r in replayed.results], [r.frame.time_s for r in live.results]
    )
    np.testing.assert_allclose(
        [r.frame.q for r in replayed.results], [r.frame.q for r in live.results], atol=1e-9
    )
    np.testing.assert_allclose(
        [r.estimate.delta_L_rad for r in replayed.results],
        [r.estimate.delta_L_rad for r in live.results],
        atol=1e-6,
    )


# ------------------------------------------------------------------------- the session
def test_a_session_wires_the_joints_and_every_output(exact_session, controller, tmp_path):
    """LiveSession: joints over UDP in; estimate datagrams, a recording and a CSV file out."""
    frames = exact_session.frames[:40]
    settings = SessionSettings(
        estimator="tip-position",
        joints_port=0,
        joint_clock="sender",
        estimate_to=controller.address,
        record_path=tmp_path / "live.mcap",
        csv_path=tmp_path / "live.csv",
    )
    model_toml = DEFAULT_MODEL_PATH.read_text()
    with LiveSession(settings, exact_session.scene, model_toml=model_toml) as live:
        joints = live.joints
        assert live.inputs == [f"joints on udp://{LOOPBACK}:{joints.address[1]} (sender clock)"]
        assert live.outputs == [
            f"estimates to udp://{LOOPBACK}:{controller.address[1]}",
            f"recording {tmp_path / 'live.mcap'}",
            f"CSV {tmp_path / 'live.csv'}",
        ]
        summary = live.run(controlled(frames, controller, joints, faults=False))
    controller.receive_estimates()
    n = len(frames)
    assert summary.frames_processed == summary.frames_valid == n
    assert [m.sequence for m in controller.estimates] == list(range(n))
    assert len((tmp_path / "live.csv").read_text().splitlines()) == n + 1
    with open_recording(tmp_path / "live.mcap") as recording:
        assert len(recording) == n and len(recording.estimates["tip-position"]) == n


def test_a_session_that_cannot_be_set_up_closes_what_it_opened(exact_session, tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((LOOPBACK, 0))
        port = s.getsockname()[1]
    settings = SessionSettings(
        joints_port=port, estimate_to=None, record_path=tmp_path / "no" / "such" / "dir.mcap"
    )
    with pytest.raises(OSError):
        LiveSession(settings, exact_session.scene, model_toml="")
    JointReceiver(LOOPBACK, port).close()  # the joint port was released


# ------------------------------------------------------------------------------ Ctrl-C
SIGINT_SCRIPT = textwrap.dedent(
    """
    import dataclasses
    import sys

    from tracker.estimators import make_estimator
    from tracker.live.loop import LiveTracker
    from replay.simulation.sources import simulated_session
    from tracker.live.sources import PacedSource
    from tracker.reconstruction import Reconstructor

    class FileSink:
        name = "file"

        def __init__(self, path):
            self.file = open(path, "w")
            self.rows = 0

        def handle(self, frame, observation, estimate, latency_s, status=0):
            self.file.write(f"{frame.time_s!r},{estimate.delta_L_rad!r}\\n")
            self.rows += 1
            if self.rows == 3:
                print("running", flush=True)

        def close(self):
            self.file.write("closed\\n")
            self.file.close()

    session = simulated_session(duration_s=5.0, frame_rate_hz=20.0, noise=0.3)
    scene = session.scene

    def forever():
        lap = 0
        while True:
            for frame in session.frames:
                yield dataclasses.replace(frame, time_s=frame.time_s + 5.0 * lap)
            lap += 1

    sink = FileSink(sys.argv[1])
    tracker = LiveTracker(
        Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        make_estimator("ukf", scene.catheter),
        [sink],
    )
    summary = tracker.run(PacedSource(forever(), speed=1.0))
    print(summary, flush=True)
    print(f"rows {sink.rows}", flush=True)
    sys.exit(130 if summary.interrupted else 0)
    """
)


def test_sigint_closes_every_sink_and_prints_the_summary(tmp_path):
    script = tmp_path / "live_script.py"
    script.write_text(SIGINT_SCRIPT)
    out_file = tmp_path / "estimates.txt"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    process = subprocess.Popen(
        [sys.executable, str(script), str(out_file)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
        env=env,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60.0
        line = ""
        while "running" not in line:
            remaining = deadline - time.monotonic()
            assert remaining > 0 and process.poll() is None, process.stderr.read()
            ready, _, _ = select.select([process.stdout], [], [], remaining)
            if ready:
                line = process.stdout.readline()
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60.0)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 130, stderr
    assert "live loop ended (interrupted)" in stdout
    assert "Traceback" not in stderr
    rows = int(stdout.strip().splitlines()[-1].split()[1])
    lines = out_file.read_text().splitlines()
    assert lines[-1] == "closed" and len(lines) == rows + 1 >= 3
    processed = int(stdout.split(" frames processed")[0].split(": ")[-1].split(" of ")[0])
    assert processed == rows
