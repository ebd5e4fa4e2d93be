"""tracker.viewer: the +/-2 sigma fan, the default blueprint, the sinks, the rerun outputs.

Recordings are read back with rerun's own reader (``rerun.chunk.RrdReader``), not a mock.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import socket
import time
from types import SimpleNamespace

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader
from scipy.stats import chi2

from models.catheter import default_catheter
from models.model_file import DEFAULT_MODEL_PATH
from models.pose import Pose
from models.rig_file import rig_toml
from models.rotations import rot_z, wrap_angle
from replay.cli import main
from replay.evaluation.outputs import scene_frames
from replay.simulation.render import default_render_rig
from replay.simulation.simulator import default_scene
from replay.simulation.sources import simulated_session
from tracker.estimators import estimator_names, make_estimator
from tracker.io.recording import RecordingWriter
from tracker.live.loop import run_live
from tracker.live.sinks import LiveStatus
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Flag
from tracker.viewer.layout import (
    BENDING_PLANE,
    DELTA_L_TRUTH,
    PLANE_FAN,
    SIDES,
    TRUTH_COLOR,
    band_path,
    default_blueprint,
    delta_L_path,
    dial_path,
    error_band_path,
    error_path,
    method_color,
    nis_band_path,
    nis_path,
    plane_fan_w,
)
from tracker.viewer.output import (
    ViewerWatch,
    WebViewer,
    add_rerun_args,
    file_stream,
    open_rerun_output,
    parse_viewer_url,
    reachable_host,
    viewer_reachable,
    web_viewer_url,
)
from tracker.viewer.sink import LiveViewerSink, RerunSink


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


def view_property(path, origin: str, archetype: str) -> dict:
    """Field -> value of one archetype of the blueprint's view with this space origin."""
    reader = RrdReader(path)
    (blueprint,) = reader.blueprints()
    chunks = [chunk.to_record_batch() for chunk in reader.stream(store=blueprint)]
    paths = [chunk.entity_path for chunk in reader.stream(store=blueprint)]
    (view,) = [
        entity
        for entity, batch in zip(paths, chunks, strict=True)
        if "ViewBlueprint:space_origin" in batch.schema.names
        and batch.column("ViewBlueprint:space_origin").to_pylist()[0][0] == origin
    ]
    fields = {}
    for entity, batch in zip(paths, chunks, strict=True):
        if entity == f"{view}/{archetype}":
            for name in batch.schema.names:
                if name.startswith(f"{archetype}:"):
                    value = batch.column(name).to_pylist()[0]
                    fields[name.split(":", 1)[1]] = value[0] if len(value) == 1 else value
    return fields


def columns(path, entity: str, column: str) -> list:
    """Every row's value of one column of an entity (static rows first), across chunks."""
    values = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity:
            batch = chunk.to_record_batch()
            if column in batch.schema.names:
                values += batch.column(column).to_pylist()
    return values


def series(path, entity: str) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and values of a scalar series, in time order."""
    t, v = [], []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            if "Scalars:scalars" in batch.schema.names:
                t += [x.value / 1e9 for x in batch.column("time")]
                v += [row[0] for row in batch.column("Scalars:scalars").to_pylist()]
    order = np.argsort(t, kind="stable")
    return np.asarray(t)[order], np.asarray(v, dtype=float)[order]


def rgb(packed: int) -> tuple[int, int, int]:
    """rerun's packed 0xRRGGBBAA colour -> (r, g, b)."""
    return (packed >> 24 & 255, packed >> 16 & 255, packed >> 8 & 255)


def colors(path, entity: str, column: str) -> set[tuple[int, int, int]]:
    return {rgb(c) for row in columns(path, entity, column) for c in (row or [])}


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
@pytest.fixture(scope="module")
def camera_scene():
    return default_scene(default_catheter(), default_render_rig())


def test_the_live_blueprint_shows_the_scene_the_views_the_dial_and_every_series(
    tmp_path, camera_scene
):
    path = tmp_path / "blueprint.rrd"
    stream = file_stream(path, blueprint=default_blueprint(["ukf"], live=True, scene=camera_scene))
    stream.flush()
    stream.disconnect()
    assert blueprint_views(path) == {
        "world": "3D",
        **{f"world/cameras/{name}": "2D" for name in camera_scene.rig.names},
        "dial": "2D",
        "series/delta_L": "TimeSeries",
        "series/error": "TimeSeries",
        "series/nis": "TimeSeries",
        "series/latency_ms": "TimeSeries",
        "series/frames": "TimeSeries",
    }


