"""Bi-plane rig files (TOML): reading and writing (docs/design.md sections 4 and 7).

The format is documented in docs/vision.md. A rig file holds, per view (``[front]`` and
``[side]``), a calibrated pinhole camera in OpenCV's conventions (image size, intrinsics,
distortion, pose of {W} in the camera) and the normal ``normal_w`` of the imaging plane that
the paper's orthographic model needs (the direction from the scene toward the camera), or the
plane alone; optionally the registered pose of the catheter base in ``[base]``.
:func:`load_rig` builds a :class:`models.imaging.Rig` of either kind from it,
:func:`base_from_dict` the base :class:`models.pose.Pose`, and :func:`rig_toml` writes the
text (the callers write the file: calibration, recordings).

It also holds the small geometric helpers that relate a far pinhole view to its orthographic
plane.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from models.imaging import DEFAULT_VIEW_NAMES, OrthographicPlane, PinholeView, Rig
from models.model_file import check_header, read_toml_file
from models.pose import Pose

Array = np.ndarray

RIG_FORMAT = "cathtrack-rig"
RIG_VERSION = 1
VIEW_NAMES = DEFAULT_VIEW_NAMES  # a file without a ``views`` list: the bi-plane rig
MAX_VIEWS = 8
RESERVED_TABLES = frozenset({"base", "calibration", "registration", "format", "version", "views"})
ROTATION_TOLERANCE = 1e-3
MODELS = ("pinhole", "orthographic")
NORMAL_TOLERANCE_RAD = 1e-3
"""How far ``normal_w`` may be from the camera's viewing direction when both are given."""

# Limits of a plausible rig: values outside are typing or calibration errors, refused with one
# line naming the file and the key (a distortion k1 = 1e30 gave confident estimates 85 deg
# off; a base 1e300 mm away no estimate at all).
MAX_DISTANCE_MM = 1e5
"""Cameras and the catheter base are within 100 m of the world origin."""
IMAGE_SIZE_RANGE_PX = (1, 1 << 16)
FOCAL_LENGTH_RANGE_PX = (1.0, 1e6)
MAX_DISTORTION_COEFFICIENT = 1e9
"""|k1|, |k2|, |k3| at most this (a narrow lens's calibration may give k3 in the thousands:
the coefficients matter only through what they do within the image, checked next)."""
MAX_DISTORTION_SCALE = 3.0
"""Within the image, radial distortion scales the radius by between 1/3 and 3."""
MAX_TANGENTIAL_DISTORTION = 0.5
"""|p1|, |p2| at most this (real lenses: below 0.01)."""
ROTATION_RANGE_RAD = (-2 * np.pi, 2 * np.pi)


class RigFileError(ValueError):
    """A rig file that cannot be read or does not describe a valid rig."""


def _is_number(x: Any) -> bool:
    """A TOML integer or float; a boolean is not a number."""
    return isinstance(x, int | float) and not isinstance(x, bool)


def _shape_of(value: Any) -> tuple[int, ...] | None:
    """The shape of nested lists of numbers (None: not a regular array of numbers)."""
    if _is_number(value):
        return ()
    if not isinstance(value, list) or not value:
        return None
    shapes = {_shape_of(v) for v in value}
    if len(shapes) != 1 or None in shapes:
        return None
    return (len(value), *shapes.pop())


def _array(
    table: dict[str, Any],
    key: str,
    shape: tuple[int, ...],
    where: str,
    max_abs: float | None = None,
    unit: str = "",
) -> Array:
    """``table[key]`` as floats of the given shape: numbers only (a boolean or a string is
    not), finite, and of magnitude at most ``max_abs``."""
    if key not in table:
        raise RigFileError(f"{where}: missing key '{key}'")
    value = table[key]
    found = _shape_of(value)
    if found is None:
        raise RigFileError(
            f"{where}: '{key}' must be numbers of shape {shape}, got {_short(value)}"
        )
    if found != shape:
        raise RigFileError(f"{where}: '{key}' must have shape {shape}, got {found}")
    array = np.array(value, dtype=float)
    if not np.all(np.isfinite(array)):
        raise RigFileError(f"{where}: '{key}' contains non-finite values")
    if max_abs is not None and np.max(np.abs(array), initial=0.0) > max_abs:
        raise RigFileError(
            f"{where}: '{key}' must be at most {max_abs:g}{unit} in magnitude, got"
            f" {np.max(np.abs(array)):.3g}{unit}"
        )
    return array


