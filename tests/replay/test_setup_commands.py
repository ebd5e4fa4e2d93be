"""The set-up commands (fit-model, register, import) and the tutorial of docs/setup.md."""

from __future__ import annotations

import argparse
import re
import shlex
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat
from scipy.spatial.transform import Rotation

from models.catheter import default_catheter
from models.model_file import load_catheter
from models.pose import Pose
from models.registration import register_base, registration_routine
from models.rig_file import base_from_dict, read_rig_file, rig_toml
from models.shape_fit import AngleShapes
from replay import cli, setup_commands
from replay.evaluation import run_methods
from replay.simulation import setup_data
from tracker.io.routine import observations_from_frames, read_routine, write_observations
from tracker.io.shapes import shape_columns, write_shapes
from tracker.io.tables import write_csv
from tracker.reconstruction import Reconstructor

DOC = Path(__file__).resolve().parents[2] / "docs" / "setup.md"
SETUP_COMMANDS = {
    "fit-model": setup_commands.add_fit_model_parser,
    "register": setup_commands.add_register_parser,
    "import": setup_commands.add_import_parser,
}
# Stated accuracy of fit-model on 49 shapes (7 x 7 grid) of the default model, 0.1 mm noise:
# the shapes over the whole joint range, and the entries of A (poorly conditioned: some
# combinations of entries hardly change the shape, so they are the least accurate).
FIT_TIP_MM = 0.15
FIT_ANGLE_DEG = 3.0
FIT_ENTRY = 0.25
# Stated accuracy of register through the calibrated cameras of the tutorial.
REGISTER_MM = 0.05
REGISTER_DEG = 0.2
METHODS = ["tip-position", "body-positions"]