def test_the_3d_view_is_framed_on_the_catheter_not_on_the_cameras(tmp_path, camera_scene):
    path = tmp_path / "blueprint.rrd"
    stream = file_stream(path, blueprint=default_blueprint(["ukf"], scene=camera_scene))
    stream.flush()
    stream.disconnect()
    eye = view_property(path, "world", "EyeControls3D")
    length = camera_scene.catheter.length_mm
    base = np.asarray(camera_scene.o_b_w_mm)
    target, position = np.array(eye["look_target"]), np.array(eye["position"])
    # It looks at the catheter's reach from a catheter length or two away; the cameras are
    # 400 mm from the base.
    assert np.linalg.norm(target - base) < length
    assert length / 2 < np.linalg.norm(position - target) < 2 * length
    np.testing.assert_allclose(eye["eye_up"], np.asarray(camera_scene.R_w_b)[:, 2])
    queries = view_property(path, "world", "ViewContents")["query"]
    assert "- world/cameras/**" in queries  # the cameras are left out of the 3-D view


# ---------------------------------------------------------------------- a session logged
@pytest.fixture(scope="module")
def session():
    return simulated_session(duration_s=1.0, frame_rate_hz=20.0, noise=0.3, seed=3)


def test_live_viewer_sink_logs_the_loop_and_close_completes_the_rrd(session, tmp_path):
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


class _CountingStream:
    """A rerun stream's flush, counted (the rest of the stream is the real one's)."""

    def __init__(self, stream):
        self.stream = stream
        self.flushes: list[float] = []

    def flush(self, *, timeout_sec: float = 1e38) -> None:
        self.flushes.append(timeout_sec)
        self.stream.flush(timeout_sec=timeout_sec)

    def __getattr__(self, name):
        return getattr(self.stream, name)


@pytest.mark.parametrize("every_s, expected", [(0.0, 20), (3600.0, 1)])
def test_the_live_viewer_sink_flushes_after_its_frames_without_waiting(
    session, tmp_path, every_s, expected
):
    scene = session.scene
    viewer = RerunSink(file_stream(tmp_path / "live.rrd"))
    counting = viewer.stream = _CountingStream(viewer.stream)
    sink = LiveViewerSink(viewer, scene, "ukf", flush_every_s=every_s)
    for frame in session.frames:
        sink.handle(frame, None, _estimate(frame.time_s), 0.002)
    assert counting.flushes == [0.0] * expected  # started, never waited for
    sink.close()
    RrdReader(tmp_path / "live.rrd").store()


def _estimate(time_s: float) -> Estimate:
    return Estimate(time_s=time_s, delta_L_rad=0.3, std_rad=0.05, q_r_rad=0.0, flags=Flag(0))


def test_a_long_flush_tick_leaves_the_flushes_to_the_caller(tmp_path):
    """With ``flush_tick_s`` the stream does not flush on its own clock (rerun's 0.2 s for a
    file): what is logged reaches the file when flushed, not before."""
    sizes = {}
    for tick in (None, 3600.0):
        path = tmp_path / f"tick-{tick}.rrd"
        output = open_rerun_output(rerun_args(["--save", str(path)]), flush_tick_s=tick)
        output.stream.flush()
        before = path.stat().st_size
        noise = np.random.default_rng(0).integers(0, 256, (256, 256), np.uint8)
        output.stream.log("image", rr.Image(noise))
        time.sleep(1.0)  # five of rerun's own ticks
        sizes[tick] = path.stat().st_size - before
        output.stream.flush()
        flushed = path.stat().st_size - before
        RerunSink(output.stream).close()
        assert flushed > 60_000  # the image, once flushed
        sizes[tick] = (sizes[tick], flushed)
    assert sizes[None][0] > 60_000  # rerun's own tick wrote it
    assert sizes[3600.0][0] < 1_000  # nothing until the flush


@pytest.fixture(scope="module")
def camera_session():
    """A 1 s session seen by the two 640x480 cameras (markers in px, no images)."""
    return simulated_session(
        duration_s=1.0, frame_rate_hz=20.0, noise=0.5, seed=3, rig=default_render_rig()
    )


