"""Calibration of a two-camera (bi-plane) rig from checkerboard images (DESIGN.md section 4).

1. Each camera alone: Zhang's method (``cv2.calibrateCamera``) on the checkerboard corners
   found in its images (``cv2.findChessboardCorners`` refined by ``cv2.cornerSubPix``).
2. The pair: the pose of the side camera relative to the front one from every pair where
   both cameras saw the board (``cv2.stereoCalibrate`` with the intrinsics fixed).
3. The world frame {W}: the board of one pair seen by both cameras (by default the first);
   optionally moved by a known board pose, e.g. a fiducial registered to the catheter base.

The result is written as a rig file (TOML, docs/vision.md) that
:func:`models.rig_file.load_rig` reads back into a :class:`models.imaging.BiplaneRig`,
with the per-view and total reprojection errors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from models.imaging import BiplaneRig, PinholeView
from models.rig_file import RIG_FORMAT, RIG_VERSION

Array = np.ndarray

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")
MIN_VIEWS = 3
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
_FIND_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE


def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` -> (9, 6): inner corners per row and per column."""
    parts = str(text).lower().replace(" ", "").split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise ValueError(
            f"board must be COLSxROWS inner corners such as 9x6, got {text!r}"
        ) from None
    if cols < 2 or rows < 2:
        raise ValueError(f"board needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


def board_points(pattern: tuple[int, int], square_mm: float) -> Array:
    """Inner corners in the board frame, mm, shape (cols * rows, 3), in OpenCV's order.

    Row by row, ``cols`` corners per row: x along a row, y down the rows, z = 0 on the board.
    """
    if not square_mm > 0:
        raise ValueError(f"square size must be positive, got {square_mm} mm")
    cols, rows = pattern
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float64)
    return np.column_stack([grid * square_mm, np.zeros(cols * rows)])