def run(argv: list[str]) -> int:
    """One set-up command line, in-process; errors propagate (replay.cli.main prints them)."""
    parser = argparse.ArgumentParser(prog="cathtrack")
    SETUP_COMMANDS[argv[0]](parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.run(args)


def cathtrack(argv: list[str]) -> int:
    """Any cathtrack command line: the set-up commands as in :func:`run`, others via the CLI."""
    return run(argv) if argv[0] in SETUP_COMMANDS else cli.main(argv)


def joint_grid(n: int = 21) -> np.ndarray:
    g = np.linspace(-1.0, 1.0, n)
    q_p, q_d = (x.ravel() for x in np.meshgrid(g, g))
    return np.column_stack([np.zeros_like(q_p), q_p, q_d])


def shape_errors(fitted, truth) -> tuple[float, float]:
    """Largest tip distance (mm) and tangent-angle difference (deg) over the joint range."""
    q = joint_grid()
    tip = np.linalg.norm(fitted.tip(q) - truth.tip(q), axis=-1).max()
    angle = 0.0
    for a, b in ((fitted.proximal, truth.proximal), (fitted.distal, truth.distal)):
        s = np.linspace(0.0, b.length_mm, 14)[None, :]
        g = np.linspace(-1.0, 1.0, 21)[:, None]
        angle = max(angle, np.degrees(np.abs(a.theta(s, g) - b.theta(s, g))).max())
    return float(tip), float(angle)


# ------------------------------------------------------------------------------ fit-model
@pytest.fixture(scope="module")
def shapes_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("shapes") / "shapes.csv"
    shapes = setup_data.measured_shapes(default_catheter(), np.random.default_rng(3))
    return write_shapes(path, shapes)


def test_fit_model_recovers_the_default_model_and_reports_its_cross_validated_residual(
    shapes_csv, tmp_path, capsys
):
    out = tmp_path / "model.toml"
    assert run(["fit-model", str(shapes_csv), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    truth, fitted = default_catheter(), load_catheter(out)
    tip_mm, angle_deg = shape_errors(fitted, truth)
    assert tip_mm < FIT_TIP_MM and angle_deg < FIT_ANGLE_DEG
    for got, want in ((fitted.proximal, truth.proximal), (fitted.distal, truth.distal)):
        assert np.abs(got.A - want.A).max() < FIT_ENTRY
    assert "49 configurations" in printed and "5-fold cross-validated" in printed
    overall = next(line for line in printed.splitlines() if line.startswith("overall"))
    fit_mm, fit_deg, held_out_mm, held_out_deg = (float(x) for x in overall.split()[1:])
    # 0.1 mm per axis is 0.17 mm per point: the held-out residual is the noise.
    assert fit_mm <= held_out_mm == pytest.approx(0.1 * np.sqrt(3), rel=0.1)
    assert (tmp_path / "model.png").stat().st_size > 10_000
    assert fitted.marker_arclengths_mm == truth.marker_arclengths_mm


def test_fit_model_reads_tangent_angles_from_a_mat_file(tmp_path, capsys):
    truth = default_catheter()
    q = joint_grid(4)
    s = (np.linspace(0.0, 13.0, 5), np.linspace(0.0, 16.0, 5))
    theta = tuple(
        segment.theta(s_k[None, :], q[:, 1 + k, None])
        for k, (segment, s_k) in enumerate(zip((truth.proximal, truth.distal), s, strict=True))
    )
    columns = shape_columns(AngleShapes(q, s, theta))
    columns["theta_deg"] = np.degrees(columns.pop("theta_rad"))
    savemat(tmp_path / "angles.mat", {k: np.asarray(v, float) for k, v in columns.items()})
    out = tmp_path / "angles.toml"
    assert run(["fit-model", str(tmp_path / "angles.mat"), "--out", str(out), "--no-figure"]) == 0
    fitted = load_catheter(out)
    np.testing.assert_allclose(fitted.proximal.A, truth.proximal.A, atol=1e-9)
    np.testing.assert_allclose(fitted.distal.A, truth.distal.A, atol=1e-9)
    assert "tangent angles" in capsys.readouterr().out
    assert not (tmp_path / "angles.png").exists()


def _break_shapes(path: Path, how: str) -> Path:
    lines = path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    if how == "missing column":
        lines = [",".join(line.split(",")[:-1]) if i >= header else line
                 for i, line in enumerate(lines)]
    elif how == "NaN":
        cells = lines[header + 7].split(",")
        cells[5] = "nan"
        lines[header + 7] = ",".join(cells)
    else:  # two configurations only
        shapes = [line for line in lines[header + 1 :] if line.split(",")[0] in ("0", "1")]
        lines = [lines[header]] + shapes
    broken = path.with_name(f"{how.replace(' ', '_')}.csv")
    broken.write_text("\n".join(lines) + "\n")
    return broken


@pytest.mark.parametrize(
    ("how", "message"),
    [
        ("missing column", r"missing_column.csv: no column 'z_mm' \(columns: shape, q_r_rad, "),
        ("NaN", r"NaN.csv: column 'x_mm' has 1 missing or non-finite value\(s\), the first at"
                r" line 8"),
        ("too few", r"too_few.csv: 2 configurations with 2 distinct q_p value\(s\)"
                    r" cannot determine the proximal joint basis of size 3; measure at least 3"),
    ],
)
def test_fit_model_bad_files_are_one_line_errors(shapes_csv, tmp_path, how, message):
    broken = _break_shapes(Path(shapes_csv), how)
    with pytest.raises(ValueError, match=message) as info:
        run(["fit-model", str(broken), "--out", str(tmp_path / "m.toml"), "--no-figure"])
    assert "\n" not in str(info.value)


# ------------------------------------------------------------------------------ register
@pytest.fixture(scope="module")
def truth():
    return setup_data.lab_truth(0)


def test_register_prints_the_routine_and_recovers_a_known_base_pose(truth, tmp_path, capsys):
    routine = tmp_path / "routine.csv"
    assert run(["register", "--routine-out", str(routine), "--planes", "3"]) == 0
    printed = capsys.readouterr().out
    assert "straight and untwisted" in printed and "120.0" in printed
    q = read_routine(routine)
    assert q.shape == (7, 3)
    frames = setup_data.routine_frames(truth.scene(), q, np.random.default_rng(4))
    observed = write_observations(tmp_path / "observed.csv", *observations_from_frames(frames))
    rig = tmp_path / "rig.toml"
    rig.write_text(rig_toml(truth.rig, None, "calibrated", {"calibration": {"pairs": 7}}))
    assert run(["register", str(observed), "--rig", str(rig)]) == 0
    printed = capsys.readouterr().out
    assert "convention: delta_L = 0 during the routine" in printed
    data = read_rig_file(rig)
    assert data["calibration"] == {"pairs": 7}  # the rest of the rig file is kept
    assert data["registration"]["residual_unit"] == "px"
    base = base_from_dict(data)
    assert np.linalg.norm(base.o_b_w_mm - truth.base.o_b_w_mm) < 0.05
    assert rotation_deg(base, truth.base) < 0.1
    with pytest.raises(ValueError, match=r"--rig FILE"):
        run(["register", str(observed)])


def rotation_deg(a: Pose, b: Pose) -> float:
    return float(np.degrees(Rotation.from_matrix(a.R_w_b @ b.R_w_b.T).magnitude()))


def test_tracking_with_the_registered_pose_matches_the_true_pose(truth):
    """The registered base (0.5 px noise, 5 pairs per step) tracks as well as the true one
    (the per-frame estimators: the session's torsion jumps between planes, which a filter
    follows only after a while)."""
    scene = truth.scene()
    rng = np.random.default_rng(6)
    frames = setup_data.routine_frames(scene, registration_routine(), rng)
    registration = register_base(truth.catheter, truth.rig, *observations_from_frames(frames))
    session = setup_data.session_logs(scene, rng, frames_per_configuration=10)
    delta_L = np.array([f.delta_L_true_rad for f in session.frames])
    rms = {}
    for name, pose in (("true", truth.base), ("registered", registration.pose)):
        reconstructor = Reconstructor(truth.catheter, truth.rig, pose.R_w_b, pose.o_b_w_mm)
        observations = reconstructor.observe_batch(session.frames)
        results = run_methods(truth.catheter, observations, delta_L, METHODS)
        rms[name] = {m: r.summary()["rms_deg"] for m, r in results.items()}
    for method in METHODS:
        assert rms["registered"][method] == pytest.approx(rms["true"][method], abs=0.05)
        assert rms["true"][method] < 1.0


def test_import_needs_a_registered_rig(truth, tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text(rig_toml(truth.rig))
    (tmp_path / "import.toml").write_text('format = "cathtrack-import"\nversion = 1\n')
    write_csv(tmp_path / "j.csv", {"time_s": np.zeros(1)})
    with pytest.raises(ValueError, match=r"missing table \[joints\]"):
        run(["import", str(tmp_path / "import.toml"), "--rig", str(rig)])


# ------------------------------------------------------------------------------ tutorial
def tutorial_commands() -> list[list[str]]:
    """The command lines of the ```sh blocks of docs/setup.md, in order."""
    blocks = re.findall(r"```sh\n(.*?)```", DOC.read_text(encoding="utf-8"), flags=re.S)
    text = "\n".join(blocks).replace("\\\n", " ")
    return [shlex.split(line) for line in text.splitlines() if line.strip()]


def test_the_tutorial_runs_end_to_end(tmp_path, monkeypatch, capsys):
    commands = tutorial_commands()
    assert [c[1] if c[0] == "cathtrack" else c[3] for c in commands] == [
        "lab", "calibrate", "fit-model", "register", "observe", "register", "import", "track",
        "evaluate",
    ]  # fmt: skip
    monkeypatch.chdir(tmp_path)
    for command in commands:
        if command[0] == "cathtrack":
            code = cathtrack(command[1:])
        else:
            assert command[:3] == ["python", "-m", "replay.simulation.setup_data"]
            code = setup_data.main(command[3:])
        assert code == 0, f"{shlex.join(command)}: {capsys.readouterr().err}"
    lab = tmp_path / "lab"
    registered = base_from_dict(read_rig_file(lab / "rig.toml"))
    true_base = base_from_dict(tomllib.loads((lab / "truth.toml").read_text()))
    assert np.linalg.norm(registered.o_b_w_mm - true_base.o_b_w_mm) < REGISTER_MM
    assert rotation_deg(registered, true_base) < REGISTER_DEG
    for name in ("model.png", "live.rrd", "tracked.mcap", "results/summary.md"):
        assert (lab / name).stat().st_size > 0, name
    summary = (lab / "results" / "summary.md").read_text()
    assert "the UKF is better than Tip Position: **holds**" in summary
