"""The lab's logs into a recording (``cathtrack import``; docs/setup.md, docs/recording.md).

A lab that has its own controller and segmentation logs joint samples with their times and
the segmented points of each view with theirs (CSV or MATLAB .mat tables,
:mod:`tracker.io.tables`), sometimes also a ground truth. A small TOML file maps their columns
to the recording's quantities:

    format = "cathtrack-import"
    version = 1
    unit = "px"                  # unit of the points: px (cameras) or mm (orthographic planes)

    [joints]                     # required; file paths are relative to the mapping file
    file = "logs/joints.csv"
    time = "t_ms"                # column names (defaults: time_s, q_r_rad, q_p_mm, q_d_mm)
    time_unit = "ms"             # s (default), ms, us or ns
    q_r = "qr_deg"
    q_r_unit = "deg"             # rad (default) or deg (also for q_r_dot, per second)
    q_p = "qp"
    q_d = "qd"
    # q_r_dot, q_p_dot, q_d_dot: the joint rates, all three or none

    [front]                      # and [side]: required
    file = "logs/markers.csv"
    time = "t_ms"
    time_unit = "ms"
    points = [["f_tip_u", "f_tip_v"], ["f_m0_u", "f_m0_v"]]   # tip, then the model's markers
    sigma = 0.5                  # segmentation noise per axis (unit of the points), or a column

    [truth]                      # optional: delta_L and the labels of the experiment
    file = "logs/truth.csv"
    time = "t_ms"
    time_unit = "ms"
    delta_L = "dL_deg"
    delta_L_unit = "deg"
    # optional label columns: delta_1, plane, configuration, deflection_mm, noise_level

The recording's session time 0 is the earliest time stamp of the logs; its log times are the
logs' clock in ns where that clock is not negative. Problems end in one
:class:`LabImportError` (or :class:`tracker.io.tables.TableError`) naming the file and the
key or column. Like the recording reader, the import keeps what it can and counts the rest:
joint samples with a missing value are dropped, repeated time stamps keep the first sample,
points not found stay missing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from models.model_file import check_header, read_toml_file
from models.rotations import wrap_angle
from tracker.io.recording import VIEWS, FrameLabels, RecordingWriter
from tracker.io.tables import Table, point_columns, read_table
from tracker.types import Frame

Array = np.ndarray

IMPORT_FORMAT = "cathtrack-import"
IMPORT_VERSION = 1
UNITS = ("px", "mm")
TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
ANGLE_UNITS_RAD = {"rad": 1.0, "deg": np.pi / 180.0}
JOINT_DEFAULTS = {"q_r": "q_r_rad", "q_p": "q_p_mm", "q_d": "q_d_mm"}
RATE_KEYS = ("q_r_dot", "q_p_dot", "q_d_dot")
LABEL_KEYS = ("delta_1", "plane", "configuration", "deflection_mm", "noise_level")
_KEYS = {
    "joints": {"file", "time", "time_unit", "q_r_unit", *JOINT_DEFAULTS, *RATE_KEYS},
    "view": {"file", "time", "time_unit", "points", "sigma"},
    "truth": {"file", "time", "time_unit", "delta_L", "delta_L_unit", *LABEL_KEYS},
}


class LabImportError(ValueError):
    """A mapping file or a log that cannot be imported."""


@dataclass(frozen=True)
class JointLog:
    time_s: Array  # (n,) on the logs' clock
    q: Array  # (n, 3) rad, mm, mm
    q_dot: Array | None  # (n, 3) rad/s, mm/s, mm/s


@dataclass(frozen=True)
class ViewLog:
    time_s: Array  # (m,)
    uv: Array  # (m, P, 2), NaN where not found
    sigma: Array  # (m,) segmentation noise per axis, unit of the points


@dataclass(frozen=True)
class TruthLog:
    time_s: Array  # (k,)
    delta_L_rad: Array  # (k,)
    labels: dict[str, Array]  # label name -> (k,), NaN where unknown


@dataclass(frozen=True)
class LabLogs:
    """Everything a mapping file names, read and checked, with what was dropped."""

    unit: str
    joints: JointLog
    views: tuple[ViewLog, ...]  # in the order of tracker.io.recording.VIEWS
    truth: TruthLog | None
    files: dict[str, str]
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class ImportSummary:
    path: Path
    frames: int
    joint_samples: int
    duration_s: float
    warnings: list[str]


# ------------------------------------------------------------------------------ mapping
def _string(table: dict, key: str, where: str, default: str | None = None) -> str:
    value = table.get(key, default)
    if not isinstance(value, str) or not value:
        raise LabImportError(f"{where}: '{key}' must be a column name (a string), got {value!r}")
    return value


def _unit(table: dict, key: str, units: dict, where: str, default: str) -> float:
    name = table.get(key, default)
    if name not in units:
        raise LabImportError(f"{where}: '{key}' must be one of {', '.join(units)}, got {name!r}")
    return units[name]


def _section(mapping: dict, name: str, kind: str, source: str, required: bool) -> dict | None:
    table = mapping.get(name)
    where = f"{source} [{name}]"
    if table is None:
        if required:
            raise LabImportError(f"{source}: missing table [{name}]")
        return None
    if not isinstance(table, dict):
        raise LabImportError(f"{where}: expected a table")
    unknown = sorted(set(table) - _KEYS[kind])
    if unknown:
        known = ", ".join(sorted(_KEYS[kind]))
        raise LabImportError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {known})")
    if "file" not in table:
        raise LabImportError(f"{where}: missing key 'file' (the log to read)")
    return table


def load_mapping(path: str | Path) -> dict[str, Any]:
    """The parsed mapping file, its header checked, or one LabImportError."""
    path = Path(path)
    data = read_toml_file(path, LabImportError, "mapping")
    check_header(data, IMPORT_FORMAT, IMPORT_VERSION, str(path), LabImportError, "mapping")
    data.setdefault("unit", "px")
    if data["unit"] not in UNITS:
        raise LabImportError(f"{path}: 'unit' must be px or mm, got {data['unit']!r}")
    return data


# ------------------------------------------------------------------------------ logs
def _read(table: dict, base: Path, where: str) -> Table:
    file = table["file"]
    if not isinstance(file, str) or not file:
        raise LabImportError(f"{where}: 'file' must be a path, got {file!r}")
    return read_table(base / file)


def _times(log: Table, table: dict, where: str) -> Array:
    scale = _unit(table, "time_unit", TIME_UNITS_S, where, "s")
    return log.column(_string(table, "time", where, "time_s")) * scale


def _first_of_each_time(time_s: Array, what: str, warnings: list[str]) -> Array:
    """Indices that sort by time and keep the first sample of each repeated time stamp."""
    order = np.argsort(time_s, kind="stable")
    keep = np.concatenate([[True], np.diff(time_s[order]) > 0.0])
    if not keep.all():
        warnings.append(f"{what}: {np.count_nonzero(~keep)} repeated time stamp(s), first kept")
    return order[keep]


def _joint_log(table: dict, base: Path, where: str, warnings: list[str]) -> JointLog:
    log = _read(table, base, where)
    time_s = _times(log, table, where)
    angle = _unit(table, "q_r_unit", ANGLE_UNITS_RAD, where, "rad")
    scales = (angle, 1.0, 1.0)
    columns = [_string(table, key, where, default) for key, default in JOINT_DEFAULTS.items()]
    q = np.column_stack([log.column(c, finite=False) for c in columns]) * scales
    given = [key for key in RATE_KEYS if key in table]
    if given and len(given) != 3:
        rates = ", ".join(RATE_KEYS)
        raise LabImportError(f"{where}: give all three joint rates ({rates}) or none")
    q_dot = None
    if given:
        rates = [log.column(_string(table, key, where), finite=False) for key in RATE_KEYS]
        q_dot = np.column_stack(rates) * scales
    ok = np.all(np.isfinite(q), axis=-1)
    if not ok.any():
        raise LabImportError(f"{log.source}: no joint sample with all of {', '.join(columns)}")
    if not ok.all():
        warnings.append(
            f"{log.source}: {np.count_nonzero(~ok)} joint sample(s) with a missing value dropped"
        )
    keep = np.flatnonzero(ok)
    keep = keep[_first_of_each_time(time_s[keep], log.source, warnings)]
    return JointLog(time_s[keep], q[keep], None if q_dot is None else q_dot[keep])


def _view_log(
    view: str, table: dict, base: Path, n_points: int, where: str, warnings: list[str]
) -> ViewLog:
    log = _read(table, base, where)
    time_s = _times(log, table, where)
    names = table.get("points", [list(pair) for pair in point_columns(view, n_points)])
    if (
        not isinstance(names, list)
        or not all(isinstance(p, list) and len(p) == 2 for p in names)
        or not all(isinstance(c, str) for p in names for c in p)
    ):
        raise LabImportError(
            f"{where}: 'points' must be a list of [u, v] column-name pairs, got {names!r}"
        )
    if len(names) != n_points:
        raise LabImportError(
            f"{where}: 'points' lists {len(names)} point(s); the model has the tip and"
            f" {n_points - 1} marker(s): give {n_points} [u, v] pairs, the tip first"
        )
    uv = np.stack(
        [
            np.column_stack([log.column(u, finite=False), log.column(v, finite=False)])
            for u, v in names
        ],
        axis=1,
    )
    uv[~np.all(np.isfinite(uv), axis=-1)] = np.nan  # found only with both coordinates
    sigma = table.get("sigma", 1.0)
    if isinstance(sigma, str):
        sigma = log.column(sigma)
    elif not isinstance(sigma, int | float) or isinstance(sigma, bool):
        raise LabImportError(f"{where}: 'sigma' must be a number or a column name, got {sigma!r}")
    sigma = np.broadcast_to(np.asarray(sigma, dtype=float), time_s.shape).copy()
    if np.any(sigma <= 0.0) or not np.all(np.isfinite(sigma)):
        raise LabImportError(f"{where}: 'sigma' must be positive (noise per axis, {view} points)")
    keep = _first_of_each_time(time_s, log.source, warnings)
    return ViewLog(time_s[keep], uv[keep], sigma[keep])


def _truth_log(table: dict, base: Path, where: str) -> TruthLog:
    log = _read(table, base, where)
    time_s = _times(log, table, where)
    scale = _unit(table, "delta_L_unit", ANGLE_UNITS_RAD, where, "rad")
    delta_L = log.column(_string(table, "delta_L", where, "delta_L_rad"), finite=False) * scale
    labels = {}
    for key in LABEL_KEYS:
        if key in table:
            values = log.column(_string(table, key, where), finite=False)
            labels[key] = values * scale if key == "delta_1" else values
    order = np.argsort(time_s, kind="stable")
    return TruthLog(time_s[order], delta_L[order], {k: v[order] for k, v in labels.items()})


def read_lab_logs(mapping_path: str | Path, n_points: int) -> LabLogs:
    """Read and check every log a mapping file names.

    Parameters
    ----------
    mapping_path : str or Path
        The mapping TOML (see the module docstring).
    n_points : int
        Points per view and frame: the tip and the model's markers.
    """
    mapping_path = Path(mapping_path)
    mapping = load_mapping(mapping_path)
    base = mapping_path.parent
    source = str(mapping_path)
    warnings: list[str] = []
    files = {}
    joints_table = _section(mapping, "joints", "joints", source, required=True)
    files["joints"] = joints_table["file"]
    joints = _joint_log(joints_table, base, f"{source} [joints]", warnings)
    views = []
    for view in VIEWS:
        table = _section(mapping, view, "view", source, required=True)
        files[view] = table["file"]
        views.append(_view_log(view, table, base, n_points, f"{source} [{view}]", warnings))
    truth_table = _section(mapping, "truth", "truth", source, required=False)
    truth = None
    if truth_table is not None:
        files["truth"] = truth_table["file"]
        truth = _truth_log(truth_table, base, f"{source} [truth]")
    return LabLogs(mapping["unit"], joints, tuple(views), truth, files, warnings)


# ------------------------------------------------------------------------------ frames
def _stamps_ns(time_s: Array, t0_s: float) -> Array:
    return np.round((np.asarray(time_s, dtype=float) - t0_s) * 1e9).astype(np.int64)


def _truth_at(truth: TruthLog, stamps: Array, t0_s: float) -> tuple[Array, dict[str, Array]]:
    """delta_L at the frame stamps (exact, else interpolated inside the truth's span; NaN
    outside) and the labels of the truth sample at or before each stamp."""
    truth_stamps = _stamps_ns(truth.time_s, t0_s)
    index = np.searchsorted(truth_stamps, stamps, side="right") - 1
    exact = (index >= 0) & (truth_stamps[np.maximum(index, 0)] == stamps)
    known = np.isfinite(truth.delta_L_rad)
    delta_L = np.full(stamps.shape, np.nan)
    if known.any():
        t_known = truth_stamps[known].astype(float)
        unwrapped = np.unwrap(truth.delta_L_rad[known])
        inside = (stamps >= t_known[0]) & (stamps <= t_known[-1])
        delta_L[inside] = wrap_angle(np.interp(stamps[inside].astype(float), t_known, unwrapped))
    delta_L[exact] = truth.delta_L_rad[index[exact]]
    labels = {}
    for name, values in truth.labels.items():
        labels[name] = np.where(index >= 0, values[np.maximum(index, 0)], np.nan)
    return delta_L, labels


def _frame_labels(labels: dict[str, Array], i: int) -> FrameLabels:
    def number(name: str, integer: bool = False):
        values = labels.get(name)
        if values is None or not np.isfinite(values[i]):
            return None
        return int(values[i]) if integer else float(values[i])

    return FrameLabels(
        plane=number("plane", True),
        configuration=number("configuration", True),
        deflection_mm=number("deflection_mm"),
        noise_level=number("noise_level"),
        delta_1_true_rad=number("delta_1"),
    )


def lab_frames(logs: LabLogs, t0_s: float) -> tuple[Array, list[Frame], list[FrameLabels]]:
    """The frames of the logs: one per distinct time stamp of either view.

    A view without a sample at a frame's time has its points missing there. The frames'
    joint values are not set (NaN): a recording keeps the joint stream and the reader
    interpolates it.

    Returns
    -------
    stamps_ns : array of int64, shape (F,)
        Frame times, ns after ``t0_s``.
    frames, labels : lists of length F
    """
    view_stamps = [_stamps_ns(view.time_s, t0_s) for view in logs.views]
    stamps = np.unique(np.concatenate(view_stamps))
    n_points = logs.views[0].uv.shape[1]
    per_view = []
    for view, own in zip(logs.views, view_stamps, strict=True):
        uv = np.full((stamps.size, n_points, 2), np.nan)
        cov = np.full((stamps.size, n_points, 2, 2), np.nan)
        rows = np.searchsorted(stamps, own)
        uv[rows] = view.uv
        cov[rows] = view.sigma[:, None, None, None] ** 2 * np.eye(2)
        per_view.append((uv, cov))
    if logs.truth is not None:
        delta_L, labels = _truth_at(logs.truth, stamps, t0_s)
    else:
        delta_L, labels = np.full(stamps.shape, np.nan), {}
    frames, frame_labels = [], []
    for i, stamp in enumerate(stamps.tolist()):
        frames.append(
            Frame(
                time_s=stamp / 1e9,
                q=np.full(3, np.nan),
                q_dot=None,
                uv=tuple(uv[i] for uv, _ in per_view),
                cov=tuple(cov[i] for _, cov in per_view),
                delta_L_true_rad=float(delta_L[i]) if np.isfinite(delta_L[i]) else None,
            )
        )
        frame_labels.append(_frame_labels(labels, i))
    return stamps, frames, frame_labels


def write_lab_recording(
    path: str | Path,
    logs: LabLogs,
    model_toml: str,
    rig_toml: str,
    settings: dict[str, Any] | None = None,
) -> ImportSummary:
    """Write the logs as a recording: the joint stream and, in time order, every frame.

    Joint samples are written up to each frame's time before the frame, as a live recording
    has them, so the file is in time order.
    """
    times = [logs.joints.time_s] + [view.time_s for view in logs.views]
    if logs.truth is not None:
        times.append(logs.truth.time_s)
    t0_s = float(min(t.min() for t in times if t.size))
    stamps, frames, labels = lab_frames(logs, t0_s)
    joint_stamps = _stamps_ns(logs.joints.time_s, t0_s)
    q, q_dot = logs.joints.q, logs.joints.q_dot
    start_ns = int(round(t0_s * 1e9)) if t0_s >= 0.0 else 0
    with RecordingWriter(
        path,
        model_toml=model_toml,
        rig_toml=rig_toml,
        settings=settings,
        point_unit=logs.unit,
        start_time_ns=start_ns,
    ) as writer:
        done = 0
        for stamp, frame, label in zip(stamps.tolist(), frames, labels, strict=True):
            upto = int(np.searchsorted(joint_stamps, stamp, side="right"))
            if upto > done:
                rates = None if q_dot is None else q_dot[done:upto]
                writer.write_joints(joint_stamps[done:upto] / 1e9, q[done:upto], rates)
                done = upto
            writer.write_frame(frame, label)
        if done < joint_stamps.size:
            rates = None if q_dot is None else q_dot[done:]
            writer.write_joints(joint_stamps[done:] / 1e9, q[done:], rates)
    last = max(int(joint_stamps[-1]), int(stamps[-1]) if stamps.size else 0)
    return ImportSummary(Path(path), len(frames), int(joint_stamps.size), last / 1e9, logs.warnings)