def _one_line(error: BaseException) -> str:
    """An error's message on one line (numpy prints matrices over several)."""
    return " ".join(str(error).split())


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _check_intrinsics(K: Array, dist: Array, size: tuple[int, int], where: str) -> None:
    """Focal lengths, principal point and distortion within the limits of a real camera."""
    low, high = FOCAL_LENGTH_RANGE_PX
    for name, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not low <= f <= high:
            raise RigFileError(
                f"{where}: K focal length {name} must be in [{low:g}, {high:g}] px, got {f:.6g}"
            )
    width, height = size
    for name, c, n in (("cx", K[0, 2], width), ("cy", K[1, 2], height)):
        if not -n <= c <= 2 * n:
            raise RigFileError(
                f"{where}: K principal point {name} = {c:.6g} px is more than an image size"
                f" ({n} px) outside the image"
            )
    radial, tangential = dist[[0, 1, 4]], dist[2:4]
    if np.max(np.abs(radial)) > MAX_DISTORTION_COEFFICIENT:
        raise RigFileError(
            f"{where}: dist radial coefficients k1, k2, k3 must be at most"
            f" {MAX_DISTORTION_COEFFICIENT:g} in magnitude, got {radial.tolist()}"
        )
    if np.max(np.abs(tangential)) > MAX_TANGENTIAL_DISTORTION:
        raise RigFileError(
            f"{where}: dist tangential coefficients p1, p2 must be at most"
            f" {MAX_TANGENTIAL_DISTORTION:g} in magnitude, got {tangential.tolist()}"
        )
    problem = _radial_problem(K, radial, size)
    if problem is not None:
        raise RigFileError(f"{where}: dist is not valid over the whole image: {problem}")


def _radial_problem(K: Array, radial: Array, size: tuple[int, int]) -> str | None:
    """Why the radial distortion does not map the image one to one, or None.

    The distorted radius ``r_d(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` (normalised
    coordinates) must grow until it reaches the image's farthest corner, else pixels there
    undistort to two rays (the image folds over) or to none; and on the way it must stay
    within a factor :data:`MAX_DISTORTION_SCALE` of ``r`` (a k1 of 1e30 gave estimates 85 deg
    off with confident error bars).
    """
    if not np.any(radial):
        return None
    k1, k2, k3 = radial
    width, height = size
    corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]])
    reach = float(np.max(np.linalg.norm((corners - K[:2, 2]) / np.diag(K)[:2], axis=1)))
    r = np.linspace(0.0, (MAX_DISTORTION_SCALE + 0.1) * reach, 4001)[1:]
    r2 = r * r
    scale = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    slope = 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))
    r_d = r * scale
    inside = np.flatnonzero(r_d >= reach)
    if not inside.size:
        return f"it shrinks the image corner's radius {reach:.3g} (normalised) more than 3-fold"
    within = slice(0, inside[0] + 1)
    falling = np.flatnonzero(slope[within] <= 0)
    if falling.size:
        return (
            f"the distorted radius stops growing at {r_d[falling[0]]:.3g} (normalised), short"
            f" of the image corner at {reach:.3g}: the image folds over"
        )
    worst = float(np.max(np.abs(np.log(scale[within]))))
    if worst > np.log(MAX_DISTORTION_SCALE):
        return (
            f"it scales radii within the image by up to {np.exp(worst):.3g}"
            f" (at most {MAX_DISTORTION_SCALE:g} for a real lens)"
        )
    return None


def _image_size(table: dict[str, Any], where: str) -> tuple[int, int]:
    size = table.get("image_size")
    low, high = IMAGE_SIZE_RANGE_PX
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(n, int) and not isinstance(n, bool) for n in size)
        or not all(low <= n <= high for n in size)
    ):
        raise RigFileError(
            f"{where}: image_size must be [width, height], integers in [{low}, {high}] px, got"
            f" {_short(size)}"
        )
    return size[0], size[1]


