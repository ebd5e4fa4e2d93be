"""``cathtrack demo`` and ``cathtrack track`` end to end, through ``main``, on loopback.

The ``.rrd`` files are read back with rerun's own reader (``rerun.chunk.RrdReader``).
"""

from __future__ import annotations

import os
import random
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from models.model_file import DEFAULT_MODEL_PATH
from models.pose import Pose
from models.rig_file import rig_toml
from models.rotations import wrap_angle
from replay.cli import main
from replay.simulation.sources import session_joints, simulated_session
from tracker.io.datagrams import decode_estimate, encode_joints, encode_markers
from tracker.io.recording import RecordingWriter, open_recording
from tracker.live.sinks import CSV_COLUMNS
from tracker.viewer import layout
from tracker.vision.parallel import parallel_possible

REPO = Path(__file__).resolve().parents[2]
LOOPBACK = "127.0.0.1"


def entity_rows(path) -> dict[str, int]:
    """Rows per entity path of the first recording in an .rrd (a file without its footer,
    i.e. not closed properly, fails in ``store()``)."""
    reader = RrdReader(path)
    reader.store()
    rows: dict[str, int] = {}
    for chunk in reader.stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


_PORTS = random.Random(os.getpid())


def free_port(kind=socket.SOCK_DGRAM) -> int:
    """A loopback port free now, below the ephemeral range: a socket bound to port 0 (the
    command's own sender, the controller) can never be handed it before the command binds
    it."""
    for _ in range(1000):
        port = _PORTS.randrange(20000, 32000)
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind((LOOPBACK, port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free loopback port below the ephemeral range")


def table_value(out: str, label: str) -> str:
    """The value cell of the row of the printed table that starts with ``label``."""
    match = re.search(rf"^\| {re.escape(label)} \| (.*) \|$", out, re.MULTILINE)
    assert match, f"no row {label!r} in:\n{out}"
    return match.group(1)


class Controller:
    """Receives estimate datagrams on a loopback port."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOPBACK, 0))
        self.sock.setblocking(False)

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def estimates(self):
        out = []
        while True:
            try:
                out.append(decode_estimate(self.sock.recv(256)))
            except BlockingIOError:
                return out

    def close(self):
        self.sock.close()


# ------------------------------------------------------------------------------- demo
def test_demo_tracks_rendered_images_live_and_writes_a_readable_rrd(tmp_path, capsys):
    rrd = tmp_path / "demo.rrd"
    assert main(["demo", "--seconds", "2", "--save", str(rrd)]) == 0
    out = capsys.readouterr().out
    frames = 40
    # Every pair is processed or counted as dropped (a busy machine may drop a few: the loop
    # takes the newest pair), and every estimate reaches the controller.
    processed, dropped, _ = (
        int(x) for x in table_value(out, "frames processed / dropped / predict-only").split(" / ")
    )
    assert processed + dropped == frames and processed >= frames // 2
    assert int(table_value(out, "pairs dropped for a newer one (loop busy)")) == dropped
    received = table_value(out, "estimates received by the controller")
    assert received.startswith(f"{processed} of {processed} sent")
    viewer_dropped = int(table_value(out, "rerun: frames dropped / waits (behind)").split(" / ")[0])
    logged = processed - viewer_dropped
    rows = entity_rows(rrd)
    for path in (
        layout.CATHETER_ESTIMATE,
        layout.CATHETER_TRUTH,
        layout.PLANE_FAN,
        layout.MARKERS_3D,
        f"{layout.camera_path('front')}/segmented",
        f"{layout.camera_path('side')}/reprojected",
        layout.delta_L_path("ukf"),
        layout.band_path("ukf", "plus"),
        layout.DELTA_L_TRUTH,
        layout.error_path("ukf"),
        layout.LATENCY_ESTIMATE,
        layout.FRAMES_DROPPED,
    ):
        assert rows.get(f"/{path}", 0) >= logged - 1, path
    assert rows.get(f"/{layout.nis_path('ukf')}", 0) >= logged - 3  # where the NIS is finite
    for view in ("front", "side"):
        assert rows.get(f"/{layout.image_path(view)}", 0) >= logged // 2 - 1  # every second
    assert rows.get(f"/{layout.delta_L_path('tip-position')}", 0) > logged // 2  # where valid
    assert len(RrdReader(rrd).blueprints()) == 1  # the default blueprint went with the data
    # The table: every method, the loop, the file.
    for method in ("ukf (live, sent)", "tip-position (same observations)"):
        cells = table_value(out, method).split(" | ")
        assert len(cells) == 5 and float(cells[0]) < 5.0, cells  # RMS error, deg
    p50, p99 = table_value(out, "latency image -> estimate sent, p50 / p99 (ms)").split(" / ")
    assert 0 < float(p50) <= float(p99)
    thirds = table_value(out, "latency p50 in each third of the run (ms)").split(" / ")
    assert len(thirds) == 3 and all(0 < float(ms) <= float(p99) for ms in thirds), thirds
    assert int(table_value(out, "image pairs rendered too late for real time")) >= 0
    # Kept awake where this process may write the PM QoS file, said either way.
    permitted = os.access("/dev/cpu_dma_latency", os.W_OK)
    assert table_value(out, "processors kept awake between frames").startswith(
        "yes" if permitted else "no"
    )
    assert str(rrd) in table_value(out, "rerun recording")
    # The views side by side wherever this process may use two processors.
    if parallel_possible():
        assert table_value(out, "views segmented side by side (a worker process)").startswith("yes")


def test_no_segmentation_worker_keeps_every_view_in_the_loops_process(
    tmp_path, capsys, monkeypatch
):
    import replay.demo
    from tracker.vision import parallel

    asked = []

    def recorded(*args, **kwargs):
        asked.append(kwargs["parallel"])
        return parallel.pair_segmenter(*args, **kwargs)

    monkeypatch.setattr(replay.demo, "pair_segmenter", recorded)
    rrd = tmp_path / "demo.rrd"
    argv = ["demo", "--seconds", "1", "--no-images", "--no-segmentation-worker", "--save", str(rrd)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert asked == [False]
    assert "views segmented side by side" not in out
    processed = int(table_value(out, "frames processed / dropped / predict-only").split(" / ")[0])
    assert processed >= 10


def test_the_demo_goes_on_when_the_segmentation_worker_dies_mid_session(tmp_path, monkeypatch):
    """Killed after the tenth frame: one line says so, every later frame is segmented in the
    loop's process, every pair is estimated and the summary tells."""
    import argparse

    import replay.demo
    from replay.demo import DemoSettings, run_demo
    from tracker.viewer.output import add_rerun_args
    from tracker.vision.parallel import ParallelPairSegmenter

    made = []

    def segmenter_that_dies(*args, parallel=None, **kwargs):  # noqa: ARG001 (always one)
        segmenter = ParallelPairSegmenter(*args, **kwargs)
        segment = segmenter.segment

        def segment_then_die(*a, **k):
            result = segment(*a, **k)
            if segmenter.frames == 10:
                os.kill(segmenter._process.pid, signal.SIGKILL)
            return result

        segmenter.segment = segment_then_die
        made.append(segmenter)
        return segmenter

    monkeypatch.setattr(replay.demo, "pair_segmenter", segmenter_that_dies)
    parser = argparse.ArgumentParser()
    add_rerun_args(parser, save_default=str(tmp_path / "demo.rrd"))
    lines, results = [], []
    code = run_demo(
        DemoSettings(seconds=2.0, images=False),
        parser.parse_args([]),
        out=lambda line: None,
        report=lines.append,
        on_result=results.append,
    )
    assert code == 0 and len(made) == 1
    summary = results[0].summary
    worker_lines = [line for line in lines if "segmentation worker stopped" in line]
    assert len(worker_lines) == 1 and "exit code -9" in worker_lines[0], lines
    assert summary.segmentation_worker.startswith("no (the segmentation worker stopped")
    assert summary.frames_processed + summary.frames_dropped == 40
    assert summary.frames_processed >= 30 and summary.frames_rejected == 0
    assert results[0].estimates_received == results[0].estimates_sent == summary.frames_processed
    assert results[0].scores["ukf"].row()["rms_deg"] < 5.0


# ------------------------------------------------------------------------------ track
@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 3 s recording of a simulated session (markers in mm) and its rig file."""
    folder = tmp_path_factory.mktemp("recorded")
    session = simulated_session(duration_s=3.0, frame_rate_hz=20.0, noise=0.3, seed=1)
    scene = session.scene
    rig = rig_toml(scene.rig, Pose(scene.R_w_b, scene.o_b_w_mm))
    path = folder / "session.mcap"
    with RecordingWriter(
        path, model_toml=DEFAULT_MODEL_PATH.read_text(), rig_toml=rig, point_unit="mm"
    ) as writer:
        for frame in session.frames:
            writer.write_joints(frame.time_s, frame.q, frame.q_dot)
            writer.write_frame(frame)
    (folder / "rig.toml").write_text(rig)
    return session, path, folder / "rig.toml"


def test_track_plays_a_recording_to_every_output_and_skips_a_missing_viewer(
    recorded, tmp_path, capsys
):
    session, path, _ = recorded
    controller = Controller()
    rrd, mcap, csv = tmp_path / "track.rrd", tmp_path / "track.mcap", tmp_path / "track.csv"
    viewer_url = f"rerun+http://{LOOPBACK}:{free_port(socket.SOCK_STREAM)}/proxy"
    try:
        code = main(
            [
                "track",
                "--recording", str(path),
                "--speed", "0",
                "--estimate-to", f"{LOOPBACK}:{controller.port}",
                "--igtl-port", "0",
                "--record", str(mcap),
                "--csv", str(csv),
                "--save", str(rrd),
                "--connect", "--url", viewer_url,
            ]
        )  # fmt: skip
        received = controller.estimates()
    finally:
        controller.close()
    captured = capsys.readouterr()
    assert code == 0, captured.err
    n = len(session.frames)
    assert f"{n} of {n} frames processed, {n} with an estimate" in captured.out
    assert "(source exhausted)" in captured.out
    # The viewer that is not running: one line, and the run went on.
    assert captured.err.count("no rerun viewer") == 1 and viewer_url in captured.err
    assert "Traceback" not in captured.err
    assert [m.sequence for m in received] == list(range(n)) and all(m.valid for m in received)
    np.testing.assert_allclose([m.time_s for m in received], [f.time_s for f in session.frames])
    rows = entity_rows(rrd)
    for entity in ("/world/catheter/estimate", "/views/front/segmented", "/series/error/ukf"):
        assert rows.get(entity, 0) >= n - 1, entity
    with open_recording(mcap) as recording:
        assert len(recording) == n
        assert len(recording.estimates["ukf"]) == n
    lines = csv.read_text().splitlines()
    assert lines[0].split(",") == list(CSV_COLUMNS) and len(lines) == n + 1


@pytest.mark.parametrize("flag, pinned", [((), True), (("--no-pin",), False)])
def test_track_pins_the_loop_thread_unless_told_not_to(recorded, flag, pinned):
    """``--no-pin`` leaves the loop's thread to the scheduler: the setting reaches the
    session's loop."""
    from replay.cli import build_parser
    from replay.commands.track import _session_settings
    from tracker.live.session import LiveSession

    session, path, _ = recorded
    args = build_parser().parse_args(["track", "--recording", str(path), *flag])
    settings = _session_settings(args, "recording")
    assert settings.pin is pinned
    with LiveSession(settings, session.scene) as live:
        assert (live.tracker.affinity is not None) is pinned
        live.tracker.close()


def test_track_takes_markers_and_joints_over_udp(recorded, capsys):
    session, _, rig = recorded
    frames = session.frames[:20]  # 1 s: the joint history (2 s at 1 kHz) holds it all
    markers_port, joints_port = free_port(), free_port()
    controller = Controller()
    argv = [
        "track",
        "--markers-port", str(markers_port),
        "--joints-port", str(joints_port),
        "--joint-clock", "sender",
        "--rig", str(rig),
        "--rig-model", "orthographic",
        "--estimate-to", f"{LOOPBACK}:{controller.port}",
        "--max-frames", str(len(frames)),
        "--idle-timeout", "20",
    ]  # fmt: skip
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault("code", main(argv)))
    thread.start()
    try:
        deadline = time.monotonic() + 20.0
        while not all(port_in_use(p) for p in (markers_port, joints_port)):
            assert thread.is_alive() and time.monotonic() < deadline, "track did not listen"
            thread.join(0.01)  # let it start
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as robot:
            # 100 Hz up to 1 s, in one burst: it fits the default socket buffer (1 kHz live
            # streaming is tested in test_live.py).
            for k in range(101):
                t = k / 100
                robot.sendto(encode_joints(k, t, *session_joints(t)), (LOOPBACK, joints_port))
            for k, frame in enumerate(frames):
                data = encode_markers(k, frame.time_s, frame.uv, (0.3, 0.3))
                robot.sendto(data, (LOOPBACK, markers_port))
        thread.join(30.0)
        assert not thread.is_alive()
        received = controller.estimates()
    finally:
        controller.close()
    out = capsys.readouterr().out
    assert result["code"] == 0
    assert "(max frames)" in out and f"{len(frames)} of {len(frames)} frames processed" in out
    assert "markers on udp://127.0.0.1:" in out
    assert "without joints (predict only, not valid): 0 frames" in out
    assert len(received) == len(frames) and all(m.status == 0 for m in received)
    errors = wrap_angle(
        np.array([m.delta_L_rad for m in received[5:]])
        - np.array([f.delta_L_true_rad for f in frames[5:]])
    )
    assert np.degrees(np.max(np.abs(errors))) < 10.0
    assert not port_in_use(markers_port) and not port_in_use(joints_port)  # released


def port_in_use(port: int) -> bool:
    """Whether a UDP socket is bound to ``port``: read from the system's table where there
    is one (Linux), so that the check never holds the port itself (a probe that binds it
    took it from the command starting meanwhile, once: "Address already in use"); elsewhere
    by trying to bind it."""
    table = Path("/proc/net/udp")
    if table.exists():
        rows = table.read_text().splitlines()[1:]
        return any(int(row.split()[1].rsplit(":", 1)[1], 16) == port for row in rows)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind((LOOPBACK, port))
        except OSError:
            return True
        return False


def test_track_errors_a_user_can_cause_are_one_line(recorded, capsys):
    _, path, rig = recorded
    assert main(["track", "--rig", str(rig)]) == 2
    assert main(["track", "--recording", str(path), "--markers-port", "1"]) == 2
    assert main(["track", "--markers-port", str(free_port())]) == 2  # no rig
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("cathtrack track: error: ") for line in err)
    assert "give one source of frames" in err[0] and "(got recording, markers)" in err[1]
    assert "--rig FILE" in err[2]


