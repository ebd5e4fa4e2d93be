"""Reading a calibrated bi-plane rig from TOML (DESIGN.md sections 4 and 7).

The format is documented in docs/vision.md; ``tracker.vision.rig_calibration`` writes it. A rig file
holds, per view (``[front]`` and ``[side]``), a calibrated pinhole camera in OpenCV's
conventions (image size, intrinsics, distortion, pose of {W} in the camera) and the normal
``normal_w`` of the imaging plane that the paper's orthographic model needs (the direction
from the scene toward the camera). :func:`load_rig` builds a
:class:`models.imaging.BiplaneRig` of either kind from it.

Like models/model_file.py this module only reads; it also holds the small geometric helpers
that relate a far pinhole view to its orthographic plane.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from models.imaging import BiplaneRig, OrthographicPlane, PinholeView
from models.model_file import check_header

Array = np.ndarray

RIG_FORMAT = "cathtrack-rig"
RIG_VERSION = 1
VIEW_NAMES = ("front", "side")
MODELS = ("pinhole", "orthographic")
NORMAL_TOLERANCE_RAD = 1e-3
"""How far ``normal_w`` may be from the camera's viewing direction when both are given."""


class RigFileError(ValueError):
    """A rig file that cannot be read or does not describe a valid rig."""


def _array(table: dict[str, Any], key: str, shape: tuple[int, ...], where: str) -> Array:
    if key not in table:
        raise RigFileError(f"{where}: missing key '{key}'")
    try:
        value = np.array(table[key], dtype=float)
    except (TypeError, ValueError):
        raise RigFileError(f"{where}: '{key}' must be numbers of shape {shape}") from None
    if value.shape != shape:
        raise RigFileError(f"{where}: '{key}' must have shape {shape}, got {value.shape}")
    if not np.all(np.isfinite(value)):
        raise RigFileError(f"{where}: '{key}' contains non-finite values")
    return value


def camera_from_table(table: Any, where: str) -> PinholeView:
    """A pinhole view from one ``[front]`` / ``[side]`` table (validated)."""
    if not isinstance(table, dict):
        raise RigFileError(f"{where}: expected a table")
    size = table.get("image_size")
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in size)
    ):
        raise RigFileError(f"{where}: image_size must be [width, height] in px, got {size!r}")
    K = _array(table, "K", (3, 3), where)
    dist = _array(table, "dist", (5,), where) if "dist" in table else np.zeros(5)
    R = _array(table, "R_cam_w", (3, 3), where)
    t = _array(table, "t_cam_w", (3,), where)
    try:
        view = PinholeView(K, R, t, dist, (size[0], size[1]))
    except ValueError as exc:
        raise RigFileError(f"{where}: {exc}") from None
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
    n = _array(table, "normal_w", (3,), where)
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


def orthographic_rig(rig: BiplaneRig) -> BiplaneRig:
    """The orthographic (far-source) approximation of a pinhole rig."""
    if rig.kind != "pinhole":
        return rig
    return BiplaneRig(orthographic_plane(rig.front), orthographic_plane(rig.side))


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


def rig_from_dict(data: dict[str, Any], source: str = "rig", model: str = "pinhole") -> BiplaneRig:
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
    views = []
    for name in VIEW_NAMES:
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
            try:
                views.append(OrthographicPlane.from_normal(_unit_normal(table, where), angle))
            except ValueError as exc:
                raise RigFileError(f"{where}: {exc}") from None
    try:
        return BiplaneRig(views[0], views[1])
    except ValueError as exc:
        raise RigFileError(f"{source}: {exc}") from None


def read_rig_file(path: str | Path) -> dict[str, Any]:
    """The parsed TOML of a rig file, or one RigFileError naming the file and the problem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RigFileError(f"cannot read rig file {path}: {exc}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RigFileError(f"{path}: malformed TOML: {exc}") from None


def load_rig(path: str | Path, model: str = "pinhole") -> BiplaneRig:
    """Read a calibrated rig from a TOML file (see docs/vision.md).

    Raises
    ------
    RigFileError
        One message naming the file and the problem: unreadable file, malformed TOML, a
        missing or invalid key, inconsistent normals, coincident cameras.
    """
    return rig_from_dict(read_rig_file(path), str(path), model)
