"""A rig of three views end to end: rig file, reconstruction, estimators, datagrams, live loop.

The data flow carries a sequence of named views; the paper's bi-plane rig is the two-view
case. A third camera is a change of the rig, not of the code.
"""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import OrthographicPlane, PinholeView, Rig
from models.model_file import DEFAULT_MODEL_PATH
from models.pose import Pose
from models.rig_file import rig_from_toml, rig_toml
from models.rotations import wrap_angle
from replay.simulation.simulator import (
    NoiseSettings,
    default_scene,
    point_arclengths,
    simulate_frames,
    sinusoidal,
    torsion_constant,
)
from replay.simulation.sources import session_joints
from tracker.estimators import make_estimator
from tracker.io.datagrams import encode_markers
from tracker.io.recording import RecordingWriter, open_recording
from tracker.io.udp import JointReceiver, JointStreamer, MarkerReceiver
from tracker.live.loop import run_live
from tracker.live.sinks import MemorySink
from tracker.live.sources import UdpMarkerSource
from tracker.reconstruction import Reconstructor

NAMES = ("front", "side", "top")
DELTA_L_RAD = 1.2


def three_view_rig(kind: str) -> Rig:
    if kind == "orthographic":
        views = [OrthographicPlane.from_normal(n) for n in ([0, -1, 0], [1, 0, 0], [0, 0, 1])]
        return Rig(*views, names=NAMES)
    origin = np.zeros(3)
    views = [
        PinholeView.look_at([0.0, -400.0, 0.0], origin, [0.0, 0.0, 1.0], 1000.0),
        PinholeView.look_at([400.0, 0.0, 0.0], origin, [0.0, 0.0, 1.0], 1000.0),
        PinholeView.look_at([0.0, 0.0, 400.0], origin, [0.0, 1.0, 0.0], 1000.0),
    ]
    return Rig(*views, names=NAMES)


def session(kind: str, seed: int = 0, duration_s: float = 6.0):
    scene = default_scene(default_catheter(), three_view_rig(kind))
    trajectory = sinusoidal([0.2, 0.55, 0.2], [0.5, 0.3, 0.5], [16.0, 9.0, 6.0], duration_s)
    truth = torsion_constant(trajectory.time_s, DELTA_L_RAD)
    sigma = 0.05 if kind == "orthographic" else 0.5  # mm in a plane, px in a camera
    frames = simulate_frames(
        scene, trajectory, truth, NoiseSettings(sigma=sigma), np.random.default_rng(seed)
    )
    return scene, frames


def rms_deg(estimates) -> float:
    valid = [e for e in estimates if e.valid]
    errors = wrap_angle(np.array([e.delta_L_rad for e in valid]) - DELTA_L_RAD)
    return float(np.degrees(np.sqrt(np.mean(errors**2))))


@pytest.mark.parametrize("kind", ["orthographic", "pinhole"])
def test_frames_carry_one_set_of_points_per_view(kind):
    scene, frames = session(kind, duration_s=1.0)
    assert scene.rig.names == NAMES
    assert all(f.n_views == 3 for f in frames)


@pytest.mark.parametrize("kind", ["orthographic", "pinhole"])
def test_a_third_view_shrinks_the_reconstruction_covariance(kind):
    scene, frames = session(kind, duration_s=1.0)
    three = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    two_rig = scene.rig.subset([0, 1])
    two = Reconstructor(scene.catheter, two_rig, scene.R_w_b, scene.o_b_w_mm)
    two_frames = [
        type(f)(f.time_s, f.q, f.q_dot, f.uv[:2], f.cov[:2], None, f.delta_L_true_rad)
        for f in frames
    ]
    cov3 = np.array([o.tip_cov_b for o in three.observe_batch(frames)])
    cov2 = np.array([o.tip_cov_b for o in two.observe_batch(two_frames)])
    # Information adds over views: the three-view covariance is never larger.
    assert np.all(np.trace(cov3, axis1=1, axis2=2) < np.trace(cov2, axis1=1, axis2=2))