def test_each_method_has_one_colour_in_every_view_series_and_legend(camera_session, tmp_path):
    scene = camera_session.scene
    path = tmp_path / "colours.rrd"
    viewer = RerunSink(file_stream(path), primary="ukf")
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    estimators = {m: make_estimator(m, scene.catheter) for m in ("ukf", "tip-position")}
    for frame in camera_session.frames:
        observation = reconstructor.observe(frame)
        estimates = {m: e.step(observation) for m, e in estimators.items()}
        viewer.log_frame(frame, observation, estimates, scene)
        for m, e in estimates.items():
            viewer.log_estimate(m, e, frame.delta_L_true_rad)
    assert viewer.close()
    for m in estimators:
        color = {method_color(m)}
        lines = [delta_L_path(m), error_path(m)]
        lines += [f(m, side) for f in (band_path, error_band_path) for side in SIDES]
        for entity in lines:
            assert colors(path, f"/{entity}", "SeriesLines:colors") == color, entity
            # The band is named after its method: the legend has one entry per method.
            assert columns(path, f"/{entity}", "SeriesLines:names") == [[m]], entity
        assert colors(path, f"/{nis_path(m)}", "SeriesPoints:colors") == color
        assert colors(path, f"/{dial_path(m)}", "LineStrips2D:colors") == color
    # The primary method draws the 3-D scene and the reprojected markers in its colour.
    ukf = {method_color("ukf")}
    assert colors(path, "/world/catheter/estimate", "LineStrips3D:colors") == ukf
    assert colors(path, f"/{PLANE_FAN}", "Mesh3D:albedo_factor") == ukf
    assert colors(path, f"/{BENDING_PLANE}", "Mesh3D:albedo_factor") == ukf
    for name in scene.rig.names:
        assert colors(path, f"/world/cameras/{name}/reprojected", "Points2D:colors") == ukf
    # The truth: one colour of its own, in 3-D, on the dial and in the plot.
    truth = {TRUTH_COLOR}
    assert colors(path, f"/{DELTA_L_TRUTH}", "SeriesLines:colors") == truth
    assert colors(path, "/world/catheter/truth", "Points3D:colors") == truth
    assert colors(path, "/dial/truth", "LineStrips2D:colors") == truth
    every = {method_color(m) for m in estimator_names()}
    assert len(every) == len(estimator_names()) and TRUTH_COLOR not in every
    assert method_color("recorded-ukf") not in every | truth


def crossing_estimates(n: int = 40) -> tuple[np.ndarray, list[Estimate]]:
    """A truth from 150 to 228 deg (wrapped: through +/-180) and estimates 0.5 deg off it,
    with NIS 6 of 6 degrees of freedom; the 21st has no estimate."""
    truth = np.radians(150.0 + 2.0 * np.arange(n))
    estimates = [
        Estimate(0.05 * k, float(wrap_angle(x + np.radians(0.5))), 0.02, 0.1, nis=6.0, nis_dof=6)
        for k, x in enumerate(truth)
    ]
    estimates[20] = Estimate(1.0, math.nan, math.nan, 0.1, Flag.NO_MEASUREMENT)
    return truth, estimates


@pytest.mark.parametrize("logged", ["frame by frame", "as columns"])
def test_delta_L_is_unwrapped_through_180_deg_with_gaps_and_nis_bands(tmp_path, logged):
    truth, estimates = crossing_estimates()
    wrapped = wrap_angle(truth)
    path = tmp_path / "unwrap.rrd"
    viewer = RerunSink(file_stream(path))
    if logged == "frame by frame":
        for estimate, x in zip(estimates, wrapped, strict=True):
            viewer.log_estimate("ukf", estimate, float(x))
    else:
        viewer.log_series("ukf", estimates, wrapped)
    assert viewer.close()
    _, truth_deg = series(path, f"/{DELTA_L_TRUTH}")
    np.testing.assert_allclose(truth_deg, np.degrees(truth))  # continuous, past 180
    t, value = series(path, f"/{delta_L_path('ukf')}")
    assert t.size == len(estimates) and np.isnan(value[20])  # a gap, not a line across it
    have = np.isfinite(value)
    np.testing.assert_allclose(value[have], np.degrees(truth[have]) + 0.5)
    _, plus = series(path, f"/{band_path('ukf', 'plus')}")
    np.testing.assert_allclose(plus[have] - value[have], np.degrees(0.04))
    _, error = series(path, f"/{error_path('ukf')}")
    np.testing.assert_allclose(error[have], 0.5)
    # NIS per degree of freedom, with the chi-square 95% band of 6 degrees of freedom.
    _, nis = series(path, f"/{nis_path('ukf')}")
    np.testing.assert_allclose(nis, 1.0)
    for side, p in (("low", 0.025), ("high", 0.975)):
        _, band = series(path, f"/{nis_band_path('ukf', side)}")
        np.testing.assert_allclose(band, chi2.ppf(p, 6) / 6)


