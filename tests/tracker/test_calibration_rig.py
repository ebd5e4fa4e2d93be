"""Rig calibration: OpenCV's real stereo images, the synthetic rig, rig files and the CLI."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from models.imaging import PinholeView, Rig
from models.rig_file import RigFileError, load_rig, orthographic_plane, rig_toml
from replay.cli import main
from replay.simulation.render import (
    RenderSettings,
    default_render_rig,
    look_at_board,
    render_background,
    render_checkerboard,
)
from tracker.vision.rig_calibration import (
    board_points,
    calibrate_camera,
    calibrate_rig,
    calibration_tables,
    find_corners,
    parse_board,
    read_images,
    write_rig,
)

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
STEREO = SHARED / "data" / "opencv_stereo"
PATTERN = (9, 6)
SQUARE_MM = 25.0


def stereo_files():
    if not STEREO.is_dir():
        pytest.fail(
            f"the shared data folder {STEREO} is missing: these tests need OpenCV's stereo"
            " images (see shared/data/opencv_stereo/README.md) beside the repository"
        )
    left = sorted(STEREO.glob("left*.jpg"))
    right = sorted(STEREO.glob("right*.jpg"))
    assert len(left) == len(right) == 13, "expected OpenCV's 13 stereo pairs"
    return left, right


@pytest.fixture(scope="module")
def stereo_images():
    left, right = stereo_files()
    return read_images(left), read_images(right)


@pytest.fixture(scope="module")
def real_rig(stereo_images):
    return calibrate_rig(stereo_images, PATTERN, SQUARE_MM)


# ------------------------------------------------------------------------ real stereo data
def test_all_13_pairs_are_detected(real_rig):
    assert [len(camera.used) for camera in real_rig.cameras] == [13, 13]
    assert [len(pairs) for pairs in real_rig.pairs] == [13]


def test_each_camera_reprojects_below_half_a_pixel(real_rig):
    assert all(camera.rms_px < 0.5 for camera in real_rig.cameras)
    assert real_rig.total_rms_px < 0.5
    assert real_rig.stereo_rms_px < 0.5


def test_left_intrinsics_within_1_percent_of_opencvs_calibration(stereo_images):
    """Calibrated as OpenCV did (CALIB_FIX_ASPECT_RATIO) against its shipped result."""
    shipped = cv2.FileStorage(str(STEREO / "left_intrinsics.yml"), cv2.FILE_STORAGE_READ)
    K_ref = shipped.getNode("camera_matrix").mat()
    shipped.release()
    left = calibrate_camera(stereo_images[0], PATTERN, SQUARE_MM, fix_aspect_ratio=True)
    assert left.K[0, 0] == left.K[1, 1]
    for (i, j) in ((0, 0), (1, 1), (0, 2), (1, 2)):
        assert left.K[i, j] == pytest.approx(K_ref[i, j], rel=0.01)


def test_triangulated_corners_are_one_square_apart(real_rig, stereo_images):
    rig = real_rig.rig
    per_pair = []
    for i in real_rig.pairs[0]:
        front = find_corners(stereo_images[0][i], PATTERN)
        side = find_corners(stereo_images[1][i], PATTERN)
        grid = rig.reconstruct(front, side).reshape(PATTERN[1], PATTERN[0], 3)
        spacing = np.concatenate(
            [
                np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel(),
                np.linalg.norm(np.diff(grid, axis=0), axis=-1).ravel(),
            ]
        )
        per_pair.append(np.median(spacing))
    assert np.mean(per_pair) == pytest.approx(SQUARE_MM, rel=0.02)
    assert np.all(np.abs(np.array(per_pair) / SQUARE_MM - 1.0) < 0.02)


def test_world_frame_is_the_board_of_the_first_pair(real_rig, stereo_images):
    """Board corner (0, 0) is the world origin: it projects onto the detected corner."""
    corners = find_corners(stereo_images[0][real_rig.world_pair], PATTERN)
    projected = real_rig.rig.views[0].project(board_points(PATTERN, SQUARE_MM))
    assert np.abs(projected - corners).max() < 2.0


def test_rig_file_round_trip(real_rig, tmp_path):
    path = write_rig(tmp_path / "rig.toml", real_rig.rig, real_rig, comment="test rig")
    rig = load_rig(path)
    assert rig.names == real_rig.rig.names == ("front", "side")
    for a, b in zip(rig.views, real_rig.rig.views, strict=True):
        assert np.allclose(a.K, b.K) and np.allclose(a.dist, b.dist)
        assert np.allclose(a.R_cam_w, b.R_cam_w) and np.allclose(a.t_cam_w, b.t_cam_w)
        assert a.image_size == b.image_size
    # OpenCV's pair is a stereo rig (parallel cameras): no orthographic bi-plane model.
    with pytest.raises(RigFileError, match="parallel"):
        load_rig(path, model="orthographic")


def test_orthographic_planes_from_a_rig_file(tmp_path):
    truth = default_render_rig()
    planes = load_rig(write_rig(tmp_path / "rig.toml", truth), model="orthographic")
    assert planes.kind == "orthographic"
    assert np.allclose(planes["front"].normal_w, [0.0, -1.0, 0.0])
    assert np.allclose(planes["side"].normal_w, [1.0, 0.0, 0.0])
    assert np.allclose(planes["front"].R_w_view, orthographic_plane(truth["front"]).R_w_view)


# --------------------------------------------------------------------------- synthetic rig
def board_pose(rng, toward, tilt_rad):
    """A board facing ``toward`` (a unit vector to the camera(s)), tilted by up to tilt_rad."""
    n0 = np.asarray(toward, float) / np.linalg.norm(toward)
    side = np.cross(n0, [0.0, 0.0, 1.0] if abs(n0[2]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    axis = cv2.Rodrigues(n0 * rng.uniform(0, 2 * np.pi))[0] @ side
    n = cv2.Rodrigues(axis * rng.uniform(*tilt_rad))[0] @ n0
    up0 = np.array([0.0, 0.0, 1.0] if abs(n0[2]) < 0.9 else [0.0, 1.0, 0.0])
    up = cv2.Rodrigues(n * rng.uniform(-0.4, 0.4))[0] @ up0
    return look_at_board(rng.uniform(-5, 5, 3), n, up, PATTERN, 5.0)


def three_camera_rig() -> Rig:
    """The rendering rig with a third camera looking down from above."""
    two = default_render_rig()
    top = PinholeView.look_at([0.0, 0.0, 400.0], np.zeros(3), [0.0, 1.0, 0.0], 2500.0)
    return Rig(*two.views, top, names=("front", "side", "top"))


@pytest.mark.parametrize("n_views", [2, 3])
def test_synthetic_rig_recovers_its_intrinsics_and_poses(n_views):
    """Rendered checkerboards of the default rendering rig (and of a three-camera rig),
    calibrated: the rig comes back."""
    truth = default_render_rig() if n_views == 2 else three_camera_rig()
    rng = np.random.default_rng(1)
    square_mm = 5.0
    poses = [board_pose(rng, [1.0, -1.0, 0.0], (0.0, 0.2)) for _ in range(4)]  # seen by both
    if n_views == 3:  # tilted toward the top camera too
        poses = [board_pose(rng, [1.0, -1.0, 1.2], (0.0, 0.15)) for _ in range(4)]
    poses += [board_pose(rng, [0.0, -1.0, 0.0], (0.35, 0.7)) for _ in range(8)]  # front
    poses += [board_pose(rng, [1.0, 0.0, 0.0], (0.35, 0.7)) for _ in range(8)]  # side
    if n_views == 3:
        poses += [board_pose(rng, [0.0, 0.0, 1.0], (0.35, 0.7)) for _ in range(8)]  # top
    settings = RenderSettings(supersampling=2)
    images = []
    for k, view in enumerate(truth.views):
        background = render_background(view.image_size, 20 + k, settings)
        images.append(
            [render_checkerboard(view, R, o, PATTERN, square_mm, rng, background, settings)
             for R, o in poses]
        )
    # {W} of the truth: give the pose of the world board to the calibration.
    result = calibrate_rig(images, PATTERN, square_mm, R_w_board=poses[0][0],
                           o_board_w_mm=poses[0][1], names=truth.names)
    assert result.world_pair == 0 and result.rig.names == truth.names
    for got, want in zip(result.rig.views, truth.views, strict=True):
        assert got.K[0, 0] == pytest.approx(want.K[0, 0], rel=0.005)
        assert got.K[1, 1] == pytest.approx(want.K[1, 1], rel=0.005)
        assert np.linalg.norm(got.center_w - want.center_w) < 1.0
        angle = np.arccos(np.clip((np.trace(got.R_cam_w @ want.R_cam_w.T) - 1) / 2, -1, 1))
        assert np.degrees(angle) < 0.2
    assert result.total_rms_px < 0.1


# ------------------------------------------------------------------------------ bad input
def test_checkerboard_not_found_is_one_clear_error(stereo_images):
    with pytest.raises(ValueError, match="no 12x11 checkerboard found"):
        calibrate_camera(stereo_images[0][:3], (12, 11), SQUARE_MM, name="front")
    blank = [np.full((480, 640), 128, np.uint8)] * 3
    with pytest.raises(ValueError, match="no 9x6 checkerboard found in any of the 3"):
        calibrate_rig([blank, blank], PATTERN, SQUARE_MM)


def test_unequal_folders_and_bad_board_text_are_clear_errors(stereo_images):
    with pytest.raises(ValueError, match="synchronised sets"):
        calibrate_rig([stereo_images[0][:4], stereo_images[1][:3]], PATTERN, SQUARE_MM)
    for text in ("9", "9x", "ax6", "1x6"):
        with pytest.raises(ValueError, match="board"):
            parse_board(text)
    assert parse_board("9x6") == (9, 6) and parse_board(" 7 X 5 ") == (7, 5)
    with pytest.raises(ValueError, match="square"):
        board_points(PATTERN, 0.0)


def set_line(text, key, value):
    """The rig text with the first ``key = ...`` line given a new value."""
    lines = text.splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith(f"{key} = "))
    lines[k] = f"{key} = {value}"
    return "\n".join(lines)


@pytest.fixture
def rig_text(real_rig):
    return rig_toml(real_rig.rig, extra=calibration_tables(real_rig))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace('format = "cathtrack-rig"', 'format = "other"'), "format"),
        (lambda t: t.replace("version = 1", "version = 7"), "version"),
        (lambda t: t.replace("[side]", "[lateral]"), r"missing table \[side\]"),
        (lambda t: t.replace("image_size = [640, 480]", "image_size = [640]", 1), "image_size"),
        (lambda t: set_line(t, "K", "[[1.0, 0.0], [0.0, 1.0]]"), "'K' must have shape"),
        (lambda t: set_line(t, "dist", "[0.1, 0.0]"), "'dist' must have shape"),
        (lambda t: set_line(t, "K", "[[-5.0, 0, 320], [0, 5.0, 240], [0, 0, 1]]"), "focal"),
        (lambda t: t.replace("t_cam_w = [", "t_cam_w = [1.0, ", 1), "t_cam_w"),
        (lambda t: t.replace("normal_w = [", "normal_w = [-", 1), "normal_w"),
        (lambda t: t + "\n[oops\n", "malformed TOML"),
    ],
)
def test_rig_file_errors_name_the_problem(rig_text, tmp_path, edit, message):
    path = tmp_path / "rig.toml"
    path.write_text(edit(rig_text))
    with pytest.raises(RigFileError, match=message):
        load_rig(path)


def test_rig_file_rotation_and_missing_file(rig_text, tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(set_line(rig_text, "R_cam_w", "[[2.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]"))
    with pytest.raises(RigFileError, match="rotation"):
        load_rig(path)
    with pytest.raises(RigFileError, match="cannot read rig file"):
        load_rig(tmp_path / "missing.toml")
    with pytest.raises(ValueError, match="model"):
        load_rig(path, model="fisheye")


def test_planes_only_rig_file_loads_as_orthographic(tmp_path):
    path = tmp_path / "planes.toml"
    path.write_text(
        'format = "cathtrack-rig"\nversion = 1\n[front]\nnormal_w = [0.0, -1.0, 0.0]\n'
        "[side]\nnormal_w = [1.0, 0.0, 0.0]\n"
    )
    rig = load_rig(path, model="orthographic")
    assert np.allclose(rig["front"].normal_w, [0, -1, 0])
    assert np.allclose(rig["side"].normal_w, [1, 0, 0])
    with pytest.raises(RigFileError, match="only has plane normals"):
        load_rig(path)


# ------------------------------------------------------------------------------------ CLI
@pytest.fixture(scope="module")
def stereo_folders(tmp_path_factory):
    left, right = stereo_files()
    root = tmp_path_factory.mktemp("stereo")
    for name, files in (("front", left), ("side", right)):
        (root / name).mkdir()
        for f in files:
            shutil.copy(f, root / name / f.name)
    return root / "front", root / "side"


def test_cli_calibrate_writes_a_rig_file_and_reports_errors(stereo_folders, tmp_path, capsys):
    out = tmp_path / "rig.toml"
    code = main(
        ["calibrate", "--view", f"front={stereo_folders[0]}", "--view", f"side={stereo_folders[1]}",
         "--board", "9x6", "--square-mm", "25", "--out", str(out)]
    )
    text = capsys.readouterr().out
    assert code == 0
    assert "front: 13 boards, RMS reprojection" in text and "side: 13 boards" in text
    assert "total RMS reprojection error" in text and "left01.jpg" in text
    rig = load_rig(out)
    assert rig["front"].image_size == (640, 480)


def cli_error(argv, capsys):
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("cathtrack calibrate: error:")
    return err[0]


def test_cli_calibrate_bad_input_is_one_line(stereo_folders, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    front, side = (str(p) for p in stereo_folders)
    assert "no images" in cli_error(["calibrate", "--view", f"front={empty}", "--view", f"side={side}"], capsys)
    assert "does not exist" in cli_error(
        ["calibrate", "--view", f"front={tmp_path / 'nope'}", "--view", f"side={side}"], capsys
    )
    assert "no 12x11 checkerboard" in cli_error(
        ["calibrate", "--view", f"front={front}", "--view", f"side={side}", "--board", "12x11"], capsys
    )
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in Path(front).iterdir():
        shutil.copy(f, broken / f.name)
    (broken / "left07.jpg").write_bytes(b"not a jpeg")
    assert "cannot read image" in cli_error(
        ["calibrate", "--view", f"front={broken}", "--view", f"side={side}"], capsys
    )
    assert "board" in cli_error(
        ["calibrate", "--view", f"front={front}", "--view", f"side={side}", "--board", "nine"], capsys
    )
