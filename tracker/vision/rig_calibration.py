"""Calibration of a two-camera (bi-plane) rig from checkerboard images (docs/design.md section 4).

1. Each camera alone: Zhang's method (``cv2.calibrateCamera``) on the checkerboard corners
   found in its images (``cv2.findChessboardCorners`` refined by ``cv2.cornerSubPix``).
2. The pair: the pose of the side camera relative to the front one from every pair where
   both cameras saw the board (``cv2.stereoCalibrate`` with the intrinsics fixed).
3. The world frame {W}: the board of one pair seen by both cameras (by default the first);
   optionally moved by a known board pose, e.g. a fiducial registered to the catheter base.

The result is written as a rig file (TOML, docs/vision.md, :func:`models.rig_file.rig_toml`)
that :func:`models.rig_file.load_rig` reads back into a :class:`models.imaging.Rig`,
with the per-view and total reprojection errors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from models.imaging import PinholeView, Rig, default_view_names
from models.rig_file import rig_toml

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
    rig : Rig
        Pinhole views in {W}, named as calibrated.
    cameras : tuple of CameraCalibration
        Each view's own calibration, in the rig's order.
    stereo_rms_px : float
        Reprojection error of the pair fits of every view with the first (fixed intrinsics),
        px.
    total_rms_px : float
        RMS reprojection error over every corner of every camera's calibration, px.
    pairs : tuple of tuple of int
        For each view after the first, the image indices where it and the first view saw the
        board consistently (used in its pair fit).
    world_pair : int
        The image index whose board, seen by every camera, defines {W} (before
        ``R_w_board``, ``o_board_w_mm``).
    pattern, square_mm : the board.
    """

    rig: Rig
    cameras: tuple[CameraCalibration, ...]
    stereo_rms_px: float
    total_rms_px: float
    pairs: tuple[tuple[int, ...], ...]
    world_pair: int
    pattern: tuple[int, int]
    square_mm: float


def _reversed_board(corners: Array) -> Array:
    """The same corners listed from the opposite corner (the board turned by 180 degrees)."""
    return corners[::-1].copy()


