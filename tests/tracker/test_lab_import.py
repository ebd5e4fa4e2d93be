"""The lab's logs into a recording: round trips through CSV and .mat, and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.io import savemat

from models.model_file import DEFAULT_MODEL_PATH, load_catheter
from models.rig_file import rig_toml
from replay.evaluation import evaluate_recording
from replay.simulation.setup_data import lab_truth, session_logs
from tracker.io.lab_import import LabImportError, read_lab_logs, write_lab_recording
from tracker.io.recording import RecordingWriter, open_recording
from tracker.io.tables import TableError, read_table, write_csv

MODEL_TOML = DEFAULT_MODEL_PATH.read_text(encoding="utf-8")
N_POINTS = 1 + len(load_catheter(DEFAULT_MODEL_PATH).marker_arclengths_mm)
METHODS = ["tip-position", "ukf"]


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    """A recording with joint rates, missing points, truth and labels, and its rig file."""
    folder = tmp_path_factory.mktemp("lab")
    truth = lab_truth(0)
    logs = session_logs(
        truth.scene(), np.random.default_rng(5), frames_per_configuration=6, joint_rate_hz=100.0
    )
    logs.frames[3].uv[0][1] = np.nan  # a marker not found in the front view
    logs.frames[7].uv[1][0] = np.nan
    rig_text = rig_toml(truth.rig, truth.base)
    (folder / "rig.toml").write_text(rig_text, encoding="utf-8")
    path = folder / "original.mcap"
    with RecordingWriter(path, model_toml=MODEL_TOML, rig_toml=rig_text) as writer:
        done = 0
        for frame, label in zip(logs.frames, logs.labels, strict=True):
            upto = int(np.searchsorted(logs.joint_time_s, frame.time_s, side="right"))
            writer.write_joints(logs.joint_time_s[done:upto], logs.q[done:upto],
                                logs.q_dot[done:upto])
            done = upto
            writer.write_frame(frame, label)
        writer.write_joints(logs.joint_time_s[done:], logs.q[done:], logs.q_dot[done:])
    return path, folder / "rig.toml"


def export(recording_path, folder, kind):
    """The recording as a lab would log it: CSV in ms and deg, or .mat in s and rad."""
    with open_recording(recording_path) as recording:
        joints = recording.joints
        recorded = list(recording.frames(images=False))
    frames = [r.frame for r in recorded]
    labels = [r.labels for r in recorded]
    deg = kind == "csv"
    angle = np.degrees if deg else (lambda x: np.asarray(x))
    time = (lambda t: np.asarray(t) * 1e3) if deg else (lambda t: np.asarray(t))
    none = lambda values: np.array([np.nan if v is None else v for v in values], float)  # noqa: E731
    tables = {
        "joints": {
            "t": time(joints.time_s),
            "qr": angle(joints.q[:, 0]),
            "qp": joints.q[:, 1],
            "qd": joints.q[:, 2],
            "qr_dot": angle(joints.q_dot[:, 0]),
            "qp_dot": joints.q_dot[:, 1],
            "qd_dot": joints.q_dot[:, 2],
        },
        "markers": {"t": time([f.time_s for f in frames])},
        "truth": {
            "t": time([f.time_s for f in frames]),
            "dL": angle(none([f.delta_L_true_rad for f in frames])),
            "d1": angle(none([x.delta_1_true_rad for x in labels])),
            "plane": none([x.plane for x in labels]),
            "config": none([x.configuration for x in labels]),
            "defl": none([x.deflection_mm for x in labels]),
            "noise": none([x.noise_level for x in labels]),
        },
    }
    points = {}
    for v_index, view in enumerate(("front", "side")):
        uv = np.array([f.uv[v_index] for f in frames])
        points[view] = [[f"{view}{k}u", f"{view}{k}v"] for k in range(N_POINTS)]
        for k, (u, v) in enumerate(points[view]):
            tables["markers"][u], tables["markers"][v] = uv[:, k, 0], uv[:, k, 1]
        tables["markers"][f"{view}_sigma"] = np.sqrt(
            np.array([np.nanmax(f.cov[v_index][:, 0, 0]) for f in frames])
        )
    names = {}
    for name, columns in tables.items():
        if kind == "csv":
            names[name] = write_csv(folder / f"{name}.csv", columns).name
        else:
            savemat(folder / f"{name}.mat", {k: np.asarray(v, float) for k, v in columns.items()})
            names[name] = f"{name}.mat"
    time_unit = "ms" if deg else "s"
    angle_unit = "deg" if deg else "rad"
    mapping = [
        'format = "cathtrack-import"', "version = 1", 'unit = "px"', "",
        "[joints]", f'file = "{names["joints"]}"', 'time = "t"', f'time_unit = "{time_unit}"',
        'q_r = "qr"', f'q_r_unit = "{angle_unit}"', 'q_p = "qp"', 'q_d = "qd"',
        'q_r_dot = "qr_dot"', 'q_p_dot = "qp_dot"', 'q_d_dot = "qd_dot"', "",
        "[truth]", f'file = "{names["truth"]}"', 'time = "t"', f'time_unit = "{time_unit}"',
        'delta_L = "dL"', f'delta_L_unit = "{angle_unit}"', 'delta_1 = "d1"',
        'plane = "plane"', 'configuration = "config"', 'deflection_mm = "defl"',
        'noise_level = "noise"',
    ]  # fmt: skip
    for view in ("front", "side"):
        mapping += [
            "", f"[{view}]", f'file = "{names["markers"]}"', 'time = "t"',
            f'time_unit = "{time_unit}"', f"points = {json.dumps(points[view])}",
            f'sigma = "{view}_sigma"',
        ]  # fmt: skip
    path = folder / "import.toml"
    path.write_text("\n".join(mapping) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("kind", ["csv", "mat"])
def test_export_and_import_give_the_same_frames_and_evaluation(original, tmp_path, kind):
    recording_path, rig_path = original
    mapping = export(recording_path, tmp_path, kind)
    logs = read_lab_logs(mapping, N_POINTS)
    assert logs.warnings == []
    imported = tmp_path / "imported.mcap"
    summary = write_lab_recording(imported, logs, MODEL_TOML, rig_path.read_text("utf-8"))
    with open_recording(recording_path) as a, open_recording(imported) as b:
        assert b.report.ok, b.report.summary()
        first, second = list(a.frames(images=False)), list(b.frames(images=False))
    assert summary.frames == len(first) == len(second)
    exact = kind == "mat"  # the CSV goes through ms and degrees
    tolerance = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-12, "atol": 1e-12}
    for x, y in zip(first, second, strict=True):
        fx, fy = x.frame, y.frame
        assert fx.time_s == pytest.approx(fy.time_s, abs=1e-12)
        np.testing.assert_allclose(fy.q, fx.q, **tolerance)
        np.testing.assert_allclose(fy.q_dot, fx.q_dot, **tolerance)
        for a, b in zip(fx.uv + fx.cov, fy.uv + fy.cov, strict=True):
            np.testing.assert_allclose(b, a, rtol=1e-14)
        assert fy.delta_L_true_rad == pytest.approx(fx.delta_L_true_rad, abs=1e-14)
        assert y.labels.plane == x.labels.plane
        assert y.labels.configuration == x.labels.configuration
        assert y.labels.delta_1_true_rad == pytest.approx(x.labels.delta_1_true_rad, abs=1e-14)
    tables = [
        evaluate_recording(p, None, METHODS, rrd=False, figures=False).tables
        for p in (recording_path, imported)
    ]
    assert tables[0].keys() == tables[1].keys()
    for name in tables[0]:
        assert len(tables[0][name]) == len(tables[1][name])
        for row_a, row_b in zip(tables[0][name], tables[1][name], strict=True):
            assert row_a.keys() == row_b.keys()
            for key, value in row_a.items():
                if isinstance(value, float):
                    assert row_b[key] == pytest.approx(value, rel=1e-9, abs=1e-12, nan_ok=True)
                else:
                    assert row_b[key] == value


def test_unsynchronised_views_and_missing_joint_values(tmp_path):
    """Each view at its own times: frames at the union, the other view missing there. A joint
    sample with a missing value is dropped and counted."""
    t = np.arange(0.0, 1.0, 0.01)
    write_csv(tmp_path / "joints.csv", {"time_s": t, "q_r_rad": 0 * t, "q_p_mm": 0.5 + 0 * t,
                                        "q_d_mm": np.where(np.arange(t.size) == 4, np.nan, 0.2)})
    uv = {f"{view}_{p}_{c}": np.full(3, 100.0) for view in ("front", "side")
          for p in ("tip", "marker0") for c in "uv"}
    write_csv(tmp_path / "front.csv", {"time_s": np.array([0.1, 0.2, 0.3]), **uv})
    write_csv(tmp_path / "side.csv", {"time_s": np.array([0.1, 0.25, 0.35]), **uv})
    (tmp_path / "import.toml").write_text(
        'format = "cathtrack-import"\nversion = 1\n[joints]\nfile = "joints.csv"\n'
        '[front]\nfile = "front.csv"\n[side]\nfile = "side.csv"\n'
    )
    logs = read_lab_logs(tmp_path / "import.toml", N_POINTS)
    assert logs.warnings == [f"{tmp_path / 'joints.csv'}: 1 joint sample(s) with a missing value"
                             " dropped"]
    truth = lab_truth(0)
    summary = write_lab_recording(
        tmp_path / "out.mcap", logs, MODEL_TOML, rig_toml(truth.rig, truth.base)
    )
    assert summary.frames == 5 and summary.joint_samples == t.size - 1
    with open_recording(tmp_path / "out.mcap") as recording:
        frames = [r.frame for r in recording.frames(images=False)]
    np.testing.assert_allclose([f.time_s for f in frames], [0.1, 0.2, 0.25, 0.3, 0.35])
    assert np.isnan(frames[1].uv[1]).all() and np.isfinite(frames[1].uv[0]).all()
    np.testing.assert_allclose(frames[2].q, [0.0, 0.5, 0.2])


# ------------------------------------------------------------------------------ errors
@pytest.fixture
def lab(tmp_path):
    """A minimal valid set of logs and mapping; tests break one thing each."""
    t = np.arange(0.0, 1.0, 0.1)
    write_csv(tmp_path / "joints.csv", {"t": t, "qr": 0 * t, "qp": 0 * t, "qd": 0 * t})
    write_csv(tmp_path / "markers.csv", {"t": t, **{
        f"{view}_{p}_{c}": t for view in ("front", "side") for p in ("tip", "marker0")
        for c in "uv"}})  # fmt: skip
    text = (
        'format = "cathtrack-import"\nversion = 1\n'
        '[joints]\nfile = "joints.csv"\ntime = "t"\nq_r = "qr"\nq_p = "qp"\nq_d = "qd"\n'
        '[front]\nfile = "markers.csv"\ntime = "t"\n[side]\nfile = "markers.csv"\ntime = "t"\n'
    )
    (tmp_path / "import.toml").write_text(text)
    return tmp_path, text


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("q_p = \"qp\"", "q_p = \"q_p\""), r"joints.csv: no column 'q_p' \(columns: t, qr, qp, qd\)"),
        (("[side]\nfile = \"markers.csv\"\ntime = \"t\"\n", ""), r"import.toml: missing table \[side\]"),
        (("time = \"t\"\nq_r", "time = \"t\"\ntime_unit = \"min\"\nq_r"),
         r"import.toml \[joints\]: 'time_unit' must be one of s, ms, us, ns, got 'min'"),
        (("[front]\nfile", "[front]\npoints = [[\"front_tip_u\", \"front_tip_v\"]]\nfile"),
         r"import.toml \[front\]: 'points' lists 1 point\(s\); the model has the tip and 1"),
        (("[front]\nfile", "[front]\ncolour = 1\nfile"), r"import.toml \[front\]: unknown key"),
        (("version = 1", "version = 2"), r"import.toml: unsupported mapping version 2"),
        (("joints.csv", "nowhere.csv"), r"cannot read .*nowhere.csv: no such file"),
    ],
)
def test_mapping_and_log_problems_are_one_line_errors(lab, change, message):
    folder, text = lab
    (folder / "import.toml").write_text(text.replace(*change))
    with pytest.raises((LabImportError, TableError), match=message) as info:
        read_lab_logs(folder / "import.toml", N_POINTS)
    assert "\n" not in str(info.value)


def test_bad_values_name_the_file_column_and_line(lab):
    folder, _ = lab
    joints = folder / "joints.csv"
    lines = joints.read_text().splitlines()
    lines[3] = "abc," + lines[3].split(",", 1)[1]
    joints.write_text("\n".join(lines) + "\n")
    with pytest.raises(TableError, match=r"joints.csv line 4, column 't': 'abc' is not a number"):
        read_lab_logs(folder / "import.toml", N_POINTS)
    lines[3] = "," + lines[3].split(",", 1)[1]
    joints.write_text("\n".join(lines) + "\n")
    with pytest.raises(TableError, match=r"column 't' has 1 missing .* the first at line 4"):
        read_lab_logs(folder / "import.toml", N_POINTS)
    lines[3] = "0.3,0"
    joints.write_text("\n".join(lines) + "\n")
    with pytest.raises(TableError, match=r"line 4: 2 cells, the header has 4 columns"):
        read_table(joints)
    with pytest.raises(TableError, match=r"unsupported file type '.xlsx'"):
        read_table(folder / "log.xlsx")
