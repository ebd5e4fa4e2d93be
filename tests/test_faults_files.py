"""Bad input and faults (issue 14), files: a model, rig, image or video file that cannot be
used is one error of one line that names the file and the problem.

One table per kind of file; each row is one fault and a word the message must hold. The
other inputs' faults: recordings and the command line in ``test_faults_recordings.py``, what
a recording holds in ``test_faults_recording_contents.py``, datagrams and estimator inputs in
``test_faults_streams.py``.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from models.model_file import ModelFileError, load_catheter
from models.rig_file import RigFileError, base_from_dict, read_rig_file, rig_from_dict, rig_toml
from replay.simulation.render import default_render_rig
from tests.faults_common import BASE, MODEL_TOML, RIG_TOML, assert_one_line
from tracker.live.sources import VideoSource
from tracker.vision.settings import check_image, read_grayscale


# ----------------------------------------------------------------------------------- TOML
def _toml_value(x) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, str):
        return json.dumps(x)
    if isinstance(x, int | float):
        return repr(x)
    if isinstance(x, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in x.items()) + " }"
    return "[" + ", ".join(_toml_value(v) for v in x) + "]"


def _toml(data: dict) -> str:
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for name, table in data.items():
        if isinstance(table, dict):
            lines += ["", f"[{name}]"] + [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


DELETE = object()


def _edited(data: dict, key: str, value) -> dict:
    """A deep copy of ``data`` with ``a.b.c`` set to ``value`` (DELETE removes it)."""
    data = json.loads(json.dumps(data))
    *tables, last = key.split(".")
    target = data
    for name in tables:
        target = target[name]
    if value is DELETE:
        del target[last]
    else:
        target[last] = value
    return data


# ----------------------------------------------------------------------------- model files
MODEL = tomllib.loads(MODEL_TOML)
MODEL_EDITS = [
    # (key, bad value, a word the message must hold)
    ("proximal.length_mm", True, "length_mm"),
    ("proximal.length_mm", "13", "length_mm"),
    ("proximal.length_mm", 0.0, "length_mm"),
    ("proximal.length_mm", -5.0, "length_mm"),
    ("proximal.length_mm", 1e300, "length_mm"),
    ("distal.length_mm", math.nan, "length_mm"),
    ("distal.length_mm", math.inf, "length_mm"),
    ("distal.length_mm", DELETE, "length_mm"),
    ("proximal.psi", {"basis": ["power"]}, "basis"),
    ("proximal.psi", {"basis": "fourier", "size": 3}, "fourier"),
    ("proximal.psi", {"basis": "power", "size": 0}, "size"),
    ("proximal.psi", {"basis": "power", "size": 100}, "size"),
    ("proximal.psi", {"basis": "power", "size": True}, "size"),
    ("proximal.psi", {"basis": "power", "size": 3.0}, "size"),
    ("proximal.eta", "power", "expected a table"),
    ("proximal.A", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], "shape"),
    ("proximal.A", [[1.0, 0.0, 0.0], [0.0, 1.0], [0.0, 0.0, 1.0]], "shape"),
    ("proximal.A", [[1.0, "x", 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "A"),
    ("proximal.A", [[True, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "A"),
    ("distal.A", [[1e300, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "magnitude"),
    ("quadrature_order", 3000, "quadrature_order"),
    ("quadrature_order", 100_000, "quadrature_order"),
    ("quadrature_order", 1, "quadrature_order"),
    ("quadrature_order", True, "quadrature_order"),
    ("quadrature_order", 10.5, "quadrature_order"),
    ("delta_2_rad", 100.0, "delta_2_rad"),
    ("delta_2_rad", True, "delta_2_rad"),
    ("marker_arclengths_mm", [1e300], "marker"),
    ("marker_arclengths_mm", "13", "marker_arclengths_mm"),
    ("marker_arclengths_mm", [1.0] * 100, "marker_arclengths_mm"),
    ("format", "cathtrack-rig", "format"),
    ("version", 2, "version"),
    ("distal", DELETE, "distal"),
    ("proximal", 3, "proximal"),
]
MODEL_TEXTS = [
    # (name, file bytes, a word the message must hold)
    ("damaged UTF-8", MODEL_TOML.encode()[:200] + b"\xff\xfe" + MODEL_TOML.encode()[200:], "UTF-8"),
    ("malformed TOML", b"format = \n", "malformed TOML"),
    ("nested too deeply", b"a = " + b"[" * 100_000 + b"]" * 100_000, "malformed TOML"),
    ("empty file", b"", "format"),
    ("binary file", bytes(range(256)) * 4, "UTF-8"),
]


@pytest.mark.parametrize(("key", "value", "word"), MODEL_EDITS, ids=lambda x: str(x)[:30])
def test_model_file_values(tmp_path, key, value, word):
    path = tmp_path / "model.toml"
    path.write_text(_toml(_edited(MODEL, key, value)))
    with pytest.raises(ModelFileError) as error:
        load_catheter(path)
    assert_one_line(error.value, path, word)


@pytest.mark.parametrize(("name", "data", "word"), MODEL_TEXTS, ids=[c[0] for c in MODEL_TEXTS])
def test_model_file_texts(tmp_path, name, data, word):
    path = tmp_path / "model.toml"
    path.write_bytes(data)
    with pytest.raises(ModelFileError) as error:
        load_catheter(path)
    assert_one_line(error.value, path, word)


def test_model_file_that_is_missing_or_a_folder(tmp_path):
    for path in (tmp_path / "missing.toml", tmp_path):
        with pytest.raises(ModelFileError) as error:
            load_catheter(path)
        assert_one_line(error.value, path, "cannot read")


def test_the_model_edits_start_from_a_valid_model(tmp_path):
    path = tmp_path / "model.toml"
    path.write_text(_toml(MODEL))
    assert load_catheter(path).marker_arclengths_mm == (13.0,)


# ------------------------------------------------------------------------------- rig files
RIG_DATA = tomllib.loads(RIG_TOML)
PLANES = tomllib.loads(rig_toml(default_render_rig(), BASE).replace("K = ", "K_unused = "))
ROTATION_Y = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
RIG_EDITS = [
    ("front.dist", [1e30, 0.0, 0.0, 0.0, 0.0], "dist"),
    ("front.dist", [-20.0, 0.0, 0.0, 0.0, 0.0], "dist"),
    ("front.dist", [0.0, 0.0, 0.0, 0.0, -1e8], "dist"),
    ("front.dist", [0.0, 0.0, 2.0, 0.0, 0.0], "p1, p2"),
    ("front.dist", [True, 0.0, 0.0, 0.0, 0.0], "dist"),
    ("front.dist", [0.0, 0.0, 0.0, 0.0], "dist"),
    ("front.dist", [0.0, "0", 0.0, 0.0, 0.0], "dist"),
    ("side.dist", [math.nan, 0.0, 0.0, 0.0, 0.0], "non-finite"),
    ("front.K", [[0.0, 0.0, 319.5], [0.0, 2500.0, 239.5], [0.0, 0.0, 1.0]], "fx"),
    ("front.K", [[-2500.0, 0.0, 319.5], [0.0, 2500.0, 239.5], [0.0, 0.0, 1.0]], "fx"),
    ("front.K", [[1e300, 0.0, 319.5], [0.0, 2500.0, 239.5], [0.0, 0.0, 1.0]], "fx"),
    ("front.K", [[2500.0, 0.0, 319.5], [0.0, 0.5, 239.5], [0.0, 0.0, 1.0]], "fy"),
    ("front.K", [[True, 0.0, 319.5], [0.0, 2500.0, 239.5], [0.0, 0.0, 1.0]], "'K'"),
    ("front.K", [[2500.0, 3.0, 319.5], [0.0, 2500.0, 239.5], [0.0, 0.0, 1.0]], "skew"),
    ("front.K", [[2500.0, 0.0, 1e6], [0.0, 2500.0, 239.5], [0.0, 0.0, 1.0]], "cx"),
    ("front.K", [[2500.0, 0.0, 319.5], [0.0, 2500.0, 239.5]], "shape"),
    ("side.image_size", [0, 480], "image_size"),
    ("side.image_size", [640.0, 480], "image_size"),
    ("side.image_size", [True, 480], "image_size"),
    ("side.image_size", [10**7, 480], "image_size"),
    ("side.image_size", DELETE, "image_size"),
    ("front.t_cam_w", [0.0, 0.0, 1e300], "t_cam_w"),
    ("front.t_cam_w", [0.0, 0.0, 1e6], "t_cam_w"),
    ("front.t_cam_w", [0.0, True, 400.0], "t_cam_w"),
    ("front.R_cam_w", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]], "R_cam_w"),
    ("front.R_cam_w", [[1e300, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "R_cam_w"),
    ("front.normal_w", [0.0, 0.0, 1.0], "normal_w"),
    ("front.normal_w", [0.0, 0.0, 0.0], "normal_w"),
    ("front.normal_w", [0.0, -1e300, 0.0], "normal_w"),
    ("base.o_b_w_mm", [0.0, 0.0, 1e300], "o_b_w_mm"),
    ("base.o_b_w_mm", [True, 0.0, 0.0], "o_b_w_mm"),
    ("base.o_b_w_mm", [0.0, 0.0], "o_b_w_mm"),
    ("base.R_w_b", [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]], "R_w_b"),
    ("base.R_w_b", [[1e300, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "R_w_b"),
    ("base", 5, "[base]"),
    ("views", ["front"], "views"),
    ("views", ["front", "front"], "views"),
    ("views", ["base", "side"], "views"),
    ("views", [1, 2], "views"),
    ("views", ["front", "side", "top"], "[top]"),
    ("side", DELETE, "[side]"),
    ("format", "cathtrack-catheter", "format"),
    ("version", True, "version"),
    ("version", 2, "version"),
]


def _check_rig(path: Path, model: str = "pinhole") -> None:
    """Read a rig file as the commands do: the rig, then its base."""
    data = read_rig_file(path)
    rig_from_dict(data, str(path), model)
    base_from_dict(data, str(path))


@pytest.mark.parametrize(("key", "value", "word"), RIG_EDITS, ids=lambda x: str(x)[:30])
def test_rig_file_values(tmp_path, key, value, word):
    path = tmp_path / "rig.toml"
    path.write_text(_toml(_edited(RIG_DATA, key, value)))
    with pytest.raises(RigFileError) as error:
        _check_rig(path)
    assert_one_line(error.value, path, word)


PLANE_RIG = {
    "format": "cathtrack-rig",
    "version": 1,
    "front": {"normal_w": [0.0, -1.0, 0.0]},
    "side": {"normal_w": [1.0, 0.0, 0.0]},
}
PLANE_EDITS = [
    ("front.in_plane_rotation_rad", True, "in_plane_rotation_rad"),
    ("front.in_plane_rotation_rad", 1e300, "in_plane_rotation_rad"),
    ("front.in_plane_rotation_rad", "0.1", "in_plane_rotation_rad"),
    ("side.normal_w", [0.0, -1.0, 1e-9], "parallel"),
    ("side.normal_w", [0.0, 0.0, math.inf], "non-finite"),
]


@pytest.mark.parametrize(("key", "value", "word"), PLANE_EDITS, ids=lambda x: str(x)[:30])
def test_plane_rig_values(tmp_path, key, value, word):
    path = tmp_path / "planes.toml"
    path.write_text(_toml(_edited(PLANE_RIG, key, value)))
    with pytest.raises(RigFileError) as error:
        _check_rig(path, "orthographic")
    assert_one_line(error.value, path, word)


RIG_TEXTS = [
    ("damaged UTF-8", RIG_TOML.encode()[:100] + b"\xc3\x28" + RIG_TOML.encode()[100:], "UTF-8"),
    ("malformed TOML", b"[front\n", "malformed TOML"),
    ("nested too deeply", b"views = " + b"[" * 100_000 + b"]" * 100_000, "malformed TOML"),
    ("empty file", b"", "format"),
    ("coincident cameras", _toml(_edited(RIG_DATA, "side", RIG_DATA["front"])).encode(), "apart"),
    ("planes only, read as cameras", _toml(PLANE_RIG).encode(), "no camera"),
]


@pytest.mark.parametrize(("name", "data", "word"), RIG_TEXTS, ids=[c[0] for c in RIG_TEXTS])
def test_rig_file_texts(tmp_path, name, data, word):
    path = tmp_path / "rig.toml"
    path.write_bytes(data)
    with pytest.raises(RigFileError) as error:
        _check_rig(path)
    assert_one_line(error.value, path, word)


def test_the_rig_edits_start_from_valid_rigs(tmp_path):
    for name, data, model in (("rig", RIG_DATA, "pinhole"), ("planes", PLANE_RIG, "orthographic")):
        path = tmp_path / f"{name}.toml"
        path.write_text(_toml(data))
        _check_rig(path, model)
    # a real lens: a narrow field of view calibrates to a large k3 that does little
    path.write_text(_toml(_edited(RIG_DATA, "side.dist", [0.03, -34.0, 0.0, 0.0, 6623.0])))
    _check_rig(path)


# ---------------------------------------------------------------------- images and videos
def _png(tmp_path: Path) -> bytes:
    path = tmp_path / "ok.png"
    cv2.imwrite(str(path), np.full((48, 64), 128, np.uint8))
    return path.read_bytes()


IMAGE_FILES = [
    ("empty", lambda d: b""),
    ("text", lambda d: b"not an image\n" * 10),
    ("truncated PNG", lambda d: d[: len(d) // 2]),
    ("PNG header only", lambda d: d[:8]),
    ("bytes flipped in the header", lambda d: d[:1] + b"XXXX" + d[5:]),
]


@pytest.mark.parametrize(("name", "make"), IMAGE_FILES, ids=[c[0] for c in IMAGE_FILES])
def test_bad_image_file_is_one_line(tmp_path, name, make):
    path = tmp_path / "bad.png"
    path.write_bytes(make(_png(tmp_path)))
    with pytest.raises(OSError) as error:
        read_grayscale(path)
    assert_one_line(error.value, path, "cannot read image")


def test_missing_image_file_or_folder_is_one_line(tmp_path):
    for path in (tmp_path / "missing.png", tmp_path):
        with pytest.raises(OSError) as error:
            read_grayscale(path)
        assert_one_line(error.value, path, "cannot read image")


BAD_ARRAYS = [
    ("float image", np.zeros((48, 64)), "uint8"),
    ("colour image", np.zeros((48, 64, 3), np.uint8), "single-channel"),
    ("wrong size", np.zeros((40, 64), np.uint8), "expected 64x48"),
    ("a list", [[0, 1]], "numpy array"),
]


@pytest.mark.parametrize(("name", "image", "word"), BAD_ARRAYS, ids=[c[0] for c in BAD_ARRAYS])
def test_bad_image_array_is_one_line(name, image, word):
    with pytest.raises(ValueError) as error:
        check_image(image, "front image", (48, 64))
    assert "\n" not in str(error.value) and word in str(error.value)


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("video") / "ok.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20, (64, 48), False)
    for k in range(20):
        writer.write(np.full((48, 64), 10 * k, np.uint8))
    writer.release()
    return path.read_bytes()


VIDEO_FILES = [
    ("empty", lambda d: b"", "cannot open"),
    ("text", lambda d: b"not a video\n" * 100, "cannot open"),
    ("header only", lambda d: d[:200], "cannot open"),
    ("missing", None, "no such file"),
]


@pytest.mark.parametrize(("name", "make", "word"), VIDEO_FILES, ids=[c[0] for c in VIDEO_FILES])
def test_bad_video_file_is_one_line(tmp_path, video, name, make, word):
    path = tmp_path / "bad.avi"
    if make is not None:
        path.write_bytes(make(video))
    good = tmp_path / "good.avi"
    good.write_bytes(video)
    with pytest.raises(OSError) as error:
        VideoSource([str(good), str(path)], ["front", "side"])
    assert_one_line(error.value, path, word)


def test_truncated_video_is_refused_or_delivers_its_frames_then_names_the_stop(tmp_path, video):
    good, cut = tmp_path / "good.avi", tmp_path / "cut.avi"
    good.write_bytes(video)
    cut.write_bytes(video[: len(video) // 2])
    try:
        source = VideoSource([str(good), str(cut)], ["front", "side"])
    except OSError as error:  # the container cannot be opened without its end
        assert_one_line(error, cut, "cannot open")
        return
    with source:
        n = sum(1 for _ in source)
        assert 0 < n < 20 and str(cut) in source.stop_reason