def find_corners(image: Array, pattern: tuple[int, int]) -> Array | None:
    """Sub-pixel inner corners of the checkerboard, shape (n, 2), px, or None if not found."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError("checkerboard images must be 8-bit grayscale or colour arrays")
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    found, corners = cv2.findChessboardCorners(gray, tuple(pattern), flags=_FIND_FLAGS)
    if not found:
        return None
    # The refinement window must not reach the next corner (boards seen at a slant).
    grid = corners.reshape(pattern[1], pattern[0], 2)
    spacing = min(
        np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(),
        np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
    )
    half = int(np.clip(0.4 * spacing, 2, 11))
    corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
    return corners.reshape(-1, 2).astype(np.float64)


@dataclass(frozen=True)
class CameraCalibration:
    """One camera calibrated by Zhang's method.

    Attributes
    ----------
    K : array (3, 3), dist : array (5,)
        Intrinsics (px) and OpenCV distortion coefficients.
    image_size : (width, height), px
    rms_px : float
        Root-mean-square reprojection error over every corner of every board, px.
    per_image_rms_px : array (n_used,)
    used : tuple of int
        Indices of the images where the board was found.
    R_cam_board, t_cam_board : arrays (n_used, 3, 3), (n_used, 3)
        Board poses in the camera frame, mm.
    corners : tuple of arrays (n, 2)
        The detected corners of the used images.
    """

    K: Array
    dist: Array
    image_size: tuple[int, int]
    rms_px: float
    per_image_rms_px: Array
    used: tuple[int, ...]
    R_cam_board: Array
    t_cam_board: Array
    corners: tuple[Array, ...]


def _check_images(images: Sequence[Array], name: str) -> tuple[int, int]:
    if len(images) == 0:
        raise ValueError(f"no {name} images")
    sizes = {(im.shape[1], im.shape[0]) for im in images}
    if len(sizes) != 1:
        raise ValueError(f"{name} images differ in size: {sorted(sizes)}")
    return sizes.pop()


def calibrate_camera(
    images: Sequence[Array],
    pattern: tuple[int, int],
    square_mm: float,
    fix_aspect_ratio: bool = False,
    name: str = "camera",
    corners: Sequence[Array | None] | None = None,
) -> CameraCalibration:
    """Zhang's calibration of one camera from images of a checkerboard.

    Parameters
    ----------
    images : sequence of uint8 arrays
        Grayscale (or colour) images of one camera, all the same size.
    pattern : (cols, rows)
        Inner corners of the board.
    square_mm : float
        Side of a square, mm.
    fix_aspect_ratio : bool
        Calibrate with fx = fy (OpenCV's CALIB_FIX_ASPECT_RATIO).
    corners : sequence, optional
        Already detected corners (None where not found), to skip detection.

    Raises
    ------
    ValueError
        No board in any image, or fewer than 3 views of it.
    """
    size = _check_images(images, name)
    if corners is None:
        corners = [find_corners(im, pattern) for im in images]
    used = tuple(i for i, c in enumerate(corners) if c is not None)
    cols, rows = pattern
    if not used:
        raise ValueError(
            f"no {cols}x{rows} checkerboard found in any of the {len(images)} {name} images"
            " (is --board the number of inner corners per row x per column?)"
        )
    if len(used) < MIN_VIEWS:
        raise ValueError(
            f"the {cols}x{rows} checkerboard was found in only {len(used)} {name} image(s);"
            f" calibration needs at least {MIN_VIEWS} views of it"
        )
    obj = board_points(pattern, square_mm).astype(np.float32)
    img_pts = [corners[i].astype(np.float32).reshape(-1, 1, 2) for i in used]
    flags = cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect_ratio else 0
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj] * len(used), img_pts, size, np.eye(3), np.zeros(5), flags=flags
    )
    R = np.array([cv2.Rodrigues(r)[0] for r in rvecs])
    t = np.array([np.asarray(v, float).reshape(3) for v in tvecs])
    per_image = []
    for pts, rv, tv in zip(img_pts, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj, rv, tv, K, dist)
        per_image.append(np.sqrt(np.mean(np.sum((proj - pts) ** 2, axis=-1))))
    return CameraCalibration(
        K=K,
        dist=np.asarray(dist, float).reshape(-1)[:5],
        image_size=size,
        rms_px=float(rms),
        per_image_rms_px=np.array(per_image),
        used=used,
        R_cam_board=R,
        t_cam_board=t,
        corners=tuple(corners[i] for i in used),
    )


@dataclass(frozen=True)
class RigCalibration:
    """A calibrated rig and how well it fits the images.

    Attributes
    ----------
    rig : BiplaneRig
        Pinhole front and side views in {W}.
    front, side : CameraCalibration
    stereo_rms_px : float
        Reprojection error of the pair fit (both cameras, fixed intrinsics), px.
    total_rms_px : float
        RMS reprojection error over every corner of both cameras' calibrations, px.
    pairs : tuple of int
        Image indices where both cameras saw the board consistently (used in the pair fit).
    world_pair : int
        The image index whose board defines {W} (before ``R_w_board``, ``o_board_w_mm``).
    pattern, square_mm : the board.
    """

    rig: BiplaneRig
    front: CameraCalibration
    side: CameraCalibration
    stereo_rms_px: float
    total_rms_px: float
    pairs: tuple[int, ...]
    world_pair: int
    pattern: tuple[int, int]
    square_mm: float


def _reversed_board(corners: Array) -> Array:
    """The same corners listed from the opposite corner (the board turned by 180 degrees)."""
    return corners[::-1].copy()


def _angle_between(R_a: Array, R_b: Array) -> float:
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def calibrate_rig(
    front_images: Sequence[Array],
    side_images: Sequence[Array],
    pattern: tuple[int, int],
    square_mm: float,
    world_pair: int | None = None,
    R_w_board: Array | None = None,
    o_board_w_mm: Array | None = None,
    fix_aspect_ratio: bool = False,
) -> RigCalibration:
    """Calibrate both cameras and their relative pose; define {W} by a board seen by both.

    Parameters
    ----------
    front_images, side_images : sequences of uint8 arrays
        Synchronised images: ``front_images[i]`` and ``side_images[i]`` are one pair.
    pattern : (cols, rows)
        Inner corners of the board.
    square_mm : float
    world_pair : int, optional
        Index of the pair whose board defines {W}; default the first pair where both
        cameras found it.
    R_w_board, o_board_w_mm : arrays (3, 3), (3,), optional
        Pose of that board in the desired world frame (identity: {W} is the board).
    fix_aspect_ratio : bool
        Calibrate each camera with fx = fy.

    Raises
    ------
    ValueError
        A clear message when the board is missing, too few views, no pair sees it in both.
    """
    if len(front_images) != len(side_images):
        raise ValueError(
            f"{len(front_images)} front and {len(side_images)} side images: they must be"
            " synchronised pairs"
        )
    # One camera after the other, so that a wrong --board fails after one folder.
    corners_f = [find_corners(im, pattern) for im in front_images]
    front = calibrate_camera(front_images, pattern, square_mm, fix_aspect_ratio, "front",
                             corners_f)
    corners_s = [find_corners(im, pattern) for im in side_images]
    side = calibrate_camera(side_images, pattern, square_mm, fix_aspect_ratio, "side", corners_s)
    pairs = tuple(i for i in front.used if i in side.used)
    if not pairs:
        raise ValueError(
            "no image pair shows the checkerboard to both cameras: the world frame and the"
            " relative pose need at least one board seen by both"
        )
    if world_pair is None:
        world_pair = pairs[0]
    if world_pair not in pairs:
        raise ValueError(
            f"pair {world_pair} does not show the board to both cameras; pairs that do:"
            f" {list(pairs)}"
        )
    # Board poses of each pair in each camera; a board listed from the opposite corner by
    # one camera (a 180-degree ambiguity of symmetric boards) is re-listed to agree.
    obj = board_points(pattern, square_mm)
    idx_f = {i: k for k, i in enumerate(front.used)}
    relative = []
    for i in pairs:
        R_f = front.R_cam_board[idx_f[i]]
        candidates = []
        for pts in (corners_s[i], _reversed_board(corners_s[i])):
            _, rv, _ = cv2.solvePnP(obj, pts, side.K, side.dist)
            R_s = cv2.Rodrigues(rv)[0]
            candidates.append((R_s @ R_f.T, pts))
        relative.append(candidates)
    # The reference orientation: the one most pairs agree with.
    best_votes, reference = -1, None
    for cand in relative[pairs.index(world_pair)]:
        R_ref = cand[0]
        votes = sum(min(_angle_between(R_ref, c[0]) for c in cands) < np.radians(5) for cands in
                    relative)
        if votes > best_votes:
            best_votes, reference = votes, R_ref
    # Pairs whose relative pose disagrees with the others (a board seen from behind, a
    # wrong detection) are left out of the pair fit.
    chosen, stereo_pairs = [], []
    for i, cands in zip(pairs, relative, strict=True):
        angles = [_angle_between(reference, c[0]) for c in cands]
        k = int(np.argmin(angles))
        if angles[k] < np.radians(5.0):
            chosen.append(cands[k][1])
            stereo_pairs.append(i)
    obj32 = obj.astype(np.float32)
    stereo = cv2.stereoCalibrate(
        [obj32] * len(stereo_pairs),
        [corners_f[i].astype(np.float32).reshape(-1, 1, 2) for i in stereo_pairs],
        [c.astype(np.float32).reshape(-1, 1, 2) for c in chosen],
        front.K, front.dist, side.K, side.dist, front.image_size,
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    stereo_rms, R_s_f, t_s_f = float(stereo[0]), stereo[5], np.asarray(stereo[6], float).reshape(3)
    # {W} = the board of the world pair, then moved by the given board pose.
    R_f_board = front.R_cam_board[idx_f[world_pair]]
    t_f_board = front.t_cam_board[idx_f[world_pair]]
    R_w_board = np.eye(3) if R_w_board is None else np.asarray(R_w_board, float)
    o_board_w = np.zeros(3) if o_board_w_mm is None else np.asarray(o_board_w_mm, float)
    # x_f = R_f_board x_board + t_f_board and x_board = R_w_board^T (x_w - o_board_w).
    R_f_w = R_f_board @ R_w_board.T
    t_f_w = t_f_board - R_f_w @ o_board_w
    R_s_w = R_s_f @ R_f_w
    t_s_w = R_s_f @ t_f_w + t_s_f
    rig = BiplaneRig(
        PinholeView(front.K, R_f_w, t_f_w, front.dist, front.image_size),
        PinholeView(side.K, R_s_w, t_s_w, side.dist, side.image_size),
    )
    n_f = len(front.used) * obj.shape[0]
    n_s = len(side.used) * obj.shape[0]
    total = np.sqrt((n_f * front.rms_px**2 + n_s * side.rms_px**2) / (n_f + n_s))
    return RigCalibration(
        rig=rig,
        front=front,
        side=side,
        stereo_rms_px=stereo_rms,
        total_rms_px=float(total),
        pairs=tuple(stereo_pairs),
        world_pair=world_pair,
        pattern=tuple(pattern),
        square_mm=float(square_mm),
    )


# ------------------------------------------------------------------------------ folders
def image_files(folder: str | Path, name: str = "image") -> list[Path]:
    """Image files of a folder, sorted by name; OSError if it is missing or has none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise OSError(f"{name} folder {folder} does not exist or is not a folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise OSError(
            f"no images ({', '.join(IMAGE_SUFFIXES)}) in {name} folder {folder}"
        )
    return files


def read_images(files: Sequence[Path]) -> list[Array]:
    """Grayscale 8-bit images; OSError naming the first file that cannot be read."""
    images = []
    for path in files:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise OSError(f"cannot read image {path}: not an image OpenCV can decode")
        images.append(image)
    return images


def calibrate_folders(
    front_dir: str | Path,
    side_dir: str | Path,
    pattern: tuple[int, int],
    square_mm: float,
    fix_aspect_ratio: bool = False,
) -> tuple[RigCalibration, list[Path], list[Path]]:
    """:func:`calibrate_rig` on two folders of images paired by sorted file name."""
    files_f = image_files(front_dir, "front")
    files_s = image_files(side_dir, "side")
    if len(files_f) != len(files_s):
        raise ValueError(
            f"{len(files_f)} front and {len(files_s)} side images: images are paired by"
            " sorted file name, so both folders need the same number"
        )
    calibration = calibrate_rig(
        read_images(files_f), read_images(files_s), pattern, square_mm,
        fix_aspect_ratio=fix_aspect_ratio,
    )
    return calibration, files_f, files_s


# ------------------------------------------------------------------------------- writing
def _fmt(x: float) -> str:
    return repr(float(x))


def _vector(v: Array) -> str:
    return "[" + ", ".join(_fmt(x) for x in np.asarray(v).reshape(-1)) + "]"


def _matrix(M: Array) -> str:
    return "[" + ", ".join(_vector(row) for row in np.asarray(M)) + "]"


def rig_toml(
    rig: BiplaneRig,
    calibration: RigCalibration | None = None,
    comment: str = "",
) -> str:
    """The text of a rig file for a pinhole rig (see docs/vision.md)."""
    if rig.kind != "pinhole":
        raise ValueError("only pinhole rigs are written; planes follow from their normals")
    lines = []
    if comment:
        lines += [f"# {line}" for line in comment.splitlines()]
    lines += [f'format = "{RIG_FORMAT}"', f"version = {RIG_VERSION}", ""]
    if calibration is not None:
        c = calibration
        lines += [
            "[calibration]",
            f"board = [{c.pattern[0]}, {c.pattern[1]}]",
            f"square_mm = {_fmt(c.square_mm)}",
            f"pairs = {len(c.pairs)}",
            f"world_pair = {c.world_pair}",
            f"total_rms_px = {_fmt(c.total_rms_px)}",
            f"stereo_rms_px = {_fmt(c.stereo_rms_px)}",
            "",
        ]
    cams = {"front": rig.front, "side": rig.side}
    for name, view in cams.items():
        lines += [
            f"[{name}]",
            f"image_size = [{view.image_size[0]}, {view.image_size[1]}]",
            f"K = {_matrix(view.K)}",
            f"dist = {_vector(view.dist)}",
            f"R_cam_w = {_matrix(view.R_cam_w)}",
            f"t_cam_w = {_vector(view.t_cam_w)}",
            f"normal_w = {_vector(-np.asarray(view.R_cam_w)[2])}",
        ]
        if calibration is not None:
            cam = calibration.front if name == "front" else calibration.side
            lines += [f"rms_px = {_fmt(cam.rms_px)}", f"images = {len(cam.used)}"]
        lines.append("")
    return "\n".join(lines)


def write_rig(
    path: str | Path,
    rig: BiplaneRig,
    calibration: RigCalibration | None = None,
    comment: str = "",
) -> Path:
    """Write a rig file; OSError if it cannot be written."""
    path = Path(path)
    text = rig_toml(rig, calibration, comment)
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise OSError(f"cannot write rig file {path}: {exc.strerror or exc}") from None
    return path


def report_lines(
    calibration: RigCalibration, names: tuple[str, str] = ("front", "side")
) -> list[str]:
    """Human-readable summary: per-view and total reprojection errors, px."""
    c = calibration
    out = []
    for label, cam in zip(names, (c.front, c.side), strict=True):
        K = cam.K
        out.append(
            f"{label}: {len(cam.used)} boards, RMS reprojection {cam.rms_px:.3f} px"
            f" (worst image {cam.per_image_rms_px.max():.3f} px); fx {K[0, 0]:.2f},"
            f" fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, cy {K[1, 2]:.2f} px"
        )
    baseline = np.linalg.norm(c.rig.front.center_w - c.rig.side.center_w)
    n_f, n_s = c.rig.front.R_cam_w[2], c.rig.side.R_cam_w[2]
    angle = np.degrees(np.arccos(np.clip(n_f @ n_s, -1.0, 1.0)))
    out.append(
        f"pair: {len(c.pairs)} boards seen by both, stereo RMS {c.stereo_rms_px:.3f} px,"
        f" baseline {baseline:.1f} mm, {angle:.1f} deg between the optical axes"
    )
    out.append(f"total RMS reprojection error {c.total_rms_px:.3f} px")
    return out