@pytest.mark.parametrize("source", ["recording", "silent markers"])
def test_ctrl_c_stops_track_prints_the_summary_and_closes_the_files(recorded, tmp_path, source):
    """Ctrl-C as soon as track runs: with a recording played back it may come before the
    first frame or after some; with a marker port that nothing sends to, always before the
    first frame and the first joint sample. Either way the files are complete."""
    _, path, rig = recorded
    rrd, mcap = tmp_path / "live.rrd", tmp_path / "live.mcap"
    if source == "recording":
        frames = ["--recording", str(path), "--speed", "0.5"]
    else:
        # Port 0: the command binds ports the system picks as it binds them, free then
        # (a port chosen here may be taken before the command starts: "Address already in
        # use" once, in a full run); nothing knows them, so nothing comes.
        frames = [
            "--markers-port", "0", "--joints-port", "0",
            "--rig", str(rig), "--rig-model", "orthographic",
        ]  # fmt: skip
    command = [
        sys.executable, "-m", "replay.cli", "track", *frames,
        "--estimate-to", "off", "--save", str(rrd), "--record", str(mcap),
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO, env=env
    )
    try:
        # Raw reads: a buffered readline could hold the line while select waits for more.
        deadline = time.monotonic() + 60.0
        head = b""
        while b"Ctrl-C to stop" not in head:
            remaining = deadline - time.monotonic()
            assert remaining > 0 and process.poll() is None, process.stderr.read()
            ready, _, _ = select.select([process.stdout], [], [], remaining)
            if ready:
                head += os.read(process.stdout.fileno(), 65536)
        process.send_signal(signal.SIGINT)
        stdout, stderr = (text.decode() for text in process.communicate(timeout=60.0))
        stdout = head.decode() + stdout
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 130, stderr
    assert "live loop ended (interrupted)" in stdout and "Traceback" not in stderr
    RrdReader(rrd).store()  # the .rrd has its footer
    # Whenever the Ctrl-C came (before the first frame or after some), the recording opens,
    # undamaged, with every frame the loop processed.
    processed = int(re.search(r"(\d+) of \d+ frames processed", stdout).group(1))
    with open_recording(mcap) as recording:
        assert not recording.report.damage and len(recording) == processed
        if processed:
            assert recording.report.ok, recording.report.warnings
        else:
            assert len(recording.report.warnings) == 1
            assert "no frames" in recording.report.warnings[0]
    if source == "silent markers":
        assert processed == 0
