"""Measured-shape files for ``cathtrack fit-model`` and the model file it writes (docs/setup.md).

A shape file is a table (:mod:`tracker.io.tables`: CSV or MATLAB .mat) with one row per
measured sample and a ``shape`` column numbering the configurations. Two kinds:

Backbone points in the base frame {B} (taken with delta_L = 0, so that ``q_r`` is the bending
plane; the convention of ``cathtrack register``):

    shape, q_r_rad, q_p_mm, q_d_mm, s_mm, x_mm, y_mm, z_mm

Tangent angles of each segment in its own plane (straight: pi/2 rad, 90 deg), ``segment``
1 (proximal) or 2 (distal), ``s_mm`` from that segment's base:

    shape, q_p_mm, q_d_mm, segment, s_mm, theta_rad      (or theta_deg)

Every shape must be measured at the same arclengths (per segment, for angles). Each problem
ends in one ValueError naming the file and the column or the shape.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.catheter import Catheter
from models.modal import ModalSegment, PowerBasis
from models.model_file import MODEL_FORMAT, MODEL_VERSION
from models.rig_file import toml_value
from models.shape_fit import AngleShapes, PointShapes, Shapes
from tracker.io.tables import Table, TableError, read_table, write_csv

Array = np.ndarray

POINT_COLUMNS = ("shape", "q_r_rad", "q_p_mm", "q_d_mm", "s_mm", "x_mm", "y_mm", "z_mm")
ANGLE_COLUMNS = ("shape", "q_p_mm", "q_d_mm", "segment", "s_mm", "theta_rad")
_SAME_ARCLENGTH_MM = 1e-9


def _groups(key: Array) -> list[Array]:
    """Row indices of each distinct value of ``key``, in order of the values."""
    values, inverse = np.unique(key, return_inverse=True)
    return [np.flatnonzero(inverse == k) for k in range(values.size)]


def _constant_joints(table: Table, rows: Array, names: tuple[str, ...], shape: float) -> list:
    out = []
    for name in names:
        values = table.columns[name][rows]
        if np.ptp(values) > 0.0:
            raise TableError(
                f"{table.source}: shape {shape:g} has different '{name}' values in its rows"
                f" ({table.where(int(rows[0]))} and others); one configuration per shape"
            )
        out.append(float(values[0]))
    return out


def _common_arclengths(table: Table, groups: list[Array]) -> Array:
    """The arclengths of the first group, or a TableError for a group with others."""
    s = table.columns["s_mm"]
    first = np.sort(s[groups[0]])
    for rows in groups:
        if np.unique(s[rows]).size != rows.size:
            raise TableError(
                f"{table.source}: the shape at {table.where(int(rows[0]))} repeats an arclength"
            )
    for rows in groups[1:]:
        here = np.sort(s[rows])
        if here.shape != first.shape or np.max(np.abs(here - first)) > _SAME_ARCLENGTH_MM:
            raise TableError(
                f"{table.source}: the shape at {table.where(int(rows[0]))} is measured at"
                f" arclengths {np.round(here, 6).tolist()} mm, the first at"
                f" {np.round(first, 6).tolist()} mm; every shape needs the same arclengths"
            )
    return first


def _point_shapes(table: Table) -> PointShapes:
    for name in POINT_COLUMNS:
        table.column(name)
    groups = _groups(table.columns["shape"])
    s = _common_arclengths(table, groups)
    q, points = [], []
    for rows in groups:
        shape = float(table.columns["shape"][rows[0]])
        q.append(_constant_joints(table, rows, ("q_r_rad", "q_p_mm", "q_d_mm"), shape))
        rows = rows[np.argsort(table.columns["s_mm"][rows])]
        points.append(np.column_stack([table.columns[c][rows] for c in ("x_mm", "y_mm", "z_mm")]))
    try:
        return PointShapes(np.array(q), s, np.array(points))
    except ValueError as exc:
        raise TableError(f"{table.source}: {exc}") from None


def _angle_shapes(table: Table) -> AngleShapes:
    unit = "theta_rad" if table.has("theta_rad") else "theta_deg"
    for name in ANGLE_COLUMNS[:-1] + (unit,):
        table.column(name)
    theta_all = table.columns[unit] * (1.0 if unit == "theta_rad" else np.pi / 180.0)
    segment = table.columns["segment"]
    bad = np.flatnonzero((segment != 1) & (segment != 2))
    if bad.size:
        raise TableError(
            f"{table.source}: column 'segment' must be 1 (proximal) or 2 (distal), got"
            f" {segment[bad[0]]:g} at {table.where(int(bad[0]))}"
        )
    shape_groups = _groups(table.columns["shape"])
    q = [
        [0.0]
        + _constant_joints(
            table, rows, ("q_p_mm", "q_d_mm"), float(table.columns["shape"][rows[0]])
        )
        for rows in shape_groups
    ]
    arclengths, thetas = [], []
    for k in (1, 2):
        per_shape = [rows[segment[rows] == k] for rows in shape_groups]
        if any(rows.size == 0 for rows in per_shape):
            name = ("proximal", "distal")[k - 1]
            raise TableError(
                f"{table.source}: a shape has no angles of the {name} segment (segment = {k});"
                " every shape needs angles of both segments"
            )
        arclengths.append(_common_arclengths(table, per_shape))
        by_arclength = [rows[np.argsort(table.columns["s_mm"][rows])] for rows in per_shape]
        thetas.append(np.array([theta_all[rows] for rows in by_arclength]))
    try:
        return AngleShapes(np.array(q), tuple(arclengths), tuple(thetas))
    except ValueError as exc:
        raise TableError(f"{table.source}: {exc}") from None


def read_shapes(path: str | Path) -> Shapes:
    """Measured shapes from a CSV or .mat file (see the module docstring)."""
    table = read_table(path)
    if table.has("x_mm") or table.has("y_mm") or table.has("z_mm"):
        return _point_shapes(table)
    if table.has("theta_rad") or table.has("theta_deg"):
        return _angle_shapes(table)
    raise TableError(
        f"{table.source}: neither backbone points ({', '.join(POINT_COLUMNS)}) nor tangent"
        f" angles ({', '.join(ANGLE_COLUMNS)}); columns found: {', '.join(table.columns)}"
    )


def shape_columns(shapes: Shapes) -> dict[str, Array]:
    """The columns of a shape file for ``shapes`` (one row per sample)."""
    n = shapes.n_shapes
    if isinstance(shapes, PointShapes):
        n_s = shapes.arclength_mm.size
        rows = np.repeat(np.arange(n), n_s)
        points = shapes.points_b_mm.reshape(-1, 3)
        return {
            "shape": rows,
            "q_r_rad": shapes.q[rows, 0],
            "q_p_mm": shapes.q[rows, 1],
            "q_d_mm": shapes.q[rows, 2],
            "s_mm": np.tile(shapes.arclength_mm, n),
            "x_mm": points[:, 0],
            "y_mm": points[:, 1],
            "z_mm": points[:, 2],
        }
    parts = []
    for k in (0, 1):
        s = shapes.arclength_mm[k]
        rows = np.repeat(np.arange(n), s.size)
        parts.append(
            {
                "shape": rows,
                "q_p_mm": shapes.q[rows, 1],
                "q_d_mm": shapes.q[rows, 2],
                "segment": np.full(rows.size, k + 1),
                "s_mm": np.tile(s, n),
                "theta_rad": shapes.theta_rad[k].ravel(),
            }
        )
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def write_shapes(path: str | Path, shapes: Shapes, comment: str = "") -> Path:
    """Write a shape file that :func:`read_shapes` reads back (CSV)."""
    return write_csv(path, shape_columns(shapes), comment)


# ------------------------------------------------------------------------------ model file
def _basis_name(basis) -> str:
    if type(basis) is not PowerBasis:
        raise ValueError(f"only power bases can be written to a model file, got {basis!r}")
    return "power"


def _segment_lines(name: str, segment: ModalSegment, joint: str) -> list[str]:
    rows = ",\n".join(f"  {toml_value(row)}" for row in np.asarray(segment.A).tolist())
    return [
        "",
        f"[{name}]                              # driven by {joint} (mm)",
        f"length_mm = {toml_value(float(segment.length_mm))}",
        f'psi = {{ basis = "{_basis_name(segment.psi)}", size = {segment.psi.size} }}',
        f'eta = {{ basis = "{_basis_name(segment.eta)}", size = {segment.eta.size} }}',
        f"A = [\n{rows},\n]",
    ]


def model_toml(catheter: Catheter, comment: str = "") -> str:
    """The text of a model file (docs/model-file.md) that ``models.load_catheter`` reads back."""
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [
        "# Units: mm and rad. theta_i(s, q) = psi(s / L)^T A eta(q), rows of A follow psi.",
        f'format = "{MODEL_FORMAT}"',
        f"version = {MODEL_VERSION}",
        f"delta_2_rad = {toml_value(float(catheter.delta_2_rad))}",
        f"marker_arclengths_mm = {toml_value([float(s) for s in catheter.marker_arclengths_mm])}",
        f"quadrature_order = {int(catheter.quadrature_order)}",
    ]
    lines += _segment_lines("proximal", catheter.proximal, "q_p")
    lines += _segment_lines("distal", catheter.distal, "q_d")
    return "\n".join(lines) + "\n"


def write_model(path: str | Path, catheter: Catheter, comment: str = "") -> Path:
    """Write a model file; OSError naming it if it cannot be written."""
    path = Path(path)
    try:
        path.write_text(model_toml(catheter, comment), encoding="utf-8")
    except OSError as exc:
        raise OSError(f"cannot write model file {path}: {exc.strerror or exc}") from None
    return path
