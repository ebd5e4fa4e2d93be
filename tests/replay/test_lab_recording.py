"""What a lab meets, in a recording (``cathtrack simulate`` options, replay.protocol) and in
the report (``cathtrack evaluate``'s robustness table, replay.evaluation.tables).

The recording is a reduced paper protocol, markers only, with every lab condition at once:
a contact deviation of the joints per configuration, a true catheter that bends 5 % more
than the model, wrong and missing markers, and torsion wind-up with play. Seeds are fixed,
so the statistics are deterministic; the tolerances are a few binomial standard deviations.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig
from models.rotations import wrap_angle
from replay import evaluation
from replay.cli import main
from replay.protocol import ProtocolSettings, build_protocol
from replay.simulation.simulator import (
    LabConditions,
    Scene,
    image_sigma,
    point_arclengths,
    torsion_windup,
    truth_catheter,
)
from tracker.io.recording import FrameLabels, ReadReport, RecordedFrame, open_recording
from tracker.types import Estimate, Frame

LAB = LabConditions(
    model_scale_error=0.05,
    contact_joint_std_mm=0.08,
    outlier_probability=0.1,
    outlier_magnitude=5.0,
    dropout_probability=0.1,
    windup_play_rad=math.radians(20.0),
)
LAB_OPTIONS = [
    "--model-scale-error", "0.05",
    "--contact-joint-std-mm", "0.08",
    "--outlier-rate", "0.1",
    "--outlier-size-mm", "5",
    "--dropout-rate", "0.1",
    "--windup-play-deg", "20",
]  # fmt: skip
NOISE_MM = 0.1


def simulate(path: Path, rig: str) -> None:
    code = main(
        ["simulate", "--no-images", "--rig", rig, "--planes", "3", "--configs", "6",
         "--frames", "60", "--seed", "2", "--noise-levels-mm", str(NOISE_MM), *LAB_OPTIONS,
         "--out", str(path), "--no-progress"]
    )  # fmt: skip
    assert code == 0


@pytest.fixture(scope="module", params=["orthographic", "pinhole"])
def lab_recording(request, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("lab") / f"lab_{request.param}.mcap"
    simulate(path, request.param)
    return path


def residuals(recording, catheter, joint_offsets) -> tuple[np.ndarray, np.ndarray]:
    """Distance of every recorded point of the scored frames from where ``catheter`` at the
    recorded joints plus ``joint_offsets[configuration]`` and the true torsion puts it (image
    unit; NaN where dropped), and the image unit per mm at the isocentre."""
    scene = evaluation.recording_scene(recording)
    s = np.asarray(point_arclengths(catheter))
    out = []
    for recorded in recording.frames():
        frame, c = recorded.frame, recorded.labels.configuration
        if c is None:
            continue
        points_b = catheter.backbone(
            np.asarray(frame.q) + joint_offsets[c], frame.delta_L_true_rad, s
        )
        points_w = points_b @ scene.R_w_b.T + scene.o_b_w_mm
        for view, uv in zip(scene.rig.views, frame.uv, strict=True):
            out.append(np.linalg.norm(view.project(points_w) - uv, axis=-1))
    return np.concatenate(out), image_sigma(scene.rig.views[0], 1.0)


def test_a_recording_with_every_lab_condition_has_them_and_reads_back(lab_recording):
    recording = open_recording(lab_recording)
    settings = recording.metadata.settings
    fields = ProtocolSettings.__dataclass_fields__
    read = ProtocolSettings(**{k: v for k, v in settings.items() if k in fields})
    assert read.lab_conditions == LAB
    assert set(settings["lab_conditions_units"]) == set(LabConditions.__dataclass_fields__)
    offsets = np.array(settings["joint_offset_per_configuration"])
    model = recording.catheter()
    truth = truth_catheter(model, LAB.model_scale_error)

    # Everything the truth does is in the recording: with the true catheter, the joint
    # offsets and the recorded torsion, the points that are no outliers sit at the noise.
    error, px_per_mm = residuals(recording, truth, offsets)
    sigma = NOISE_MM * px_per_mm
    dropped = np.isnan(error)
    assert np.mean(dropped) == pytest.approx(LAB.dropout_probability, abs=0.03)
    wrong = error[~dropped] > 0.5 * LAB.outlier_magnitude * px_per_mm
    assert np.mean(wrong) == pytest.approx(LAB.outlier_probability, abs=0.03)
    outliers = error[~dropped][wrong]
    np.testing.assert_allclose(outliers, LAB.outlier_magnitude * px_per_mm, atol=5 * sigma)
    inliers = error[~dropped][~wrong]
    # The distance of a 2-D Gaussian error has median sigma sqrt(2 ln 2).
    assert np.median(inliers) == pytest.approx(sigma * math.sqrt(2 * math.log(2)), rel=0.15)

    # Without the deflections and contact deviations, or with the model, it is far off.
    for catheter, joints in ((truth, 0.0 * offsets), (model, offsets)):
        error, _ = residuals(recording, catheter, joints)
        assert np.nanmedian(error) > 3 * np.median(inliers)

    # The torsion winds up within the play about each plane's delta_L.
    delta_L = np.array(settings["delta_L_per_plane_rad"])
    wound = np.array([
        wrap_angle(r.frame.delta_L_true_rad - delta_L[r.labels.plane])
        for r in recording.frames() if r.labels.configuration is not None
    ])  # fmt: skip
    assert np.all(np.abs(wound) <= LAB.windup_play_rad + 1e-9)
    assert np.max(np.abs(wound)) > 0.5 * LAB.windup_play_rad
    for r in recording.frames():
        assert r.labels.delta_1_true_rad == pytest.approx(
            float(wrap_angle(r.frame.q[0] + r.frame.delta_L_true_rad)), abs=1e-6
        )


def test_contact_deviations_and_the_windup_of_the_protocol():
    """Over the 94 configurations of the paper's protocol, q_p (which the deflection leaves
    alone) is off by the contact std; the wind-up of any stretch of the session, from the
    state stored at its configuration's start, is the one pass over the whole session."""
    settings = ProtocolSettings(images=False, rig="orthographic", lab_conditions=LAB)
    scene = Scene(
        default_catheter(), default_orthographic_rig(), np.eye(3), np.array([0, 0, -15.0])
    )
    protocol = build_protocol(settings, scene)
    offsets = np.array([c.joint_offset for c in protocol.configurations])
    assert np.all(offsets[:, 0] == 0.0)
    assert np.std(offsets[:, 1]) == pytest.approx(LAB.contact_joint_std_mm, rel=0.2)
    t_ns = np.arange(0, protocol.end_ns // 8, settings.joint_period_ns)
    whole = torsion_windup(protocol.joints(t_ns)[0][:, 0], LAB.windup_play_rad)
    np.testing.assert_allclose(protocol.windup_rad(t_ns[::7]), whole[::7], atol=1e-12)


def test_wrong_and_missing_markers_need_markers_only():
    with pytest.raises(ValueError, match="markers only"):
        ProtocolSettings(lab_conditions=LabConditions(dropout_probability=0.1))
    ProtocolSettings(lab_conditions=LabConditions(model_scale_error=0.05, windup_play_rad=0.1))


# ------------------------------------------------------------------------ the report
def constructed_replay() -> evaluation.Replay:
    """Four configurations of 10 frames and a move of 5 after each but the last, and two
    methods: ``honest`` is 1 degree off with a 1-degree std everywhere; ``overconfident``
    is 40 degrees off with a 5-degree std in two frames of configuration 1, in every frame
    of configuration 3, and in the moves (which are not scored)."""
    catheter = default_catheter()
    scene = Scene(catheter, default_orthographic_rig(), np.eye(3), np.array([0.0, 0.0, -15.0]))
    configuration = []
    for c in range(4):
        configuration += [c] * 10 + ([None] * 5 if c < 3 else [])
    n = len(configuration)
    truth = np.linspace(-1.0, 1.0, n)
    points = np.zeros((len(point_arclengths(catheter)), 2))
    covs = np.tile(np.eye(2), (points.shape[0], 1, 1))
    frames = [
        RecordedFrame(
            Frame(0.05 * i, np.zeros(3), None, (points, points), (covs, covs), None, truth[i]),
            FrameLabels(plane=0, configuration=c),
        )
        for i, c in enumerate(configuration)
    ]
    c = np.array([-1 if x is None else x for x in configuration])
    index = np.arange(n)
    wrong = (c < 0) | (c == 3) | ((c == 1) & np.isin(index, index[c == 1][:2]))
    results = {}
    for name, error_deg, std_deg in (
        ("honest", np.ones(n), np.ones(n)),
        ("overconfident", np.where(wrong, 40.0, 1.0), np.where(wrong, 5.0, 1.0)),
    ):
        estimates = tuple(
            Estimate(0.05 * i, truth[i] + math.radians(error_deg[i]), math.radians(std_deg[i]), 0.0)
            for i in range(n)
        )
        results[name] = evaluation.MethodResult(name, estimates, truth)
    return evaluation.Replay(
        path="constructed.mcap",
        source="markers",
        scene=scene,
        frames=frames,
        observations=[],
        results=results,
        bound_rad=np.full(n, 0.01),
        sigma_image=np.ones(n),
        report=ReadReport("constructed.mcap"),
        settings={"noise_unit": "mm"},
    )


def test_the_report_counts_confidently_wrong_configurations():
    replay = constructed_replay()
    tables = evaluation.replay_tables(replay)
    rows = {row["method"]: row for row in tables["robustness"]}
    assert rows["honest"]["confidently_wrong_configurations"] == 0
    assert rows["honest"]["within_2sigma"] == 1.0
    assert rows["honest"]["mean_nees"] == pytest.approx(1.0)
    bad = rows["overconfident"]
    assert bad["frames"] == 40
    assert bad["confidently_wrong_frames"] == 12
    assert bad["confidently_wrong_configurations"] == 2
    assert bad["within_2sigma"] == pytest.approx(28 / 40)
    assert bad["mean_nees"] == pytest.approx((28 + 12 * 64) / 40)
    printed = evaluation.replay_markdown(replay, tables)
    assert (
        "| method | frames | RMS (deg) | max (deg) | within 2 sigma | mean NEES"
        " | confidently wrong frames | confidently wrong configurations |"
    ) in printed
    assert "| overconfident | 40 |" in printed
    line = next(x for x in printed.splitlines() if x.startswith("| overconfident | 40 |"))
    assert line.endswith("| 70.0% | 19.90 | 12 | 2 |")


def test_evaluate_prints_the_robustness_table(tmp_path, capsys):
    path = tmp_path / "lab.mcap"
    simulate(path, "orthographic")
    capsys.readouterr()
    code = main(["evaluate", str(path), "--methods", "tip-position", "ukf", "--out",
                 str(tmp_path / "eval"), "--no-rrd", "--no-figures", "--no-progress",
                 "--workers", "1"])  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "## Can the uncertainty be trusted?" in printed
    assert "confidently wrong configurations |" in printed
    for method in ("tip-position", "ukf"):
        assert any(line.startswith(f"| {method} | 360 |") for line in printed.splitlines())
    header = (tmp_path / "eval" / "summary.csv").read_text().splitlines()[0]
    assert "confidently_wrong_configurations" in header
