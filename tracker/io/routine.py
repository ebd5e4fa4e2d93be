"""The registration routine and its observations as tables (``cathtrack register``).

The routine (what the robot runs) is a CSV table ``step, q_r_rad, q_p_mm, q_d_mm``. Its
observations (what the rig saw) are a table (CSV or MATLAB .mat, :mod:`tracker.io.tables`)
with one row per image pair:

    q_r_rad, q_p_mm, q_d_mm,
    front_tip_u, front_tip_v, front_marker0_u, front_marker0_v, ...,
    side_tip_u, side_tip_v, side_marker0_u, side_marker0_v, ...

points in the rig's image unit (px for cameras, mm for planes), the tip first and then the
model's markers in the order of its ``marker_arclengths_mm``; empty or ``nan`` for a point not
found. Several rows per step (several image pairs) average the segmentation noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from tracker.io.tables import TableError, point_columns, read_table, write_csv
from tracker.types import Frame

Array = np.ndarray

JOINT_COLUMNS = ("q_r_rad", "q_p_mm", "q_d_mm")


def write_routine(path: str | Path, q: Array, comment: str = "") -> Path:
    """The routine's joint configurations (n, 3) as CSV, one numbered step per row."""
    q = np.asarray(q, dtype=float)
    columns = {"step": np.arange(1, q.shape[0] + 1)}
    columns.update({name: q[:, k] for k, name in enumerate(JOINT_COLUMNS)})
    return write_csv(path, columns, comment)


def read_routine(path: str | Path) -> Array:
    """Joint configurations (n, 3) of a routine file, in step order."""
    table = read_table(path)
    q = np.column_stack([table.column(name) for name in JOINT_COLUMNS])
    if table.has("step"):
        q = q[np.argsort(table.column("step"), kind="stable")]
    return q


def observations_from_frames(frames: Sequence[Frame]) -> tuple[Array, tuple[Array, ...]]:
    """Joint values (n, 3) and per view the points (n, P, 2) of frames (e.g. a recording's)."""
    q = np.array([frame.q for frame in frames])
    n_views = frames[0].n_views if frames else 2
    return q, tuple(np.array([frame.uv[k] for frame in frames]) for k in range(n_views))


def observation_columns(
    q: Array, uv: tuple[Array, ...], views: tuple[str, ...]
) -> dict[str, Array]:
    """The columns of an observation table: joints (n, 3), per view points (n, P, 2)."""
    columns = {name: np.asarray(q, float)[:, k] for k, name in enumerate(JOINT_COLUMNS)}
    for view, points in zip(views, uv, strict=True):
        points = np.asarray(points, dtype=float)
        for k, (u, v) in enumerate(point_columns(view, points.shape[1])):
            columns[u], columns[v] = points[:, k, 0], points[:, k, 1]
    return columns


def write_observations(
    path: str | Path,
    q: Array,
    uv: tuple[Array, ...],
    views: tuple[str, ...] = ("front", "side"),
    comment: str = "",
) -> Path:
    """Write the observations of a routine (see the module docstring) as CSV."""
    return write_csv(path, observation_columns(q, uv, views), comment)


def read_observations(
    path: str | Path, n_points: int, views: tuple[str, ...] = ("front", "side")
) -> tuple[Array, tuple[Array, ...]]:
    """Joint values (n, 3) and per view the points (n, n_points, 2) of an observation table.

    Raises
    ------
    TableError
        One line naming the file and the column: a missing column, a missing joint value.
    """
    table = read_table(path)
    q = np.column_stack([table.column(name) for name in JOINT_COLUMNS])
    uv = []
    for view in views:
        names = point_columns(view, n_points)
        points = np.stack(
            [
                np.column_stack([table.column(u, finite=False), table.column(v, finite=False)])
                for u, v in names
            ],
            axis=1,
        )
        # A point is found when both of its coordinates are.
        points[~np.all(np.isfinite(points), axis=-1)] = np.nan
        uv.append(points)
    if not any(np.isfinite(points).any() for points in uv):
        raise TableError(f"{table.source}: no point was found in any row")
    return q, tuple(uv)