def camera_from_table(table: Any, where: str) -> PinholeView:
    """A pinhole view from one ``[front]`` / ``[side]`` table (validated)."""
    if not isinstance(table, dict):
        raise RigFileError(f"{where}: expected a table")
    size = _image_size(table, where)
    K = _array(table, "K", (3, 3), where)
    dist = _array(table, "dist", (5,), where) if "dist" in table else np.zeros(5)
    R = _array(table, "R_cam_w", (3, 3), where, max_abs=1.0 + ROTATION_TOLERANCE)
    t = _array(table, "t_cam_w", (3,), where, max_abs=MAX_DISTANCE_MM, unit=" mm")
    _check_intrinsics(K, dist, size, where)
    try:
        view = PinholeView(K, R, t, dist, size)
    except ValueError as exc:
        raise RigFileError(f"{where}: {_one_line(exc)}") from None
    if "normal_w" in table:
        n = _unit_normal(table, where)
        angle = np.arccos(np.clip(n @ -view.R_cam_w[2], -1.0, 1.0))
        if angle > NORMAL_TOLERANCE_RAD:
            raise RigFileError(
                f"{where}: normal_w is {np.degrees(angle):.3g} deg away from the camera's"
                " viewing direction (-R_cam_w[2]); they must agree"
            )
    return view


def _unit_normal(table: dict[str, Any], where: str) -> Array:
    n = _array(table, "normal_w", (3,), where, max_abs=1e6)
    norm = np.linalg.norm(n)
    if norm < 1e-12:
        raise RigFileError(f"{where}: normal_w must be a non-zero vector")
    return n / norm


def orthographic_plane(view: PinholeView) -> OrthographicPlane:
    """The orthographic plane of a pinhole view: image right, image up, toward the camera.

    Columns of ``R_w_view`` are the camera's x axis, minus its y axis (rows grow downward)
    and minus its optical axis, in {W}.
    """
    R = np.asarray(view.R_cam_w)
    return OrthographicPlane(np.column_stack([R[0], -R[1], -R[2]]))


def orthographic_rig(rig: Rig) -> Rig:
    """The orthographic (far-source) approximation of a pinhole rig."""
    if rig.kind != "pinhole":
        return rig
    return Rig(*(orthographic_plane(view) for view in rig.views), names=rig.names)


def plane_from_pixels(view: PinholeView, uv: Array, cov: Array | None = None):
    """In-plane coordinates (mm) of the orthographic plane from a far view's pixels.

    For a camera far from the scene every point is at about the depth ``t_z`` of the world
    origin, so ``(R x)_x = (u - c_x) t_z / f_x - t_x`` and likewise for y with the sign of
    image-up. The error of this limit is of the order of (scene depth / t_z).

    Parameters
    ----------
    view : PinholeView
    uv : array (..., 2)
        Distorted pixels (NaN rows pass through).
    cov : array (..., 2, 2), optional
        Their covariance, px^2; returned in mm^2.

    Returns
    -------
    uv_mm : array (..., 2), and cov_mm (..., 2, 2) when cov was given.
    """
    uv = np.asarray(uv, dtype=float)
    finite = np.all(np.isfinite(uv), axis=-1)
    ideal = np.full_like(uv, np.nan)
    if finite.any():
        ideal[finite] = view.undistort(uv[finite])
    K, t = np.asarray(view.K), np.asarray(view.t_cam_w)
    depth = t[2]
    if depth <= 0:
        raise ValueError("the world origin is behind the camera: no orthographic plane")
    sx, sy = depth / K[0, 0], depth / K[1, 1]
    out = np.stack(
        [(ideal[..., 0] - K[0, 2]) * sx - t[0], -((ideal[..., 1] - K[1, 2]) * sy - t[1])], axis=-1
    )
    if cov is None:
        return out
    S = np.diag([sx, -sy])
    return out, S @ np.asarray(cov, dtype=float) @ S