def _angle_between(R_a: Array, R_b: Array) -> float:
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def _pair_fit(
    ref: CameraCalibration,
    other: CameraCalibration,
    corners_ref: Sequence[Array | None],
    corners_other: Sequence[Array | None],
    pattern: tuple[int, int],
    square_mm: float,
    reference_image: int,
) -> tuple[float, Array, Array, tuple[int, ...]]:
    """Pose of ``other`` relative to ``ref`` from the images where both saw the board:
    ``(stereo RMS px, R_o_r, t_o_r, images used)``."""
    pairs = [i for i in ref.used if i in other.used]
    obj = board_points(pattern, square_mm)
    idx_r = {i: k for k, i in enumerate(ref.used)}
    # Board poses of each pair in each camera; a board listed from the opposite corner by
    # one camera (a 180-degree ambiguity of symmetric boards) is re-listed to agree.
    relative = []
    for i in pairs:
        R_r = ref.R_cam_board[idx_r[i]]
        candidates = []
        for pts in (corners_other[i], _reversed_board(corners_other[i])):
            _, rv, _ = cv2.solvePnP(obj, pts, other.K, other.dist)
            candidates.append((cv2.Rodrigues(rv)[0] @ R_r.T, pts))
        relative.append(candidates)
    # The reference orientation: the one most pairs agree with.
    best_votes, reference = -1, None
    for cand in relative[pairs.index(reference_image)]:
        votes = sum(
            min(_angle_between(cand[0], c[0]) for c in cands) < np.radians(5)
            for cands in relative
        )
        if votes > best_votes:
            best_votes, reference = votes, cand[0]
    # Pairs whose relative pose disagrees with the others (a board seen from behind, a
    # wrong detection) are left out of the pair fit.
    chosen, used = [], []
    for i, cands in zip(pairs, relative, strict=True):
        angles = [_angle_between(reference, c[0]) for c in cands]
        k = int(np.argmin(angles))
        if angles[k] < np.radians(5.0):
            chosen.append(cands[k][1])
            used.append(i)
    obj32 = obj.astype(np.float32)
    stereo = cv2.stereoCalibrate(
        [obj32] * len(used),
        [corners_ref[i].astype(np.float32).reshape(-1, 1, 2) for i in used],
        [c.astype(np.float32).reshape(-1, 1, 2) for c in chosen],
        ref.K, ref.dist, other.K, other.dist, ref.image_size,
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    return float(stereo[0]), stereo[5], np.asarray(stereo[6], float).reshape(3), tuple(used)


def calibrate_rig(
    images: Sequence[Sequence[Array]],
    pattern: tuple[int, int],
    square_mm: float,
    world_pair: int | None = None,
    R_w_board: Array | None = None,
    o_board_w_mm: Array | None = None,
    fix_aspect_ratio: bool = False,
    names: Sequence[str] | None = None,
) -> RigCalibration:
    """Calibrate every camera and its pose relative to the first; {W} from a board seen by all.

    Parameters
    ----------
    images : sequence of sequences of uint8 arrays
        One sequence per camera, synchronised: ``images[v][i]`` is image ``i`` of view ``v``.
    pattern : (cols, rows)
        Inner corners of the board.
    square_mm : float
    world_pair : int, optional
        Index of the image whose board defines {W}; default the first one where every
        camera found it.
    R_w_board, o_board_w_mm : arrays (3, 3), (3,), optional
        Pose of that board in the desired world frame (identity: {W} is the board).
    fix_aspect_ratio : bool
        Calibrate each camera with fx = fy.
    names : sequence of str, optional
        The views' names (:func:`models.imaging.default_view_names` by default).

    Raises
    ------
    ValueError
        A clear message when the board is missing, too few views, no image shows it to
        every camera.
    """
    names = default_view_names(len(images)) if names is None else tuple(names)
    if len(images) < 2 or len(names) != len(images):
        raise ValueError(f"need images of two or more cameras, one name each; got {len(images)}")
    counts = [len(view_images) for view_images in images]
    if len(set(counts)) != 1:
        listed = " and ".join(f"{n} {name}" for n, name in zip(counts, names, strict=True))
        raise ValueError(f"{listed} images: they must be synchronised sets")
    # One camera after the other, so that a wrong --board fails after one folder.
    corners, cameras = [], []
    for name, view_images in zip(names, images, strict=True):
        corners.append([find_corners(im, pattern) for im in view_images])
        cameras.append(
            calibrate_camera(view_images, pattern, square_mm, fix_aspect_ratio, name, corners[-1])
        )
    common = tuple(i for i in cameras[0].used if all(i in c.used for c in cameras[1:]))
    if not common:
        raise ValueError(
            "no image shows the checkerboard to every camera: the world frame and the"
            " relative poses need at least one board seen by all"
        )
    if world_pair is None:
        world_pair = common[0]
    if world_pair not in common:
        raise ValueError(
            f"image {world_pair} does not show the board to every camera; images that do:"
            f" {list(common)}"
        )
    ref = cameras[0]
    idx_r = {i: k for k, i in enumerate(ref.used)}
    # {W} = the board of the world image, then moved by the given board pose.
    R_r_board = ref.R_cam_board[idx_r[world_pair]]
    t_r_board = ref.t_cam_board[idx_r[world_pair]]
    R_w_board = np.eye(3) if R_w_board is None else np.asarray(R_w_board, float)
    o_board_w = np.zeros(3) if o_board_w_mm is None else np.asarray(o_board_w_mm, float)
    # x_r = R_r_board x_board + t_r_board and x_board = R_w_board^T (x_w - o_board_w).
    R_r_w = R_r_board @ R_w_board.T
    t_r_w = t_r_board - R_r_w @ o_board_w
    views = [PinholeView(ref.K, R_r_w, t_r_w, ref.dist, ref.image_size)]
    stereo_sq, stereo_n, pairs = 0.0, 0, []
    for v in range(1, len(cameras)):
        rms, R_o_r, t_o_r, used = _pair_fit(
            ref, cameras[v], corners[0], corners[v], pattern, square_mm, world_pair
        )
        cam = cameras[v]
        views.append(
            PinholeView(cam.K, R_o_r @ R_r_w, R_o_r @ t_r_w + t_o_r, cam.dist, cam.image_size)
        )
        stereo_sq += len(used) * rms**2
        stereo_n += len(used)
        pairs.append(used)
    n_corners = board_points(pattern, square_mm).shape[0]
    n = [len(c.used) * n_corners for c in cameras]
    total = np.sqrt(sum(k * c.rms_px**2 for k, c in zip(n, cameras, strict=True)) / sum(n))
    return RigCalibration(
        rig=Rig(*views, names=names),
        cameras=tuple(cameras),
        stereo_rms_px=float(np.sqrt(stereo_sq / max(stereo_n, 1))),
        total_rms_px=float(total),
        pairs=tuple(pairs),
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
    folders: Sequence[tuple[str, str | Path]],
    pattern: tuple[int, int],
    square_mm: float,
    fix_aspect_ratio: bool = False,
) -> tuple[RigCalibration, list[list[Path]]]:
    """:func:`calibrate_rig` on one folder of images per view, ``(name, folder)`` in the rig's
    order, images matched across folders by sorted file name."""
    files = [image_files(folder, name) for name, folder in folders]
    counts = [len(f) for f in files]
    if len(set(counts)) != 1:
        listed = " and ".join(f"{n} {name}" for n, (name, _) in zip(counts, folders, strict=True))
        raise ValueError(
            f"{listed} images: images are matched by sorted file name, so every folder needs"
            " the same number"
        )
    calibration = calibrate_rig(
        [read_images(f) for f in files],
        pattern,
        square_mm,
        fix_aspect_ratio=fix_aspect_ratio,
        names=[name for name, _ in folders],
    )
    return calibration, files


# ------------------------------------------------------------------------------- writing
def calibration_tables(calibration: RigCalibration) -> dict[str, dict[str, object]]:
    """The residuals of a calibration as rig-file tables (``extra`` of
    :func:`models.rig_file.rig_toml`): ``[calibration]`` and each view's RMS and image count."""
    c = calibration
    tables: dict[str, dict[str, object]] = {
        "calibration": {
            "board": list(c.pattern),
            "square_mm": float(c.square_mm),
            "pairs": [len(p) for p in c.pairs],
            "world_pair": int(c.world_pair),
            "total_rms_px": float(c.total_rms_px),
            "stereo_rms_px": float(c.stereo_rms_px),
        }
    }
    for name, camera in zip(c.rig.names, c.cameras, strict=True):
        tables[name] = {"rms_px": float(camera.rms_px), "images": len(camera.used)}
    return tables


def write_rig(
    path: str | Path,
    rig: Rig,
    calibration: RigCalibration | None = None,
    comment: str = "",
) -> Path:
    """Write a rig file (:func:`models.rig_file.rig_toml`, with the calibration's residuals);
    OSError if it cannot be written."""
    path = Path(path)
    extra = None if calibration is None else calibration_tables(calibration)
    text = rig_toml(rig, comment=comment, extra=extra)
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise OSError(f"cannot write rig file {path}: {exc.strerror or exc}") from None
    return path


def report_lines(calibration: RigCalibration) -> list[str]:
    """Human-readable summary: per-view and total reprojection errors, px."""
    c = calibration
    out = []
    for label, cam in zip(c.rig.names, c.cameras, strict=True):
        K = cam.K
        out.append(
            f"{label}: {len(cam.used)} boards, RMS reprojection {cam.rms_px:.3f} px"
            f" (worst image {cam.per_image_rms_px.max():.3f} px); fx {K[0, 0]:.2f},"
            f" fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, cy {K[1, 2]:.2f} px"
        )
    ref = c.rig.views[0]
    for name, view, used in zip(c.rig.names[1:], c.rig.views[1:], c.pairs, strict=True):
        baseline = np.linalg.norm(ref.center_w - view.center_w)
        cos = np.clip(ref.R_cam_w[2] @ view.R_cam_w[2], -1.0, 1.0)
        out.append(
            f"{c.rig.names[0]} and {name}: {len(used)} boards seen by both, baseline"
            f" {baseline:.1f} mm, {np.degrees(np.arccos(cos)):.1f} deg between the optical axes"
        )
    out.append(f"pair fits: stereo RMS {c.stereo_rms_px:.3f} px")
    out.append(f"total RMS reprojection error {c.total_rms_px:.3f} px")
    return out
