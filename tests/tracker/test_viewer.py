"""tracker.viewer.sink: the +/-2 sigma fan, the default blueprint, closing a stream, rerun outputs.

Recordings are read back with rerun's own reader (``rerun.chunk.RrdReader``), not a mock.
"""

from __future__ import annotations

import argparse
import socket

import numpy as np
import pytest
from rerun.chunk import RrdReader

from models.catheter import default_catheter
from models.rotations import rot_z, wrap_angle
from tracker.viewer.sink import (
    PLANE_FAN,
    LiveViewerSink,
    RerunSink,
    ViewerWatch,
    add_rerun_args,
    default_blueprint,
    file_stream,
    open_rerun_output,
    parse_viewer_url,
    plane_fan_w,
    viewer_reachable,
)


def entity_rows(path) -> dict[str, int]:
    """Rows per entity path of the first recording in an .rrd."""
    rows: dict[str, int] = {}
    for chunk in RrdReader(path).stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def blueprint_views(path) -> dict[str, str]:
    """Space origin -> view class of every view in the .rrd's blueprint."""
    reader = RrdReader(path)
    (blueprint,) = reader.blueprints()
    views = {}
    for chunk in reader.stream(store=blueprint):
        batch = chunk.to_record_batch()
        if "ViewBlueprint:space_origin" in batch.schema.names:
            origin = batch.column("ViewBlueprint:space_origin").to_pylist()[0][0]
            kind = batch.column("ViewBlueprint:class_identifier").to_pylist()[0][0]
            views[origin] = kind
    return views