def rig_from_dict(data: dict[str, Any], source: str = "rig", model: str = "pinhole") -> Rig:
    """Build and validate a rig from parsed TOML tables.

    Parameters
    ----------
    model : {"pinhole", "orthographic"}
        Pinhole views as calibrated, or the orthographic planes of the paper's model (from
        the cameras' axes, or from ``normal_w`` alone for a rig of planes only).
    """
    if model not in MODELS:
        raise ValueError(f"unknown rig model {model!r}; use one of {', '.join(MODELS)}")
    check_header(data, RIG_FORMAT, RIG_VERSION, source, RigFileError, "rig")
    names = view_names(data, source)
    views = []
    for name in names:
        where = f"{source} [{name}]"
        table = data.get(name)
        if table is None:
            raise RigFileError(f"{source}: missing table [{name}]")
        has_camera = isinstance(table, dict) and "K" in table
        if model == "pinhole" or has_camera:
            if not has_camera:
                raise RigFileError(
                    f"{where}: no camera (K, R_cam_w, t_cam_w): this rig file only has plane"
                    " normals, load it with model='orthographic'"
                )
            camera = camera_from_table(table, where)
            views.append(camera if model == "pinhole" else orthographic_plane(camera))
        else:
            if not isinstance(table, dict):
                raise RigFileError(f"{where}: expected a table")
            angle = table.get("in_plane_rotation_rad", 0.0)
            low, high = ROTATION_RANGE_RAD
            if not _is_number(angle) or not low <= angle <= high:
                raise RigFileError(
                    f"{where}: in_plane_rotation_rad must be a number in [{low:.6g},"
                    f" {high:.6g}] rad, got {_short(angle)}"
                )
            try:
                views.append(OrthographicPlane.from_normal(_unit_normal(table, where), angle))
            except ValueError as exc:
                raise RigFileError(f"{where}: {_one_line(exc)}") from None
    try:
        return Rig(*views, names=names)
    except ValueError as exc:
        raise RigFileError(f"{source}: {_one_line(exc)}") from None


def view_names(data: dict[str, Any], source: str = "rig") -> tuple[str, ...]:
    """The rig's view names: the ``views`` list, or ``front`` and ``side`` without one."""
    names = data.get("views", list(VIEW_NAMES))
    if (
        not isinstance(names, list)
        or not 2 <= len(names) <= MAX_VIEWS
        or not all(isinstance(n, str) and n.isidentifier() for n in names)
        or len(set(names)) != len(names)
        or set(names) & RESERVED_TABLES
    ):
        raise RigFileError(
            f"{source}: 'views' must list 2 to {MAX_VIEWS} distinct view names (identifiers,"
            f" not {', '.join(sorted(RESERVED_TABLES))}), got {names!r}"
        )
    return tuple(names)


def read_rig_file(path: str | Path) -> dict[str, Any]:
    """The parsed TOML of a rig file, or one RigFileError naming the file and the problem."""
    return read_toml_file(path, RigFileError, "rig")


def load_rig(path: str | Path, model: str = "pinhole") -> Rig:
    """Read a calibrated rig from a TOML file (see docs/vision.md).

    Raises
    ------
    RigFileError
        One message naming the file and the problem: unreadable file, malformed TOML, a
        missing or invalid key, inconsistent normals, coincident cameras.
    """
    return rig_from_dict(read_rig_file(path), str(path), model)


def written_model(data: dict[str, Any], source: str = "rig") -> str:
    """The model a rig was written as: ``"pinhole"`` where its views have cameras (``K``),
    ``"orthographic"`` for planes only."""
    first = data.get(view_names(data, source)[0])
    return "pinhole" if isinstance(first, dict) and "K" in first else "orthographic"


def base_from_dict(data: dict[str, Any], source: str = "rig") -> Pose | None:
    """The registered base pose of the ``[base]`` table (``R_w_b``, ``o_b_w_mm``), if any.

    Raises
    ------
    RigFileError
        A ``[base]`` table without a 3x3 rotation ``R_w_b`` and a 3-vector ``o_b_w_mm``.
    """
    base = data.get("base")
    if base is None:
        return None
    where = f"{source} [base]"
    if not isinstance(base, dict):
        raise RigFileError(f"{where}: expected a table")
    R_w_b = _array(base, "R_w_b", (3, 3), where, max_abs=1.0 + ROTATION_TOLERANCE)
    o_b_w_mm = _array(base, "o_b_w_mm", (3,), where, max_abs=MAX_DISTANCE_MM, unit=" mm")
    # A rotation typed by hand (or rounded when written) is orthonormal to a few digits only:
    # within ROTATION_TOLERANCE it is replaced by the nearest rotation; beyond, it is refused.
    U, _, Vt = np.linalg.svd(R_w_b)
    nearest = U @ Vt
    if np.linalg.det(nearest) < 0 or np.max(np.abs(nearest - R_w_b)) > ROTATION_TOLERANCE:
        raise RigFileError(
            f"{where}: R_w_b is not a rotation matrix (orthonormal with det +1 to within"
            f" {ROTATION_TOLERANCE:g})"
        )
    try:
        return Pose(nearest, o_b_w_mm)
    except ValueError as exc:
        raise RigFileError(f"{where}: {_one_line(exc)}") from None


