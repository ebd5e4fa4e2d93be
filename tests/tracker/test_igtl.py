"""OpenIGTLink sink: transforms by identities, and a pyigtl client on loopback."""

from __future__ import annotations

import numpy as np
import pyigtl
import pytest

from models.catheter import default_catheter
from models.rotations import rot_z
from replay.simulation.sources import SimulatedSource, simulated_session
from tracker.estimators import make_estimator
from tracker.io.igtl import IgtlSink, bending_plane_transform_w, tip_transform_w
from tracker.live.loop import run_live
from tracker.live.sinks import MemorySink
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Flag

WAIT_S = 10.0  # generous: connections and messages normally take milliseconds


def registered_base():
    R_w_b = rot_z(0.3) @ np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return R_w_b, np.array([5.0, -2.0, -15.0])


@pytest.fixture
def client_factory():
    clients = []

    def make(port):
        client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
        clients.append(client)
        return client

    yield make
    for client in clients:
        client.stop()


@pytest.mark.parametrize("delta_2", [0.0, np.pi / 2])
def test_tip_transform_is_the_model_tip_in_the_world(delta_2):
    catheter = default_catheter(delta_2)
    R_w_b, o_b_w = registered_base()
    q, delta_L = np.array([0.4, 0.6, -0.3]), 1.1
    T = tip_transform_w(catheter, q, delta_L, R_w_b, o_b_w)
    np.testing.assert_allclose(T[:3, 3], R_w_b @ catheter.tip(q, delta_L) + o_b_w, atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    # The proximal segment's tip {2} lies in the bending plane: y = 0 in the plane frame.
    P = bending_plane_transform_w(q[0] + delta_L, R_w_b, o_b_w)
    o_2_w = R_w_b @ catheter.frames(q, delta_L).o_2_b + o_b_w
    o_2_plane = P[:3, :3].T @ (o_2_w - P[:3, 3])
    assert abs(o_2_plane[1]) < 1e-12 and o_2_plane[0] > 0
    if delta_2 == 0.0:  # planar catheter: the tip is in the plane too
        tip_plane = P[:3, :3].T @ (T[:3, 3] - P[:3, 3])
        assert abs(tip_plane[1]) < 1e-12


def test_a_pyigtl_client_receives_both_transforms(client_factory):
    catheter = default_catheter()
    R_w_b, o_b_w = registered_base()
    reports = []
    with IgtlSink(catheter, R_w_b, o_b_w, port=0, report=reports.append) as sink:
        assert sink.port > 0
        client = client_factory(sink.port)
        assert sink.wait_for_client(WAIT_S)
        q = np.array([0.2, 0.5, 0.4])
        estimate = Estimate(time_s=1.0, delta_L_rad=-0.7, std_rad=0.01, q_r_rad=q[0])
        frame = type("F", (), {"q": q})()
        sink.handle(frame, None, estimate, 0.001)
        tip = client.wait_for_message("CathTip", timeout=WAIT_S)
        plane = client.wait_for_message("BendingPlane", timeout=WAIT_S)
    assert tip is not None and plane is not None
    assert tip.message_type == "TRANSFORM" and plane.message_type == "TRANSFORM"
    expected_tip = tip_transform_w(catheter, q, -0.7, R_w_b, o_b_w)
    expected_plane = bending_plane_transform_w(q[0] - 0.7, R_w_b, o_b_w)
    # OpenIGTLink carries float32.
    np.testing.assert_allclose(tip.matrix, expected_tip, atol=1e-5)
    np.testing.assert_allclose(plane.matrix, expected_plane, atol=1e-5)
    assert sink.sent == 1 and reports == []


def test_no_client_and_invalid_estimates_are_skipped_and_reported_once():
    reports = []
    with IgtlSink(default_catheter(), np.eye(3), np.zeros(3), port=0, report=reports.append) as sink:
        frame = type("F", (), {"q": np.array([0.0, 0.5, 0.5])})()
        for k in range(3):
            sink.handle(frame, None, Estimate(k, 0.1, 0.01, 0.0), 0.001)
        sink.handle(frame, None, Estimate(4.0, np.nan, np.nan, 0.0, Flag.NO_MEASUREMENT), 0.0)
        assert sink.skipped_no_client == 3 and sink.skipped_invalid == 1 and sink.sent == 0
    assert len(reports) == 1 and "not connected" in reports[0] and str(sink.port) in reports[0]


def test_port_in_use_is_one_clear_error():
    with IgtlSink(default_catheter(), np.eye(3), np.zeros(3), port=0) as first:
        with pytest.raises(OSError, match=f"127.0.0.1:{first.port}"):
            IgtlSink(default_catheter(), np.eye(3), np.zeros(3), port=first.port)


def test_device_names_are_checked():
    with pytest.raises(ValueError, match="20 bytes"):
        IgtlSink(default_catheter(), np.eye(3), np.zeros(3), port=0, tip_name="x" * 21)


def test_a_client_that_leaves_is_replaced_by_the_next(client_factory):
    catheter = default_catheter()
    frame = type("F", (), {"q": np.array([0.0, 0.5, 0.5])})()
    with IgtlSink(catheter, np.eye(3), np.zeros(3), port=0) as sink:
        first = client_factory(sink.port)
        assert sink.wait_for_client(WAIT_S)
        sink.handle(frame, None, Estimate(0.0, 0.1, 0.01, 0.0), 0.0)
        assert first.wait_for_message("CathTip", timeout=WAIT_S) is not None
        first.stop()
        second = client_factory(sink.port)
        # The server notices the first client is gone, then serves the second.
        for _ in range(int(WAIT_S / 0.05)):
            if sink._server.clients >= 2 and sink.connected:
                break
            second.wait_for_message("none", timeout=0.05)
        assert sink._server.clients == 2 and sink.connected
        sink.handle(frame, None, Estimate(1.0, 0.2, 0.01, 0.0), 0.0)
        message = second.wait_for_message("BendingPlane", timeout=WAIT_S)
    assert message is not None
    np.testing.assert_allclose(message.matrix[:3, :3], rot_z(0.2), atol=1e-6)


def test_the_live_loop_streams_transforms(client_factory):
    session = simulated_session(duration_s=3.0, frame_rate_hz=20.0, noise=0.2, seed=3)
    scene = session.scene
    memory = MemorySink()
    sink = IgtlSink(scene.catheter, scene.R_w_b, scene.o_b_w_mm, port=0)
    client = client_factory(sink.port)
    assert sink.wait_for_client(WAIT_S)
    summary = run_live(
        SimulatedSource(session.frames, speed=None),
        Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        make_estimator("ukf", scene.catheter),
        [sink, memory],
        handle_signals=False,
    )
    assert summary.frames_processed == len(session.frames) and not summary.sink_failures
    assert sink.sent == summary.frames_valid > 0
    # close() flushed the queue: the client ends up with the last frame's transform.
    last = memory.results[-1]
    expected = tip_transform_w(
        scene.catheter, last.frame.q, last.estimate.delta_L_rad, scene.R_w_b, scene.o_b_w_mm
    )
    received = None
    for _ in range(100):  # the client thread may still be reading earlier messages
        message = client.wait_for_message("CathTip", timeout=WAIT_S / 100)
        received = message.matrix if message is not None else received
        if received is not None and np.allclose(received, expected, atol=1e-4):
            break
    np.testing.assert_allclose(received, expected, atol=1e-4)
