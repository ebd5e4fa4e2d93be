"""Replay evaluation (replay.evaluation, ``cathtrack simulate`` / ``cathtrack evaluate``)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig
from replay import evaluation
from replay.cli import main
from replay.protocol import ProtocolSettings, build_protocol, simulate_protocol
from replay.simulation.render import default_render_rig
from replay.simulation.simulator import NoiseSettings, Scene, simulate_frames, sinusoidal
from tracker.io.recording import FrameLabels, ReadReport, RecordedFrame
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Frame

PAPER_METHODS = ["tip-position", "body-positions", "tip-velocity", "ukf"]


def _overall(path: Path) -> dict[str, dict]:
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["table"] == "overall"]
    return {r["method"]: r for r in rows}


def _check_paper_findings(overall: dict[str, dict]) -> None:
    rms = {m: float(r["rms_deg"]) for m, r in overall.items()}
    assert rms["tip-position"] <= 1.5 * rms[evaluation.BOUND_NAME], rms
    assert rms["ukf"] < rms["tip-position"], rms
    others = [
        v for m, v in rms.items() if not m.startswith("tip-velocity") and m != evaluation.BOUND_NAME
    ]
    assert rms["tip-velocity"] > max(others), rms


@pytest.fixture(scope="module")
def image_recording(tmp_path_factory) -> Path:
    """A reduced paper protocol with images: 3 planes, 6 configurations, 15 frames each."""
    path = tmp_path_factory.mktemp("images") / "paper_images.mcap"
    code = main(
        [
            "simulate",
            "--protocol",
            "paper",
            "--planes",
            "3",
            "--configs",
            "6",
            "--frames",
            "15",
            "--seed",
            "1",
            "--workers",
            "2",
            "--out",
            str(path),
            "--no-progress",
        ]
    )
    assert code == 0
    return path


def test_paper_protocol_from_images_end_to_end(image_recording, tmp_path, capsys):
    out = tmp_path / "eval"
    code = main(
        [
            "evaluate",
            str(image_recording),
            "--methods",
            *PAPER_METHODS,
            "--out",
            str(out),
            "--no-progress",
            "--rrd-frame-every",
            "5",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "| tip-position |" in printed and "markers segmented from the recorded images" in printed
    assert "## Per bending plane" in printed and "## Against tip deflection" in printed
    assert "## Against segmentation noise" in printed and "NEES" in printed
    for name in (
        "summary.md",
        "summary.csv",
        "frames.csv",
        "experiment.png",
        "conditions.png",
        "replay.rrd",
    ):
        assert (out / name).stat().st_size > 0, name
    _check_paper_findings(_overall(out / "summary.csv"))
    # the .rrd is a rerun recording with the replayed series and images
    from rerun.chunk import RrdReader

    paths = {chunk.entity_path for chunk in RrdReader(out / "replay.rrd").stream()}
    assert {
        "/series/delta_L/ukf",
        "/series/error/tip-position",
        "/world/catheter/estimate",
        "/world/cameras/front/image",
    } <= paths


def test_paper_protocol_markers_only_tables(tmp_path):
    """All 11 planes, fewer configurations: every table has its groups and the UKF is
    consistent."""
    settings = ProtocolSettings(
        images=False, configurations=22, frames_per_configuration=30, seed=3
    )
    path = tmp_path / "paper.mcap"
    summary = simulate_protocol(settings, path, workers=1, progress=False)
    assert summary.frames == 22 * 30 + 21 * 20
    result = evaluation.evaluate_recording(
        path, tmp_path / "out", methods=PAPER_METHODS, rrd=False, figures=False
    )
    tables = result.tables
    assert {row["group"] for row in tables["plane"]} == set(range(11))
    assert {row["group"] for row in tables["deflection"]} == {0.0, 1.5, 3.0}
    assert {row["group"] for row in tables["noise"]} == {0.5, 1.0, 1.5}
    assert all(row["frames"] == 22 * 30 for row in tables["overall"])  # moves are not scored
    _check_paper_findings({r["method"]: r for r in tables["overall"]})
    ukf = next(r for r in tables["consistency"] if r["method"] == "ukf")
    assert 0.9 <= ukf["within_2sigma"] <= 1.0
    assert all(check.holds for check in result.checks())


def _synthetic_replay(n_frames: int, seed: int = 0) -> evaluation.Replay:
    """A replay of n frames, each with its own deflection and noise label, and two methods
    whose errors have a known spread (no estimator is run)."""
    rng = np.random.default_rng(seed)
    catheter = default_catheter()
    scene = Scene(catheter, default_orthographic_rig(), np.eye(3), np.array([0.0, 0.0, -15.0]))
    points = np.zeros((1 + len(catheter.marker_arclengths_mm), 2))
    covs = np.tile(np.eye(2), (points.shape[0], 1, 1))
    truth = rng.uniform(-np.pi, np.pi, n_frames)
    frames = [
        RecordedFrame(
            Frame(0.05 * i, np.zeros(3), None, (points, points), (covs, covs), None, truth[i]),
            FrameLabels(
                plane=i % 3,
                configuration=i // 100,
                deflection_mm=float(rng.uniform(0.0, 10.0)),
                noise_level=float(rng.uniform(0.1, 3.0)),
            ),
        )
        for i in range(n_frames)
    ]
    results = {}
    for name, std in (("tip-position", 0.05), ("ukf", 0.01)):
        delta = truth + std * rng.standard_normal(n_frames)
        estimates = tuple(
            Estimate(0.05 * i, delta[i], std, 0.0, nis=1.0, nis_dof=3) for i in range(n_frames)
        )
        results[name] = evaluation.MethodResult(name, estimates, truth)
    return evaluation.Replay(
        path="synthetic.mcap",
        source="markers",
        scene=scene,
        frames=frames,
        observations=[],
        results=results,
        bound_rad=np.full(n_frames, 0.04),
        sigma_image=np.ones(n_frames),
        report=ReadReport("synthetic.mcap"),
        settings={"noise_unit": "mm"},
    )


def test_continuous_labels_are_binned():
    """5,000 frames, each with its own deflection and noise: a few ranges, not 5,000 groups."""
    n = 5000
    replay = _synthetic_replay(n)
    tables = evaluation.replay_tables(replay)
    deflection = evaluation.bin_names(evaluation.DEFLECTION_BIN_EDGES_MM)
    noise = evaluation.bin_names(evaluation.NOISE_BIN_EDGES)
    methods = ["tip-position", "ukf", evaluation.BOUND_NAME]
    for table, names in (("deflection", deflection), ("noise", noise)):
        rows = tables[table]
        groups = list(dict.fromkeys(row["group"] for row in rows))
        assert set(groups) <= set(names) and len(groups) >= 4, groups
        assert groups == [g for g in names if g in groups]  # in order of the ranges
        assert len(rows) == len(groups) * len(methods)
        assert sum(r["frames"] for r in rows if r["method"] == "ukf") == n
    deflection_mm = np.array([r.labels.deflection_mm for r in replay.frames])
    row = next(r for r in tables["deflection"] if r["group"] == "2 to 4" and r["method"] == "ukf")
    inside = (deflection_mm >= 2.0) & (deflection_mm < 4.0)
    assert row["frames"] == np.count_nonzero(inside)
    assert row["group_median"] == pytest.approx(np.median(deflection_mm[inside]))
    # each group's statistics are those of its frames
    errors = replay.results["ukf"].errors_rad[inside]
    assert row["rms_deg"] == pytest.approx(np.degrees(np.sqrt(np.mean(errors**2))))
    # labels with a few levels keep one group per value
    assert {r["group"] for r in tables["plane"]} == {0, 1, 2}
    assert len({r["group"] for r in tables["configuration"]}) == n // 100
    assert [r["method"] for r in tables["consistency"]] == ["tip-position", "ukf"]
    markdown = evaluation.replay_markdown(replay, tables)
    assert "| 2 to 4 |" in markdown and "median (mm)" in markdown


def test_groups_by_value_or_by_range():
    include = np.array([True, True, True, False, True, True])
    groups = evaluation.group_frames([2, None, 0, 0, 2, 5], include)
    assert [(g.key, g.frames.tolist()) for g in groups] == [(0, [2]), (2, [0, 4]), (5, [5])]
    values = list(np.linspace(0.0, 9.0, 10))  # more distinct values than LEVELS_MAX
    groups = evaluation.group_frames(values, np.ones(10, bool), (1.0, 4.0))
    assert [(g.key, g.frames.tolist(), g.median) for g in groups] == [
        ("< 1", [0], 0.0),
        ("1 to 4", [1, 2, 3], 2.0),
        (">= 4", [4, 5, 6, 7, 8, 9], 6.5),
    ]


def test_protocol_layout_is_the_papers():
    settings = ProtocolSettings(images=False)
    catheter = default_catheter()
    scene = Scene(catheter, default_render_rig(), np.eye(3), np.array([0.0, 0.0, -15.0]))
    protocol = build_protocol(settings, scene)
    configurations = protocol.configurations
    assert len(configurations) == 94 and {c.plane for c in configurations} == set(range(11))
    assert protocol.n_frames == 94 * 100 + 93 * 20
    assert np.ptp(np.degrees(protocol.delta_L_rad)) > 180  # torsions beyond half a turn apart
    deflected = [c for c in configurations if c.deflection_mm > 0]
    assert 0 < len(deflected) < len(configurations)
    # frames fall on the joint grid, and the joints are continuous across the moves
    t = np.arange(0, protocol.end_ns, settings.joint_period_ns)
    q, _ = protocol.joints(t)
    assert np.abs(np.diff(q, axis=0)).max() < 0.01
    assert all(
        np.all(protocol.frame_times_ns(c.index) % settings.joint_period_ns == 0)
        for c in configurations
    )


def test_truncated_recording_is_evaluated_and_the_loss_reported(tmp_path):
    settings = ProtocolSettings(
        images=False, planes=3, configurations=6, frames_per_configuration=20
    )
    path = tmp_path / "whole.mcap"
    simulate_protocol(settings, path, workers=1, progress=False)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(0.7 * len(data))])
    result = evaluation.evaluate_recording(
        cut, tmp_path / "out", methods=["tip-position"], rrd=False, figures=False
    )
    summary = (tmp_path / "out" / "summary.md").read_text()
    assert "truncated" in summary and "lost" in summary
    frames = result.tables["overall"][0]["frames"]
    assert 0 < frames < 6 * 20


def test_batch_over_recordings_reports_the_bad_one(tmp_path, capsys):
    settings = ProtocolSettings(
        images=False, planes=2, configurations=2, frames_per_configuration=20
    )
    good = tmp_path / "good.mcap"
    simulate_protocol(settings, good, workers=1, progress=False)
    bad = tmp_path / "bad.mcap"
    bad.write_text("not a recording")
    out = tmp_path / "batch"
    code = main(
        [
            "evaluate",
            str(good),
            str(bad),
            "--methods",
            "tip-position",
            "ukf",
            "--out",
            str(out),
            "--workers",
            "2",
            "--no-rrd",
            "--no-figures",
            "--no-progress",
        ]
    )
    captured = capsys.readouterr()
    assert code == 1
    assert "not an MCAP file" in captured.err and captured.err.count("\n") == 1
    batch = (out / "batch.md").read_text()
    assert "good.mcap" in batch and "error" in batch
    assert (out / "good" / "summary.md").exists()


def test_cli_errors_are_one_line(tmp_path, capsys):
    notes = tmp_path / "notes.mcap"
    notes.write_text("hello")
    assert main(["evaluate", str(notes), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not an MCAP file" in err
    assert main(["evaluate", str(notes), "--methods", "nope"]) == 2


def test_batch_on_a_dask_cluster(tmp_path):
    from dask.distributed import LocalCluster

    settings = ProtocolSettings(
        images=False, planes=2, configurations=2, frames_per_configuration=20
    )
    paths = []
    for seed in (0, 1):
        path = tmp_path / f"session{seed}.mcap"
        simulate_protocol(
            ProtocolSettings(**{**settings.to_dict(), "seed": seed}),
            path,
            workers=1,
            progress=False,
        )
        paths.append(path)
    with LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
    ) as cluster:
        items = evaluation.evaluate_batch(
            paths,
            tmp_path / "batch",
            methods=["tip-position"],
            scheduler=cluster.scheduler_address,
            progress=False,
            rrd=False,
            figures=False,
        )
    assert [Path(item.path).name for item in items] == ["session0.mcap", "session1.mcap"]
    assert all(item.error is None and item.overall for item in items)
    assert (tmp_path / "batch" / "session1" / "summary.csv").exists()


def test_rerun_sink_logs_frames_and_estimates_for_the_live_loop(tmp_path):
    """The per-frame calls the live loop makes end up in a readable .rrd."""
    from rerun.chunk import RrdReader

    from tracker.estimators import make_estimator
    from tracker.viewer.layout import default_blueprint
    from tracker.viewer.output import file_stream
    from tracker.viewer.sink import RerunSink

    catheter = default_catheter()
    scene = Scene(catheter, default_render_rig(), np.eye(3), np.array([0.0, 0.0, -15.0]))
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.2, 0.1, 0.1], [3, 3, 3], 1.0)
    frames = simulate_frames(
        scene, trajectory, 1.0, NoiseSettings(sigma=0.5), np.random.default_rng(4)
    )
    reconstructor = Reconstructor(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    estimator = make_estimator("ukf", catheter)
    path = tmp_path / "live.rrd"
    stream = file_stream(path, recording_id="test-live", blueprint=default_blueprint(["ukf"]))
    sink = RerunSink(stream)
    for frame in frames:
        observation = reconstructor.observe(frame)
        estimate = estimator.step(observation)
        sink.log_frame(frame, observation, {"ukf": estimate}, scene)
        sink.log_estimate("ukf", estimate, frame.delta_L_true_rad)
    stream.flush()
    stream.disconnect()
    rows: dict[str, int] = {}
    for chunk in RrdReader(path).stream():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    for entity in (
        "/series/delta_L/ukf",
        "/series/error/ukf",
        "/series/delta_L/_truth",
        "/world/catheter/estimate",
        "/world/catheter/truth",
        "/world/cameras/front/segmented",
        "/world/cameras/side/reprojected",
    ):
        assert rows.get(entity, 0) >= len(frames) - 1, entity