def rig_from_toml(
    text: str, source: str = "rig", model: str | None = None
) -> tuple[Rig, Pose | None]:
    """The rig and the registered base pose (None without ``[base]``) of rig file text.

    ``model`` None reads the views as written (:func:`written_model`).
    """
    try:
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise RigFileError(f"{source}: malformed TOML: {_one_line(exc)}") from None
    rig = rig_from_dict(data, source, model or written_model(data, source))
    return rig, base_from_dict(data, source)


# ------------------------------------------------------------------------------- writing
def toml_value(x) -> str:
    """A TOML value: strings, booleans, integers, floats (``repr``: read back exactly), arrays."""
    if isinstance(x, str):
        return json.dumps(x)
    if isinstance(x, bool | np.bool_):
        return "true" if x else "false"
    if isinstance(x, int | np.integer):
        return str(int(x))
    if isinstance(x, float | np.floating):
        return repr(float(x))
    return "[" + ", ".join(toml_value(v) for v in np.asarray(x).tolist()) + "]"


def _view_table(view) -> dict[str, Any]:
    if isinstance(view, OrthographicPlane):
        n = view.normal_w
        reference = OrthographicPlane.from_normal(n).R_w_view
        u = np.asarray(view.R_w_view)[:, 0]
        angle = float(np.arctan2(u @ reference[:, 1], u @ reference[:, 0]))
        return {"normal_w": n, "in_plane_rotation_rad": angle}
    return {
        "image_size": [int(n) for n in view.image_size],
        "K": view.K,
        "dist": view.dist,
        "R_cam_w": view.R_cam_w,
        "t_cam_w": view.t_cam_w,
        "normal_w": -np.asarray(view.R_cam_w)[2],
    }


def rig_toml(
    rig: Rig,
    base: Pose | None = None,
    comment: str = "",
    extra: Mapping[str, Mapping[str, Any]] | None = None,
) -> str:
    """The text of a rig file (docs/vision.md) that :func:`rig_from_toml` reads back.

    Pinhole views are written as calibrated cameras (with the ``normal_w`` of their plane),
    orthographic planes by their normal and in-plane rotation. Floats are written with
    ``repr``, so reading the text back gives the same numbers (planes up to rounding of the
    in-plane rotation).

    Parameters
    ----------
    rig : Rig
    base : Pose, optional
        The registered pose of the catheter base, written as ``[base]``.
    comment : str
        Lines written as TOML comments at the top.
    extra : mapping of table name to mapping, optional
        More keys: those of a view's name end that view's table; other tables (e.g. the
        ``[calibration]`` residuals) are written before the views.
    """
    extra = dict(extra or {})
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += ["# Units: mm, rad, px.", f'format = "{RIG_FORMAT}"', f"version = {RIG_VERSION}"]
    lines.append(f"views = {toml_value(list(rig.names))}")
    tables: dict[str, Mapping[str, Any]] = {
        name: table for name, table in extra.items() if name not in rig.names
    }
    if base is not None:
        tables["base"] = {"R_w_b": base.R_w_b, "o_b_w_mm": base.o_b_w_mm}
    for name, view in zip(rig.names, rig.views, strict=True):
        tables[name] = {**_view_table(view), **extra.get(name, {})}
    for name, table in tables.items():
        lines += ["", f"[{name}]"]
        lines += [f"{key} = {toml_value(value)}" for key, value in table.items()]
    return "\n".join(lines) + "\n"