def test_without_a_truth_delta_L_is_unwrapped_against_its_previous_value(tmp_path):
    truth, estimates = crossing_estimates()
    path = tmp_path / "alone.rrd"
    viewer = RerunSink(file_stream(path))
    viewer.log_series("tip-position", estimates)
    assert viewer.close()
    _, value = series(path, f"/{delta_L_path('tip-position')}")
    have = np.isfinite(value)
    assert np.all(np.abs(np.diff(value[have])) < 5.0) and value[have].max() > 200.0


def test_replay_scene_frames_are_the_frames_with_images(tmp_path):
    def replay(with_images):
        frames = [
            SimpleNamespace(frame=SimpleNamespace(images=() if k in with_images else None))
            for k in range(10)
        ]
        return SimpleNamespace(frames=frames)

    assert scene_frames(replay({0, 5}), frame_every=4) == [0, 5]
    assert scene_frames(replay(set()), frame_every=4) == [0, 4, 8]


@pytest.fixture(scope="module")
def recording_with_images(tmp_path_factory, camera_session):
    """A recording of the camera session with (flat) images and the UKF's estimates."""
    scene = camera_session.scene
    path = tmp_path_factory.mktemp("view") / "session.mcap"
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    ukf = make_estimator("ukf", scene.catheter)
    width, height = scene.rig.views[0].image_size
    image = np.full((height, width), 128, dtype=np.uint8)
    with RecordingWriter(
        path,
        model_toml=DEFAULT_MODEL_PATH.read_text(),
        rig_toml=rig_toml(scene.rig, Pose(scene.R_w_b, scene.o_b_w_mm)),
        point_unit="px",
    ) as writer:
        for frame in camera_session.frames:
            writer.write_joints(frame.time_s, frame.q, frame.q_dot)
            writer.write_frame(dataclasses.replace(frame, images=(image,) * len(frame.uv)))
            writer.write_estimate("ukf", ukf.step(reconstructor.observe(frame)))
    return path


def row_times(path, entity: str) -> list[float]:
    """Times (s) of an entity's non-static rows."""
    times = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            times += [x.value / 1e9 for x in chunk.to_record_batch().column("time")]
    return sorted(times)


def test_view_logs_a_recording_with_its_name_and_the_scene_on_the_same_frames(
    recording_with_images, camera_session, tmp_path, capsys
):
    rrd = tmp_path / "view.rrd"
    argv = ["view", str(recording_with_images), "--save", str(rrd), "--frame-every", "4"]
    code = main([*argv, "--methods", "tip-position", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    n = len(camera_session.frames)
    expected = pytest.approx([frame.time_s for frame in camera_session.frames[::4]])
    for name in camera_session.scene.rig.names:
        assert row_times(rrd, f"/world/cameras/{name}/image") == expected
        assert row_times(rrd, f"/world/cameras/{name}/segmented") == expected
    assert row_times(rrd, "/world/catheter/truth") == expected
    assert columns(rrd, "/__properties", "RecordingInfo:name") == [["session.mcap"]]
    for method in ("tip-position", "recorded-ukf"):
        assert len(row_times(rrd, f"/{delta_L_path(method)}")) == n
        assert colors(rrd, f"/{delta_L_path(method)}", "SeriesLines:colors") == {
            method_color(method)
        }
    assert len(row_times(rrd, "/series/joints/q_r_deg")) == n


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
        frame = next(frames)
        estimate = Estimate(frame.time_s, 2.0, 0.1, float(frame.q[0]))
        sink.handle(frame, None, estimate, 0.004, LiveStatus.NONE)

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


def test_the_web_viewer_url_names_the_host_a_browser_reaches():
    assert reachable_host("127.0.0.1") == "127.0.0.1"
    assert reachable_host("0.0.0.0") == socket.gethostname()
    assert reachable_host("10.1.2.3") == "10.1.2.3"
    url = web_viewer_url("127.0.0.1", 9090, "rerun+http://127.0.0.1:9876/proxy")
    assert url == "http://127.0.0.1:9090/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9876%2Fproxy"


def test_a_web_viewer_port_in_use_is_one_clear_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        viewer = WebViewer("127.0.0.1", port, "rerun+http://127.0.0.1:9876/proxy")
        with pytest.raises(OSError, match="--web-viewer-port"):
            viewer.start()


def test_a_command_without_listeners_of_its_own_gets_a_bind_option():
    parser = argparse.ArgumentParser()
    add_rerun_args(parser, bind_option=True)
    args = parser.parse_args(["--serve", "--bind", "0.0.0.0", "--web-viewer-port", "9191"])
    assert (args.serve, args.viewer_bind, args.web_viewer_port) == (True, "0.0.0.0", 9191)
    assert rerun_args([]).web_viewer_port == 9090 and not hasattr(rerun_args([]), "viewer_bind")