@pytest.mark.parametrize("kind", ["orthographic", "pinhole"])
@pytest.mark.parametrize("method", ["tip-position", "body-positions", "ukf"])
def test_estimators_track_with_three_views(kind, method):
    scene, frames = session(kind)
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    estimator = make_estimator(method, scene.catheter)
    estimates = [estimator.step(o) for o in reconstructor.observe_batch(frames)]
    assert sum(e.valid for e in estimates) > 0.8 * len(frames)
    assert rms_deg(estimates) < 2.0


def test_a_point_seen_by_one_view_only_becomes_a_single_view_measurement():
    scene, frames = session("pinhole", duration_s=0.5)
    f = frames[3]
    hidden = [uv.copy() for uv in f.uv]
    hidden[0][1] = np.nan  # the marker: front only missing -> side and top still triangulate
    hidden[1][0] = hidden[2][0] = np.nan  # the tip: seen by the front view only
    frame = type(f)(f.time_s, f.q, f.q_dot, tuple(hidden), f.cov, None, f.delta_L_true_rad)
    observation = Reconstructor(
        scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm
    ).observe(frame)
    assert np.all(np.isnan(observation.tip_b_mm))
    assert np.all(np.isfinite(observation.markers_b_mm[0]))
    assert [v.point_index.tolist() for v in observation.views] == [[-1]]


def test_rig_files_and_recordings_keep_the_three_named_views(tmp_path):
    scene, frames = session("pinhole", duration_s=1.0)
    text = rig_toml(scene.rig)
    rig, _ = rig_from_toml(text)
    assert rig.names == NAMES
    path = tmp_path / "three.mcap"
    model = DEFAULT_MODEL_PATH.read_text()
    with RecordingWriter(path, model_toml=model, rig_toml=text) as writer:
        writer.write_joints(
            np.array([f.time_s for f in frames]), np.array([f.q for f in frames])
        )
        for frame in frames:
            writer.write_frame(frame)
    with open_recording(path) as recording:
        read = [r.frame for r in recording.frames()]
        assert recording.views == NAMES
    assert len(read) == len(frames)
    for a, b in zip(read, frames, strict=True):
        for uv_a, uv_b in zip(a.uv, b.uv, strict=True):
            np.testing.assert_allclose(uv_a, uv_b)


def test_live_loop_with_three_views_over_udp():
    """Markers of three views as datagrams, joints at 1 kHz, the UKF, estimates out."""
    scene = default_scene(default_catheter(), three_view_rig("pinhole"))
    catheter = scene.catheter
    n_points = 1 + len(catheter.marker_arclengths_mm)
    rng = np.random.default_rng(5)
    start_s = time.monotonic()
    memory = MemorySink()
    with (
        JointReceiver(port=0, clock="sender", stale_after_s=0.2) as joints,
        JointStreamer(joints.address, session_joints, 1000.0, start_s=start_s),
        MarkerReceiver(port=0, n_points=n_points, n_views=3) as markers,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as segmenter,
    ):
        arclengths = np.asarray(point_arclengths(catheter))
        pose = Pose(scene.R_w_b, scene.o_b_w_mm)
        time.sleep(0.05)  # joints first, as a controller that is already running
        for k in range(40):
            t = start_s + 0.05 + 0.025 * k
            time.sleep(max(0.0, t - time.monotonic()))
            q, _ = session_joints(time.monotonic() - start_s)
            t = time.monotonic()
            points_w = pose.world_from_base(catheter.backbone(q, DELTA_L_RAD, arclengths))
            uv = [
                v.project(points_w) + 0.3 * rng.standard_normal((n_points, 2))
                for v in scene.rig.views
            ]
            segmenter.sendto(encode_markers(k, t, uv, (0.3, 0.3, 0.3)), markers.address)
        summary = run_live(
            UdpMarkerSource(markers, poll_s=0.02),
            Reconstructor(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
            make_estimator("ukf", catheter),
            [memory],
            joints=joints,
            idle_timeout_s=0.3,
            handle_signals=False,
        )
    assert summary.markers.accepted == 40 and summary.frames_processed == 40
    estimates = [r.estimate for r in memory.results]
    assert rms_deg(estimates[10:]) < 3.0