def closed_port() -> int:
    """A loopback TCP port that nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rerun_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_rerun_args(parser)
    return parser.parse_args(argv)


# ------------------------------------------------------------------------------- the fan
@pytest.mark.parametrize("delta_2_rad", [0.0, np.pi / 2])
def test_plane_fan_spans_two_sigma_about_the_tip_direction(delta_2_rad):
    catheter = default_catheter(delta_2_rad)
    q, delta_L, std = np.array([0.4, 0.7, 0.5]), 2.1, 0.05
    R_w_b = rot_z(0.3) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    o_b_w = np.array([3.0, -2.0, 10.0])
    vertices_w, triangles = plane_fan_w(catheter, q, delta_L, std, R_w_b, o_b_w, segments=20)
    assert vertices_w.shape == (22, 3) and triangles.shape == (20, 3)
    assert np.all(triangles[:, 0] == 0) and np.all(triangles[:, 2] == triangles[:, 1] + 1)
    vertices_b = (vertices_w - o_b_w) @ R_w_b  # back into the base frame
    np.testing.assert_allclose(vertices_b[0], 0.0, atol=1e-12)  # apex at the base origin
    rim = vertices_b[1:]
    tip_b = catheter.tip(q, delta_L)
    np.testing.assert_allclose(rim[:, 2], tip_b[2])  # at the tip's height
    radius = np.hypot(rim[:, 0], rim[:, 1])
    expected = max(np.hypot(tip_b[0], tip_b[1]), 0.25 * catheter.length_mm)
    np.testing.assert_allclose(radius, expected)
    # The middle of the rim is the tip's direction; the ends are delta_L -/+ 2 sigma's tips.
    angle = np.arctan2(rim[:, 1], rim[:, 0])
    for k, offset in ((0, -2 * std), (10, 0.0), (20, 2 * std)):
        tip_k = catheter.tip(q, delta_L + offset)
        assert abs(wrap_angle(angle[k] - np.arctan2(tip_k[1], tip_k[0]))) < 1e-9


def test_plane_fan_is_a_whole_turn_when_the_plane_is_unknown():
    catheter = default_catheter()
    vertices_w, _ = plane_fan_w(catheter, [0.0, 0.0, 0.0], 0.0, np.inf, np.eye(3), np.zeros(3))
    angle = np.unwrap(np.arctan2(vertices_w[1:, 1], vertices_w[1:, 0]))
    assert angle[-1] - angle[0] == pytest.approx(2 * np.pi)
    # A straight catheter: the rim keeps a visible radius.
    assert np.allclose(np.hypot(vertices_w[1:, 0], vertices_w[1:, 1]), 0.25 * catheter.length_mm)


# -------------------------------------------------------------------------- the blueprint
def test_the_live_blueprint_shows_the_scene_both_cameras_and_every_series(tmp_path):
    path = tmp_path / "blueprint.rrd"
    stream = file_stream(path, blueprint=default_blueprint(["ukf"], live=True))
    stream.flush()
    stream.disconnect()
    assert blueprint_views(path) == {
        "world": "3D",
        "world/cameras/front": "2D",
        "world/cameras/side": "2D",
        "series/delta_L": "TimeSeries",
        "series/error": "TimeSeries",
        "series/nis": "TimeSeries",
        "series/latency_ms": "TimeSeries",
        "series/frames": "TimeSeries",
    }


# ---------------------------------------------------------------------- a session logged
@pytest.fixture(scope="module")
def session():
    from replay.simulation.sources import simulated_session

    return simulated_session(duration_s=1.0, frame_rate_hz=20.0, noise=0.3, seed=3)


def test_live_viewer_sink_logs_the_loop_and_close_completes_the_rrd(session, tmp_path):
    from tracker.estimators import make_estimator
    from tracker.live.loop import run_live
    from tracker.reconstruction import Reconstructor

    scene = session.scene
    path = tmp_path / "live.rrd"
    viewer = RerunSink(file_stream(path, blueprint=default_blueprint(["ukf"], False, live=True)))
    sink = LiveViewerSink(viewer, scene, "ukf")
    summary = run_live(
        session.frames,
        Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        make_estimator("ukf", scene.catheter),
        [sink],
        handle_signals=False,
    )
    assert summary.frames_processed == len(session.frames) == 20 and not summary.sink_failures
    RrdReader(path).store()  # only a file with its footer (closed properly) opens as a store
    rows = entity_rows(path)
    for entity in (
        "/world/catheter/estimate",
        f"/{PLANE_FAN}",
        "/views/front/segmented",
        "/views/side/reprojected",
        "/series/delta_L/ukf",
        "/series/delta_L/ukf_plus2sigma",
        "/series/error/ukf",
        "/series/nis/ukf",
        "/series/latency_ms/estimate",
        "/series/frames/predict_only",
    ):
        assert rows.get(entity, 0) >= 19, entity  # every frame (+ a static style row)
    assert viewer.close()  # closing again does nothing


# ------------------------------------------------------------------- outputs and faults
def test_a_viewer_that_is_not_running_is_reported_once_and_skipped(tmp_path):
    url = f"rerun+http://127.0.0.1:{closed_port()}/proxy"
    reports: list[str] = []
    assert open_rerun_output(rerun_args(["--connect", "--url", url]), report=reports.append) is None
    assert len(reports) == 1 and url in reports[0] and "going on without it" in reports[0]
    # Next to a file, the file is still written.
    path = tmp_path / "sub" / "out.rrd"
    reports.clear()
    output = open_rerun_output(
        rerun_args(["--url", url, "--save", str(path)]), report=reports.append
    )
    assert output.targets == [f"file {path}"] and output.viewer_url is None
    assert output.watch() is None and len(reports) == 1
    RerunSink(output.stream).close()
    RrdReader(path).store()


def test_no_rerun_flag_means_no_rerun_output_and_stdout_is_refused():
    assert open_rerun_output(rerun_args([])) is None
    with pytest.raises(ValueError, match="--stdout"):
        open_rerun_output(rerun_args(["--stdout"]))


def test_viewer_urls_are_checked():
    assert parse_viewer_url("rerun+http://10.0.0.2:9877/proxy") == ("10.0.0.2", 9877)
    with pytest.raises(ValueError, match="not a rerun viewer URL"):
        parse_viewer_url("http://127.0.0.1:9876")
    assert viewer_reachable(f"rerun+http://127.0.0.1:{closed_port()}/proxy")[0] is False


def test_a_viewer_that_goes_away_is_reported_once_and_its_return_too(session, tmp_path):
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    url = f"rerun+http://127.0.0.1:{listener.getsockname()[1]}/proxy"
    watch = ViewerWatch(url)  # checked by hand here, not by its thread
    reports: list[str] = []
    viewer = RerunSink(file_stream(tmp_path / "watch.rrd"))
    sink = LiveViewerSink(viewer, session.scene, "ukf", watch=watch, report=reports.append)
    frames = iter(session.frames)

    def step():
        from tracker.types import Estimate

        frame = next(frames)
        sink.handle(frame, None, Estimate(frame.time_s, 2.0, 0.1, float(frame.q[0])), 0.004)

    assert watch.check()
    step()
    listener.close()
    assert not watch.check()
    step()
    step()
    assert len(reports) == 1 and "is gone" in reports[0]
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", parse_viewer_url(url)[1]))
    listener.listen()
    assert watch.check()
    step()
    assert len(reports) == 2 and "is back" in reports[1]
    listener.close()
    sink.close()
    assert sink.frames == 4


def test_a_running_viewer_is_connected_to_and_gets_everything(session):
    import rerun as rr

    port = closed_port()
    server = rr.RecordingStream("stand-in-viewer")  # a gRPC server, as a viewer hosts one
    server.set_sinks(rr.GrpcServerSink(bind_ip="127.0.0.1", port=port))
    try:
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        reports: list[str] = []
        output = open_rerun_output(rerun_args(["--connect", "--url", url]), report=reports.append)
        assert output.targets == [f"viewer {url}"] and output.viewer_url == url and not reports
        viewer = RerunSink(output.stream)
        for frame in session.frames[:5]:
            viewer.log_frame(frame, None, {}, session.scene)
        assert viewer.close(timeout_s=10.0)  # flushed to the server
    finally:
        server.disconnect()
