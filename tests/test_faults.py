"""Bad input and faults (issue 14): every case ends in a clear line, a flagged frame or a
counted drop, and no good data around it is lost.

One table per kind of input; each row is one fault and the class it must fall in:

- a file that cannot be used (model, rig, recording, image, video): one error of one line
  that names the file and the problem;
- a damaged recording that can still be read: a warning naming the problem (for a loss, its
  kind and span), and every frame outside the damage read back unchanged;
- a datagram: dropped and counted by reason, the good ones around it kept;
- an estimator input: a one-line ValueError or a flagged step, and the filter unharmed after
  it (the next steps as if the bad one had not come);
- the command line: one line and the documented exit code.

The recordings' semantic damage is made here with the ``mcap`` library (not the project's
writer); the byte damage is cut into a file the project's writer made. A fuzz test flips bytes
in and truncates a valid recording: the reader raises nothing but RecordingError, and never
hangs.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import orjson
import pytest
from mcap.writer import CompressionType, Writer

from models.catheter import default_catheter
from models.model_file import DEFAULT_MODEL_PATH, ModelFileError, load_catheter
from models.pose import Pose
from models.rig_file import (
    RigFileError,
    base_from_dict,
    read_rig_file,
    rig_from_dict,
    rig_toml,
)
from replay.cli import EXIT_INTERRUPTED, main
from replay.evaluation import evaluate_batch
from replay.simulation.render import default_render_rig
from replay.simulation.sources import simulated_session
from tracker.estimators import make_estimator
from tracker.io.datagrams import (
    ESTIMATE_STRUCT,
    JOINT_STRUCT,
    MARKER_MAGIC,
    VERSION,
    JointFlags,
    encode_joints,
    encode_markers,
)
from tracker.io.recording import (
    RecordingError,
    RecordingWriter,
    encode_image,
    open_recording,
    schema_for_topic,
)
from tracker.io.recording.images import image_schema
from tracker.io.recording.joint_samples import (
    FILE_DESCRIPTOR_SET,
    _block,
    encode_joint_block,
)
from tracker.io.recording.protobuf import len_field, varint_bytes
from tracker.io.recording.schema import SCHEMAS_V1
from tracker.io.udp import CLOCK_JUMP_SAMPLES, JointReceiver, MarkerReceiver
from tracker.live.sources import VideoSource
from tracker.reconstruction import Reconstructor
from tracker.types import Frame
from tracker.vision.settings import check_image, read_grayscale

REPO = Path(__file__).resolve().parents[1]
MODEL_TOML = DEFAULT_MODEL_PATH.read_text()
RIG = default_render_rig()
BASE = Pose(np.eye(3), np.array([0.0, 0.0, -15.0]))
RIG_TOML = rig_toml(RIG, BASE)
P = 1 + len(default_catheter().marker_arclengths_mm)  # rows per view: tip, markers
N_FRAMES = 70  # 3.5 s at 20 fps, as in the issue
FRAME_DT_S = 0.05
JOINT_BLOCK = 50  # samples per /joints message at 1 kHz


def assert_one_line(error: BaseException, path, *words: str) -> None:
    """One line that names the file and the problem."""
    text = str(error)
    assert "\n" not in text, text
    assert str(path) in text, text
    for word in words:
        assert word in text, f"{word!r} not in {text!r}"


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


# ------------------------------------------------------------------------------ recordings
def _joints(t):
    t = np.asarray(t, dtype=float)
    q = np.column_stack([0.3 + 0.2 * np.sin(t), 0.6 + 0.1 * t, -0.4 + 0.05 * np.cos(3 * t)])
    q_dot = np.column_stack([0.2 * np.cos(t), np.full_like(t, 0.1), -0.15 * np.sin(3 * t)])
    return q, q_dot


def _session_frames() -> list[Frame]:
    rng = np.random.default_rng(14)
    frames = []
    for k in range(N_FRAMES):
        t = FRAME_DT_S * k
        q, q_dot = _joints([t])
        uv = tuple(rng.uniform(0.0, 640.0, (P, 2)) for _ in range(2))
        cov = tuple(np.tile(np.diag(rng.uniform(0.1, 2.0, 2)), (P, 1, 1)) for _ in range(2))
        frames.append(Frame(t, q[0], q_dot[0], uv, cov, None, float(rng.uniform(-3.0, 3.0))))
    return frames


FRAMES = _session_frames()
T_JOINTS = np.arange(int(N_FRAMES * FRAME_DT_S * 1000) + JOINT_BLOCK) / 1000.0


def _write_session(path: Path, images: bool = False, n_frames: int = N_FRAMES) -> Path:
    """The session with the project's writer (1 s chunks): what byte damage is cut into."""
    with RecordingWriter(path, model_toml=MODEL_TOML, rig_toml=RIG_TOML) as writer:
        j = 0
        rng = np.random.default_rng(3)
        for frame in FRAMES[:n_frames]:
            upto = int(np.searchsorted(T_JOINTS, frame.time_s + 1e-9, side="right"))
            q, q_dot = _joints(T_JOINTS[j:upto])
            writer.write_joints(T_JOINTS[j:upto], q, q_dot)
            j = upto
            if images:
                pair = tuple(rng.integers(0, 256, (48, 64), dtype=np.uint8) for _ in range(2))
                frame = dataclasses.replace(frame, images=pair)
            writer.write_frame(frame)
        end = int(np.searchsorted(T_JOINTS, FRAMES[n_frames - 1].time_s + 0.05))
        writer.write_joints(T_JOINTS[j:end], *_joints(T_JOINTS[j:end]))
    return path


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    return _write_session(tmp_path_factory.mktemp("faults") / "session.mcap")


def _read(path: Path, images: bool = False):
    """(frames by time, warnings, damage) of a recording."""
    with open_recording(path) as recording:
        frames = {round(r.frame.time_s, 6): r.frame for r in recording.frames(images=images)}
        return frames, recording.report.warnings, recording.report.damage


def assert_frames_intact(frames: dict, lost: Callable[[float], bool] = lambda t: False) -> None:
    """Every written frame not in the lost span is read back unchanged (joints interpolated
    from the 1 kHz samples: the written values)."""
    for written in FRAMES:
        t = round(written.time_s, 6)
        if lost(written.time_s):
            continue
        assert t in frames, f"the frame at t = {t} s was lost"
        got = frames[t]
        for view in range(2):
            np.testing.assert_array_equal(got.uv[view], written.uv[view])
            np.testing.assert_array_equal(got.cov[view], written.cov[view])
        np.testing.assert_allclose(got.q, written.q, atol=1e-12)
        assert got.delta_L_true_rad == written.delta_L_true_rad


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, record length) of the data section's records."""
    out, offset = [], 8
    while offset + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, offset)
        out.append((offset, opcode, length))
        if opcode == 0x0F:
            break
        offset += 9 + length
    return out


def _chunks(data: bytes) -> list[tuple[int, int, float, float]]:
    """(offset, length, first and last message time in s) of the chunks."""
    out = []
    for offset, opcode, length in _records(data):
        if opcode == 0x06:
            start, end = struct.unpack_from("<QQ", data, offset + 9)
            out.append((offset, length, start / 1e9, end / 1e9))
    return out


def _within(start_s: float, end_s: float) -> Callable[[float], bool]:
    # A frame within 0.1 s of the lost span may lose its joint values (skipped, counted).
    return lambda t: start_s - 0.1 <= t <= end_s + 0.1


def _damaged_length(value_of: Callable[[int], int], chunk: int):
    def damage(data: bytearray):
        offset, length, *_ = _chunks(data)[chunk]
        struct.pack_into("<Q", data, offset + 1, value_of(length))
        return lambda t: False  # read by its content: nothing lost

    return damage


def _corrupt_chunk(chunk: int):
    def damage(data: bytearray):
        offset, length, start_s, end_s = _chunks(data)[chunk]
        middle = offset + 9 + length // 2
        data[middle : middle + 16] = bytes(16)
        return _within(start_s, end_s)

    return damage


def _zero_chunk_header(chunk: int):
    def damage(data: bytearray):
        offset, _, start_s, end_s = _chunks(data)[chunk]
        data[offset : offset + 64] = bytes(64)
        return _within(start_s, end_s)

    return damage


def _truncate(fraction: float):
    def damage(data: bytearray):
        cut = int(len(data) * fraction)
        kept = [c for c in _chunks(data) if c[0] + 9 + c[1] <= cut]
        last_s = kept[-1][3] if kept else -1.0
        del data[cut:]
        return lambda t: t > last_s - 0.1

    return damage


def _cut_summary(data: bytearray):
    """The summary and footer after the data section: not needed, nothing lost."""
    data_end = [offset for offset, opcode, _ in _records(data) if opcode == 0x0F][0]
    del data[data_end + 9 + 4 + 10 :]
    return lambda t: False


def _compression_name(chunk: int):
    def damage(data: bytearray):
        offset, _, start_s, end_s = _chunks(data)[chunk]
        name = data.index(b"zstd", offset)
        data[name : name + 4] = b"zstx"
        return _within(start_s, end_s)

    return damage


def _metadata_name_length(which: int):
    def damage(data: bytearray):
        offset = [o for o, op, _ in _records(data) if op == 0x0C][which]
        struct.pack_into("<I", data, offset + 9, 2**32 - 1)
        return lambda t: False

    return damage


def _garbage_between_chunks(data: bytearray):
    offset = _chunks(data)[2][0]
    data[offset:offset] = bytes(range(256)) * 8
    return lambda t: False


def _duplicate_chunk(data: bytearray):
    offset, length, *_ = _chunks(data)[3]
    data[offset:offset] = data[offset : offset + 9 + length]
    return lambda t: False


def _append_garbage(data: bytearray):
    data += bytes(1000)
    return lambda t: False


READABLE_DAMAGE = [
    # (name, damage -> which frames may be lost, a word of the warning; None: no warning)
    *(
        (f"chunk {c} length {label}", _damaged_length(f, c), "damaged record length")
        for c in (1, 2, -1)
        for label, f in (
            ("0", lambda n: 0),
            ("2^64-1", lambda n: 2**64 - 1),
            ("+1000", lambda n: n + 1000),
            ("halved", lambda n: n // 2),
        )
    ),
    *((f"chunk {c} CRC", _corrupt_chunk(c), "corrupt chunk") for c in (2, 3, 4)),
    *((f"chunk {c} header zeroed", _zero_chunk_header(c), "no readable record") for c in (2, 4)),
    ("chunk 3 compression name", _compression_name(3), "lost"),
    *((f"truncated at {f:.0%}", _truncate(f), "truncated") for f in (0.1, 0.35, 0.6, 0.9)),
    ("summary cut off", _cut_summary, None),
    ("settings metadata name length 2^32", _metadata_name_length(3), "no readable record"),
    ("garbage between chunks", _garbage_between_chunks, "no readable record"),
    ("a chunk written twice", _duplicate_chunk, "repeat an earlier time stamp"),
    ("garbage after the end", _append_garbage, None),
]


@pytest.mark.parametrize(
    ("name", "damage", "word"), READABLE_DAMAGE, ids=[c[0] for c in READABLE_DAMAGE]
)
def test_damaged_recording_names_the_loss_and_keeps_the_rest(session, tmp_path, name, damage, word):
    data = bytearray(session.read_bytes())
    lost = damage(data)
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    frames, warnings, damages = _read(path)
    if word is None:
        assert warnings == [], warnings
    else:
        assert any(word in w for w in warnings), warnings
        text = " ".join(warnings)
        for d in damages:  # every loss is named: where, and the span of time lost
            assert d.kind == "truncated" or f" {d.offset} " in f"{text} ", text
            if d.lost:
                assert "t = " in text, text
    assert_frames_intact(frames, lost)


def test_one_damaged_chunk_length_loses_nothing(session, tmp_path):
    """The issue's case: one damaged chunk length lost 50 of 70 frames, called 'truncated'."""
    data = bytearray(session.read_bytes())
    offset, length, *_ = _chunks(data)[2]
    struct.pack_into("<Q", data, offset + 1, length * 7)
    path = tmp_path / "length.mcap"
    path.write_bytes(bytes(data))
    frames, warnings, damages = _read(path)
    assert len(frames) == N_FRAMES and not any("truncated" in w for w in warnings)
    assert [d.kind for d in damages] == ["bad_length"]


UNREADABLE_DAMAGE = [
    ("empty file", lambda d: d.clear(), "not an MCAP file"),
    ("four bytes", lambda d: d.__delitem__(slice(4, None)), "not an MCAP file"),
    ("magic damaged", lambda d: d.__setitem__(slice(0, 8), b"\x89PNG\r\n\x1a\n"), "MCAP"),
    ("header truncated", lambda d: d.__delitem__(slice(20, None)), "damaged"),
    ("cathtrack metadata name length 2^32", _metadata_name_length(0), "damaged"),
    ("model metadata name length 2^32", _metadata_name_length(1), "'model'"),
    ("rig metadata name length 2^32", _metadata_name_length(2), "'rig'"),
    ("random bytes", lambda d: d.__setitem__(slice(None), np.random.default_rng(1).bytes(5000)),
     "not an MCAP file"),  # fmt: skip
]


@pytest.mark.parametrize(
    ("name", "damage", "word"), UNREADABLE_DAMAGE, ids=[c[0] for c in UNREADABLE_DAMAGE]
)
def test_unreadable_recording_is_one_line(session, tmp_path, name, damage, word):
    data = bytearray(session.read_bytes())
    damage(data)
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError) as error:
        open_recording(path)
    assert_one_line(error.value, path, word)


def test_recording_that_is_missing_or_a_folder(tmp_path):
    for path in (tmp_path / "missing.mcap", tmp_path):
        with pytest.raises(RecordingError) as error:
            open_recording(path)
        assert_one_line(error.value, path, "cannot read")


# ---------------------------------------------------- recordings: semantic damage with mcap
@dataclass
class Content:
    """What a recording holds, as the mcap library writes it: metadata records and messages
    (topic, log time ns, bytes) in order; ``/joints`` in JSON (format version 1) or
    protobuf (version 2), as the metadata says."""

    metadata: dict[str, dict[str, str]]
    messages: list[tuple[str, int, bytes]]

    def write(self, path: Path) -> Path:
        with open(path, "wb") as f:
            writer = Writer(f, chunk_size=16_384, compression=CompressionType.ZSTD)
            writer.start(profile="", library="test_faults")
            for name, record in self.metadata.items():
                writer.add_metadata(name, record)
            schemas, channels = {}, {}
            for topic, log_time, data in self.messages:
                if topic.startswith("#"):  # an undeclared channel id
                    writer.add_message(int(topic[1:]), log_time, data, log_time)
                    continue
                if topic not in channels:
                    name = schema_for_topic(topic)
                    protobuf_joints = self.metadata.get("cathtrack", {}).get("format_version") == "2"
                    if topic == "/joints" and protobuf_joints:
                        encoding, blob, kind = "protobuf", FILE_DESCRIPTOR_SET, "protobuf"
                    elif name is None:
                        schema = image_schema()
                        name, encoding, blob, kind = (
                            schema.name, schema.encoding, bytes(schema.data), "protobuf"
                        )  # fmt: skip
                    else:
                        encoding, blob, kind = "jsonschema", json.dumps(SCHEMAS_V1[name]).encode(), "json"
                    if name not in schemas:
                        schemas[name] = writer.register_schema(name, encoding, blob)
                    channels[topic] = writer.register_channel(topic, kind, schemas[name])
                writer.add_message(channels[topic], log_time, data, log_time)
            writer.finish()
        return path


START_NS = 1_700_000_000 * 10**9  # a live session: log times are wall-clock


def _joint_message(block: dict, version: int) -> bytes:
    """A /joints message of a format version: JSON (1) or protobuf (2)."""
    if version == 1:
        return orjson.dumps(block)
    names = ("q_r_rad", "q_p_mm", "q_d_mm", "q_r_dot_rad_s", "q_p_dot_mm_s", "q_d_dot_mm_s")
    q, q_dot = (np.column_stack([block[n] for n in part]) for part in (names[:3], names[3:]))
    return encode_joint_block(np.array(block["time_ns"]), q, q_dot)


def _content(images: bool = False, version: int = 1) -> Content:
    metadata = {
        "cathtrack": {
            "format": "cathtrack-recording",
            "format_version": str(version),
            "start_time_ns": str(START_NS),
            "writer": "test_faults",
        },
        "model": {"toml": MODEL_TOML},
        "rig": {"toml": RIG_TOML},
        "settings": {"json": "{}"},
    }
    messages = []
    stamp = lambda t: START_NS + int(round(t * 1e9))  # noqa: E731
    j = 0
    rng = np.random.default_rng(5)
    for frame in FRAMES:
        while j < T_JOINTS.size and T_JOINTS[j] <= frame.time_s + 1e-9:
            t = T_JOINTS[j : j + JOINT_BLOCK]
            t = t[t <= frame.time_s + 1e-9]
            q, q_dot = _joints(t)
            block = {"time_ns": [stamp(x) for x in t]}
            names = ("q_r_rad", "q_p_mm", "q_d_mm", "q_r_dot_rad_s", "q_p_dot_mm_s", "q_d_dot_mm_s")
            for k, name in enumerate(names):
                block[name] = (q if k < 3 else q_dot)[:, k % 3].tolist()
            messages.append(("/joints", block["time_ns"][-1], _joint_message(block, version)))
            j += t.size
        t = stamp(frame.time_s)
        for view, name in enumerate(("front", "side")):
            markers = {
                "view": name,
                "unit": "px",
                "uv": frame.uv[view].tolist(),
                "cov": frame.cov[view].tolist(),
            }
            messages.append((f"/markers/{name}", t, orjson.dumps(markers)))
            if images:
                image = rng.integers(0, 256, (48, 64), dtype=np.uint8)
                messages.append((f"/camera/{name}/image", t, encode_image(image, name, t)))
        truth = {"delta_L_rad": frame.delta_L_true_rad, "delta_1_rad": None}
        messages.append(("/truth", t, orjson.dumps(truth)))
    rest = T_JOINTS[j : j + JOINT_BLOCK]
    q, q_dot = _joints(rest)
    block = {"time_ns": [stamp(x) for x in rest]}
    for k, name in enumerate(("q_r_rad", "q_p_mm", "q_d_mm")):
        block[name] = q[:, k].tolist()
    for k, name in enumerate(("q_r_dot_rad_s", "q_p_dot_mm_s", "q_d_dot_mm_s")):
        block[name] = q_dot[:, k].tolist()
    messages.append(("/joints", block["time_ns"][-1], _joint_message(block, version)))
    return Content(metadata, messages)


FRAME_10_NS = START_NS + int(round(10 * FRAME_DT_S * 1e9))
FRAME_10_S = 10 * FRAME_DT_S


def _message(content: Content, topic: str, log_time: int | None = None) -> int:
    """Index of the first message on ``topic`` (at ``log_time``)."""
    for i, (name, t, _) in enumerate(content.messages):
        if name == topic and (log_time is None or t == log_time):
            return i
    raise KeyError(topic)


def _set_message(topic: str, data=None, log_time: int | None = None, at: int = FRAME_10_NS):
    """Replace the message on ``topic`` at frame 10 (its data and/or its log time)."""

    def edit(content: Content) -> None:
        i = _message(content, topic, at)
        name, t, old = content.messages[i]
        new = old if data is None else (data if isinstance(data, bytes) else orjson.dumps(data))
        content.messages[i] = (name, t if log_time is None else log_time, new)

    return edit


def _joint_sample(column: str, value, sample: int = 7):
    """Set one sample of the joint block that ends at frame 10."""

    def edit(content: Content) -> None:
        i = _message(content, "/joints", FRAME_10_NS)
        block = json.loads(content.messages[i][2])
        block[column][sample] = value
        content.messages[i] = ("/joints", content.messages[i][1], json.dumps(block).encode())

    return edit


def _joint_column(column: str, values: list):
    """Replace a whole column of the joint block that ends at frame 10."""

    def edit(content: Content) -> None:
        i = _message(content, "/joints", FRAME_10_NS)
        block = json.loads(content.messages[i][2])
        block[column] = values
        content.messages[i] = ("/joints", content.messages[i][1], json.dumps(block).encode())

    return edit


def _joint_block(data: bytes):
    def edit(content: Content) -> None:
        i = _message(content, "/joints", FRAME_10_NS)
        content.messages[i] = ("/joints", FRAME_10_NS, data)

    return edit


def _insert(topic: str, log_time: int, data: bytes, after: int = 5):
    def edit(content: Content) -> None:
        content.messages.insert(after, (topic, log_time, data))

    return edit


def _markers(uv=None, cov=None, row: int = 0):
    frame = FRAMES[10]
    rows, covs = frame.uv[0].tolist(), frame.cov[0].tolist()
    if uv is not None:
        rows[row] = uv
    if cov is not None:
        covs[row] = cov
    return {"view": "front", "unit": "px", "uv": rows, "cov": covs}


def _move(topic: str, at_ns: int, to_ns: int):
    def edit(content: Content) -> None:
        i = _message(content, topic, at_ns)
        name, _, data = content.messages.pop(i)
        content.messages.append((name, to_ns, data))

    return edit


FRAME_10 = lambda t: abs(t - FRAME_10_S) < 1e-9  # noqa: E731
BLOCK_10 = lambda t: FRAME_10_S - 0.1 <= t <= FRAME_10_S + 0.1  # noqa: E731
NOTHING = lambda t: False  # noqa: E731
SEMANTIC_DAMAGE = [
    # (name, edit, a word of the warning, frames that may differ)
    ("marker log_time 2^64-1", _set_message("/markers/front", log_time=2**64 - 1),
     "outside the session", FRAME_10),
    ("marker log_time 0", _set_message("/markers/front", log_time=0), "outside the session",
     FRAME_10),
    ("truth log_time 2^63", _set_message("/truth", log_time=2**63), "outside the session",
     FRAME_10),
    ("joint block log_time 2^64-1", _set_message("/joints", log_time=2**64 - 1),
     "outside the session", BLOCK_10),
    ("joint q_r 1e300", _joint_sample("q_r_rad", 1e300), "beyond the physical ranges", NOTHING),
    ("joint q_p -1e300", _joint_sample("q_p_mm", -1e300), "beyond the physical ranges", NOTHING),
    ("joint q_d 1e3 mm", _joint_sample("q_d_mm", 1e3), "beyond the physical ranges", NOTHING),
    ("joint rate 1e300", _joint_sample("q_r_dot_rad_s", 1e300), "beyond the physical ranges",
     NOTHING),
    ("joint time 2^64", _joint_sample("time_ns", 2**64), "outside the session", NOTHING),
    ("joint time -1", _joint_sample("time_ns", -1), "outside the session", NOTHING),
    ("joint time a string", _joint_sample("time_ns", "soon"), "do not match", BLOCK_10),
    ("joint value null", _joint_sample("q_r_rad", None), "NaN or null", NOTHING),
    ("joint value NaN literal", _joint_sample("q_p_mm", math.nan), "NaN or null", NOTHING),
    ("joint columns of unequal length", _joint_column("q_d_mm", [0.0, 1.0]), "do not match",
     BLOCK_10),
    ("joint block not JSON", _joint_block(b"{\"time_ns\": [1, 2"), "do not match", BLOCK_10),
    ("joint block nested too deeply", _joint_block(b"[" * 5000 + b"]" * 5000), "do not match",
     BLOCK_10),
    ("joint block a list", _joint_block(b"[1, 2, 3]"), "do not match", BLOCK_10),
    ("marker u 1e300", _set_message("/markers/front", _markers(uv=[1e300, 5.0])),
     "beyond the physical ranges", FRAME_10),
    ("marker cov negative", _set_message("/markers/front", _markers(cov=[[-1.0, 0], [0, 1.0]])),
     "beyond the physical ranges", FRAME_10),
    ("marker cov 1e300", _set_message("/markers/front", _markers(cov=[[1e300, 0], [0, 1.0]])),
     "beyond the physical ranges", FRAME_10),
    ("marker cov asymmetric", _set_message("/markers/front", _markers(cov=[[1, 0.5], [0, 1]])),
     "beyond the physical ranges", FRAME_10),
    ("marker cov indefinite", _set_message("/markers/front", _markers(cov=[[1, 2], [2, 1]])),
     "beyond the physical ranges", FRAME_10),
    ("marker u a string", _set_message("/markers/front", _markers(uv=["a", 5.0])),
     "do not match", FRAME_10),
    ("marker NaN literal", _set_message("/markers/front", b'{"view": "front", "unit": "px",'
     b' "uv": [[NaN, 1.0], [1.0, 2.0]], "cov": [[[1, 0], [0, 1]], [[1, 0], [0, 1]]]}'),
     "NaN or infinite", FRAME_10),
    ("marker not JSON", _set_message("/markers/side", b"\x00\x01"), "do not match", FRAME_10),
    ("marker nested too deeply", _set_message("/markers/side", b"[" * 5000 + b"]" * 5000),
     "do not match", FRAME_10),
    ("marker rows missing", _set_message("/markers/side", {"view": "side", "unit": "px"}),
     "do not match", FRAME_10),
    ("marker one row too many", _set_message("/markers/side", {
        "view": "side", "unit": "px", "uv": [[1.0, 2.0]] * (P + 1),
        "cov": [[[1.0, 0.0], [0.0, 1.0]]] * (P + 1)}), "do not match", FRAME_10),
    ("marker repeated", _insert("/markers/front", FRAME_10_NS, orjson.dumps(_markers()), 400),
     "repeat an earlier time stamp", NOTHING),
    ("marker out of order", _move("/markers/side", FRAME_10_NS, FRAME_10_NS), "out of time order",
     NOTHING),
    ("marker 1e6 s in the future", _insert("/markers/front", START_NS + 10**15,
     orjson.dumps(_markers()), 400), "no joint values", NOTHING),
    ("truth 1e300", _set_message("/truth", {"delta_L_rad": 1e300}), "beyond the physical ranges",
     FRAME_10),
    ("truth not JSON", _set_message("/truth", b"delta_L = 1"), "do not match", FRAME_10),
    ("truth NaN literal", _set_message("/truth", b'{"delta_L_rad": NaN}'), "NaN truth", FRAME_10),
    ("truth a string", _set_message("/truth", {"delta_L_rad": "one"}), "do not match", FRAME_10),
    ("estimate malformed", _insert("/estimates/ukf", FRAME_10_NS, b'{"delta_L_rad": 1}'),
     "do not match", NOTHING),
    ("message on an undeclared channel", _insert("#999", FRAME_10_NS, b"{}"),
     "undeclared channel", NOTHING),
    ("settings not JSON", lambda c: c.metadata["settings"].update(json="{"), "settings",
     NOTHING),
    ("settings nested too deeply", lambda c: c.metadata["settings"].update(json="[" * 100_000),
     "settings", NOTHING),
    ("no /truth at all", lambda c: c.messages.__setitem__(slice(None),
     [m for m in c.messages if m[0] != "/truth"]), "no ground truth", lambda t: True),
]


@pytest.fixture(scope="module")
def content_frames(tmp_path_factory):
    """The undamaged semantic recording reads back every frame unchanged."""
    path = _content().write(tmp_path_factory.mktemp("content") / "good.mcap")
    frames, warnings, _ = _read(path)
    assert warnings == [] and len(frames) == N_FRAMES
    assert_frames_intact(frames)
    return frames


@pytest.mark.parametrize(
    ("name", "edit", "word", "affected"), SEMANTIC_DAMAGE, ids=[c[0] for c in SEMANTIC_DAMAGE]
)
def test_recording_semantic_damage_is_counted_and_the_rest_kept(
    content_frames, tmp_path, name, edit, word, affected
):
    content = _content()
    edit(content)
    path = content.write(tmp_path / "semantic.mcap")
    frames, warnings, _ = _read(path)
    assert any(word in w for w in warnings), warnings
    assert all("\n" not in w for w in warnings)
    if name == "no /truth at all":
        assert len(frames) == N_FRAMES
        return
    assert_frames_intact(frames, affected)
    # the damaged frame itself is still there (with a point or its truth missing) unless
    # its message was the one dropped
    assert len(frames) >= N_FRAMES - 1


def _binary_joints(edit: Callable[[np.ndarray, np.ndarray, np.ndarray], bytes]):
    """Replace the protobuf joint block that ends at frame 10 by ``edit(t, q, q_dot)``."""

    def apply(content: Content) -> None:
        i = _message(content, "/joints", FRAME_10_NS)
        t, q, q_dot = _block(content.messages[i][2])
        content.messages[i] = ("/joints", FRAME_10_NS, edit(t.copy(), q.copy(), q_dot.copy()))

    return apply


def _set(array: np.ndarray, index, value) -> np.ndarray:
    array[index] = value
    return array


def _column_bytes(n: int) -> int:
    """Bytes of one packed column of n samples: key, length (a varint), values."""
    return 1 + len(varint_bytes(8 * n)) + 8 * n


def _unequal_columns(t, q, q_dot) -> bytes:
    """The block with its q_d column (field 4) one sample short, the others as written."""
    good, field = encode_joint_block(t, q, q_dot), _column_bytes(t.size)
    return good[: 3 * field] + len_field(4, q[:-1, 2].tobytes()) + good[4 * field :]


BINARY_JOINT_DAMAGE = [
    # (name, edit, a word of the warning, frames that may differ): format version 2
    ("truncated block", _binary_joints(lambda t, q, r: encode_joint_block(t, q, r)[:-5]),
     "do not match", BLOCK_10),
    ("columns of unequal length", _binary_joints(_unequal_columns), "do not match", BLOCK_10),
    ("rate column q_d_dot missing", _binary_joints(lambda t, q, r: encode_joint_block(t, q, r)[
        : -_column_bytes(t.size)]), "do not match", BLOCK_10),  # fmt: skip
    ("not protobuf", _binary_joints(lambda t, q, r: b"\xff" * 64), "do not match", BLOCK_10),
    ("a JSON block", _binary_joints(lambda t, q, r: orjson.dumps({"time_ns": t.tolist()})),
     "do not match", BLOCK_10),
    ("joint value NaN", _binary_joints(lambda t, q, r: encode_joint_block(t, _set(q, (7, 1),
     math.nan), r)), "NaN or null", NOTHING),  # fmt: skip
    ("joint rate infinite", _binary_joints(lambda t, q, r: encode_joint_block(t, q, _set(r, (3, 0),
     math.inf))), "NaN or null", NOTHING),  # fmt: skip
    ("joint times unsorted", _binary_joints(lambda t, q, r: encode_joint_block(t[::-1], q[::-1],
     r[::-1])), "out of time order", NOTHING),  # fmt: skip
    ("joint time -1", _binary_joints(lambda t, q, r: encode_joint_block(_set(t, 7, -1), q, r)),
     "outside the session", NOTHING),
    ("joint q_d 1e3 mm", _binary_joints(lambda t, q, r: encode_joint_block(t, _set(q, (7, 2),
     1e3), r)), "beyond the physical ranges", NOTHING),  # fmt: skip
]


@pytest.fixture(scope="module")
def binary_content_frames(tmp_path_factory):
    """The undamaged version 2 recording reads back every frame unchanged."""
    path = _content(version=2).write(tmp_path_factory.mktemp("content") / "good_v2.mcap")
    frames, warnings, _ = _read(path)
    assert warnings == [] and len(frames) == N_FRAMES
    assert_frames_intact(frames)
    return frames


@pytest.mark.parametrize(
    ("name", "edit", "word", "affected"),
    BINARY_JOINT_DAMAGE,
    ids=[c[0] for c in BINARY_JOINT_DAMAGE],
)
def test_recording_binary_joint_damage_is_counted_and_the_rest_kept(
    binary_content_frames, tmp_path, name, edit, word, affected
):
    """Format version 2: a damaged protobuf joint block is one counted loss (or its bad
    samples are), never a crash, and the frames away from it read back unchanged."""
    content = _content(version=2)
    edit(content)
    path = content.write(tmp_path / "binary.mcap")
    frames, warnings, _ = _read(path)
    assert any(word in w for w in warnings), warnings
    assert all("\n" not in w for w in warnings)
    assert_frames_intact(frames, affected)
    assert len(frames) == N_FRAMES


IMAGE_DAMAGE = [
    ("image garbage", b"\xff" * 100),
    ("image of another encoding", encode_image(np.zeros((4, 4), np.uint8), "front", 0).replace(
        b"mono8", b"rgba8")),
    ("image data shorter than its size", encode_image(np.zeros((48, 64), np.uint8), "front", 0)[
        :-100]),
    ("image varint overflow", b"\x08" + b"\xff" * 20),
]


@pytest.mark.parametrize(("name", "data"), IMAGE_DAMAGE, ids=[c[0] for c in IMAGE_DAMAGE])
def test_recording_image_damage_is_counted_and_the_rest_kept(tmp_path, name, data):
    content = _content(images=True)
    _set_message("/camera/front/image", data)(content)
    path = content.write(tmp_path / "images.mcap")
    with open_recording(path) as recording:
        with_images = [r.frame.images is not None for r in recording.frames(images=True)]
        warnings = recording.report.warnings
    assert with_images.count(False) == 1 and not with_images[10] and len(with_images) == N_FRAMES
    assert any("cannot be decoded" in w for w in warnings), warnings


METADATA_DAMAGE = [
    ("start_time_ns not a number", ("cathtrack", "start_time_ns", "soon"), "start_time_ns"),
    ("start_time_ns 2^64", ("cathtrack", "start_time_ns", str(2**64)), "start_time_ns"),
    ("start_time_ns negative", ("cathtrack", "start_time_ns", "-5"), "start_time_ns"),
    ("format version 3", ("cathtrack", "format_version", "3"), "version"),
    ("another format", ("cathtrack", "format", "ros2"), "not a cathtrack recording"),
    ("no cathtrack record", ("cathtrack", None, None), "not a cathtrack recording"),
    ("no rig record", ("rig", None, None), "'rig'"),
    ("no model record", ("model", None, None), "'model'"),
]


@pytest.mark.parametrize(("name", "change", "word"), METADATA_DAMAGE, ids=[c[0] for c in METADATA_DAMAGE])
def test_recording_metadata_damage_is_one_line(tmp_path, name, change, word):
    content = _content()
    record, key, value = change
    if key is None:
        del content.metadata[record]
    else:
        content.metadata[record][key] = value
    path = content.write(tmp_path / "metadata.mcap")
    with pytest.raises(RecordingError) as error:
        open_recording(path)
    assert_one_line(error.value, path, word)


EMBEDDED_FILE_DAMAGE = [
    ("model TOML malformed", "model", "format = ", "catheter", "malformed TOML"),
    ("model quadrature order 3000", "model", "quadrature_order = 3000\n" + MODEL_TOML,
     "catheter", "quadrature_order"),  # fmt: skip
    ("rig TOML malformed", "rig", "[front", "rig", "malformed TOML"),
    ("rig distortion k1 1e30", "rig", RIG_TOML.replace("dist = [0.0,", "dist = [1e30,", 1),
     "rig", "dist"),  # fmt: skip
    ("rig base 1e300 mm away", "rig", RIG_TOML.replace("-15.0]", "1e300]"), "rig", "o_b_w_mm"),
    ("rig without a base", "rig", RIG_TOML.split("[base]")[0] + "[front]" + RIG_TOML.split(
        "[front]")[1], "rig", "[base]"),  # fmt: skip
]


@pytest.mark.parametrize(
    ("name", "record", "text", "method", "word"),
    EMBEDDED_FILE_DAMAGE,
    ids=[c[0] for c in EMBEDDED_FILE_DAMAGE],
)
def test_recorded_model_and_rig_damage_is_one_line(tmp_path, name, record, text, method, word):
    """The recording reads; the embedded file fails when used, naming the recording."""
    content = _content()
    content.metadata[record]["toml"] = text
    path = content.write(tmp_path / "embedded.mcap")
    with open_recording(path) as recording:
        assert len(recording) == N_FRAMES
        with pytest.raises(RecordingError) as error:
            getattr(recording, method)()
    assert_one_line(error.value, path, word)


def test_recording_stopped_before_the_first_frame_is_readable(tmp_path):
    empty = tmp_path / "empty.mcap"
    RecordingWriter(empty, model_toml=MODEL_TOML, rig_toml=RIG_TOML).close()
    joints_only = _content()
    joints_only.messages = [m for m in joints_only.messages if m[0] == "/joints"]
    for path in (empty, joints_only.write(tmp_path / "joints_only.mcap")):
        with open_recording(path) as recording:
            assert len(recording) == 0 and list(recording.frames()) == []
            assert any("no frames" in w for w in recording.report.warnings)


def test_recording_with_frames_but_no_joints_is_one_line(tmp_path):
    content = _content()
    content.messages = [m for m in content.messages if m[0] != "/joints"]
    path = content.write(tmp_path / "no_joints.mcap")
    with pytest.raises(RecordingError) as error:
        open_recording(path)
    assert_one_line(error.value, path, "/joints")


# ------------------------------------------------------------------------- recording fuzz
def _alarm(signum, frame):
    raise TimeoutError("the reader hung")


@pytest.mark.parametrize("seed", range(4))
def test_fuzzed_recordings_raise_only_recording_error_and_never_hang(tmp_path, seed):
    """Random byte flips, zeroed runs and truncations of a valid recording (with images):
    the reader raises nothing but RecordingError, and reads each in bounded time."""
    path = _write_session(tmp_path / "fuzz.mcap", images=True, n_frames=24)
    good = path.read_bytes()
    rng = np.random.default_rng(seed)
    previous = signal.signal(signal.SIGALRM, _alarm)
    outcomes = {"read": 0, "error": 0}
    try:
        for _ in range(100):
            data = bytearray(good)
            kind = rng.integers(4)
            if kind == 0:  # flip bytes
                for at in rng.integers(0, len(data), rng.integers(1, 20)):
                    data[at] ^= int(rng.integers(1, 256))
            elif kind == 1:  # truncate
                del data[int(rng.integers(0, len(data))) :]
            elif kind == 2:  # a run of zeros or 0xFF
                at, n = int(rng.integers(0, len(data))), int(rng.integers(1, 300))
                data[at : at + n] = bytes([int(rng.choice([0, 255]))]) * len(data[at : at + n])
            else:  # a damaged length or time field: 8 random bytes anywhere
                at = int(rng.integers(0, len(data) - 8))
                data[at : at + 8] = rng.bytes(8)
            bad = tmp_path / "fuzzed.mcap"
            bad.write_bytes(bytes(data))
            signal.setitimer(signal.ITIMER_REAL, 10.0)
            try:
                with open_recording(bad) as recording:
                    for recorded in recording.frames(images=True):
                        assert recorded.frame.n_views == 2
                    recording.report.summary()
                    for embedded in (recording.catheter, recording.rig):
                        try:
                            embedded()
                        except RecordingError as error:
                            assert "\n" not in str(error)
                outcomes["read"] += 1
            except RecordingError as error:
                assert "\n" not in str(error) and str(bad) in str(error)
                outcomes["error"] += 1
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0.0)
    finally:
        signal.signal(signal.SIGALRM, previous)
    assert outcomes["read"] > 0


# ------------------------------------------------------------------------------- datagrams
def _joint_datagram(k: int, time_s: float | None = None) -> bytes:
    """Good datagram k: 1 kHz samples from t = 1000 s on the sender's clock."""
    t = 1000.0 + k * 1e-3 if time_s is None else time_s
    values, rates = _joints([k * 1e-3])
    return encode_joints(k, t, values[0], rates[0])


def _raw_joint(k: int, *, magic=None, version=VERSION, flags=0, values=None) -> bytes:
    q, q_dot = _joints([k * 1e-3])
    doubles = values or [1000.0 + k * 1e-3, *q[0], *q_dot[0]]
    return JOINT_STRUCT.pack(magic or 0x564A5443, version, flags, k, 0, *doubles)


def _with(k: int, index: int, value: float, flags: int = 0) -> bytes:
    q, q_dot = _joints([k * 1e-3])
    doubles = [1000.0 + k * 1e-3, *q[0], *q_dot[0]]
    doubles[index] = value
    return _raw_joint(k, values=doubles, flags=flags)


JOINT_FAULTS = [
    # (name, bad datagram sent after good datagram 50, the counter it goes to)
    ("truncated", _joint_datagram(51)[:40], "size"),
    ("one byte too long", _joint_datagram(51) + b"\x00", "size"),
    ("empty", b"", "size"),
    ("bad magic", _raw_joint(51, magic=0x12345678), "magic"),
    ("bad version", _raw_joint(51, version=7), "version"),
    ("time NaN", _with(51, 0, math.nan), "non-finite"),
    ("q_r inf", _with(51, 1, math.inf), "non-finite"),
    ("q_p NaN", _with(51, 2, math.nan), "non-finite"),
    ("rate NaN without NO_RATES", _with(51, 4, math.nan), "non-finite"),
    ("q_r 1e300", _with(51, 1, 1e300), "range"),
    ("q_p -1e300", _with(51, 2, -1e300), "range"),
    ("q_d 1000 mm", _with(51, 3, 1e3), "range"),
    ("q_r rate 1e300", _with(51, 4, 1e300), "range"),
    ("q_r 1e300 with NO_RATES", _with(51, 1, 1e300, int(JointFlags.NO_RATES)), "range"),
    ("time 1e300", _with(51, 0, 1e300), "range"),
    ("stamped 1e6 s ahead", _joint_datagram(51, time_s=1e6), "time"),
    ("stamped 10 s ahead", _joint_datagram(51, time_s=1010.0), "time"),
    ("stamped 1e6 s back", _joint_datagram(51, time_s=-1e6 + 1000.0), "stale"),
    ("a repeat", _joint_datagram(50), "duplicate"),
    ("an old sequence", _joint_datagram(20), "stale"),
    ("a marker datagram", encode_markers(51, 1000.0, (np.ones((2, 2)),) * 2, (1.0, 1.0)), "magic"),
    ("an estimate datagram", ESTIMATE_STRUCT.pack(0x53455443, 1, 0, 51, 0, *[0.0] * 6), "magic"),
    ("72 random bytes", np.random.default_rng(0).bytes(72), "magic"),
    ("72 zero bytes", bytes(72), "magic"),
]


@pytest.mark.parametrize(("name", "bad", "reason"), JOINT_FAULTS, ids=[c[0] for c in JOINT_FAULTS])
def test_joint_datagram_faults_are_counted_and_the_stream_goes_on(name, bad, reason):
    receiver = JointReceiver(port=None, clock="aligned")
    good = [_joint_datagram(k) for k in range(100)]
    for k, data in enumerate(good):
        arrival = 5.0 + k * 1e-3
        receiver.add_datagram(data, arrival)
        if k == 50:
            assert receiver.add_datagram(bad, arrival) == 0
    counts = receiver.counts
    assert counts.received == 101 and counts.accepted == 100, counts
    dropped = {"stale": counts.stale, "duplicate": counts.duplicate, **counts.malformed}
    assert dropped == {"stale": 0, "duplicate": 0, reason: 1} | (
        {reason: 1} if reason in ("stale", "duplicate") else {}
    ), dropped
    np.testing.assert_allclose(receiver.sample_times(), 5.0 + np.arange(100) * 1e-3, atol=1e-9)
    sample = receiver.sample(5.0 + 0.0985)
    assert sample.usable and np.allclose(sample.q, _joints([0.0985])[0][0], atol=1e-6)


def test_a_sender_clock_jump_restarts_the_history_instead_of_freezing_it():
    """A controller whose clock jumps (sequence going on) is followed after a few samples."""
    receiver = JointReceiver(port=None, clock="aligned")
    for k in range(200):
        jump = 1e6 if k >= 100 else 0.0
        receiver.add_datagram(_joint_datagram(k, time_s=1000.0 + k * 1e-3 + jump), 5 + k * 1e-3)
    counts = receiver.counts
    assert counts.restarts == 1 and counts.malformed == {} and counts.accepted == 200
    assert len(receiver) == 200 - 100
    assert receiver.newest.sequence == 199 and CLOCK_JUMP_SAMPLES < 100


def test_a_first_datagram_stamped_far_ahead_does_not_freeze_the_stream():
    """With no history to judge it by, the first datagram is kept; the good ones that follow
    agree with each other, not with it, and take over after a few samples."""
    receiver = JointReceiver(port=None, clock="aligned")
    receiver.add_datagram(_joint_datagram(0, time_s=1e6), 5.0)
    for k in range(1, 100):
        receiver.add_datagram(_joint_datagram(k), 5.0 + k * 1e-3)
    assert receiver.counts.restarts == 1 and receiver.newest.sequence == 99
    assert len(receiver) == 99 and receiver.sample_times()[-1] == pytest.approx(5.099)
    assert receiver.sample(5.0985).usable


def test_a_flood_of_garbage_is_counted_and_the_good_datagrams_kept():
    receiver = JointReceiver(port=None)
    rng = np.random.default_rng(2)
    for k in range(100):
        for _ in range(100):
            receiver.add_datagram(rng.bytes(int(rng.integers(0, 100))), 5 + k * 1e-3)
        receiver.add_datagram(_joint_datagram(k), 5 + k * 1e-3)
    assert receiver.counts.accepted == 100 and receiver.counts.malformed_total == 10_000


def _marker_datagram(k: int) -> bytes:
    """Good marker datagram k: both views, 20 fps from t = 1000 s."""
    return encode_markers(k, 1000.0 + 0.05 * k, (np.full((P, 2), 100.0 + k),) * 2, (1.0, 1.0))


def _marker_head(n_points=P, views=2, magic=MARKER_MAGIC, version=VERSION, time_s=1000.0) -> bytes:
    head = struct.pack("<IHHIHHd", magic, version, 0, 9, n_points, views, time_s)
    return head + np.full(views * n_points * 3, 1.0).astype("<f8").tobytes()


def _bad_row(value: float, column: int) -> bytes:
    rows = np.full((2, P, 3), 1.0)
    rows[0, 0, column] = value
    head = struct.pack("<IHHIHHd", MARKER_MAGIC, VERSION, 0, 9, P, 2, 1000.0)
    return head + rows.astype("<f8").tobytes()


MARKER_FAULTS = [
    ("shorter than a header", b"CTMK", "size"),
    ("one byte too long", _marker_datagram(9) + b"\x00", "size"),
    ("bad magic", _marker_head(magic=0x11111111), "magic"),
    ("bad version", _marker_head(version=3), "version"),
    ("no points", _marker_head(n_points=0)[:24], "points"),
    ("65 points", _marker_head(n_points=65), "points"),
    ("one view", _marker_head(views=1), "views"),
    ("nine views", _marker_head(views=9), "views"),
    ("points unlike the catheter's", _marker_head(n_points=P + 1), "points"),
    ("views unlike the rig's", _marker_head(views=3), "views"),
    ("time NaN", _marker_head(time_s=math.nan), "non-finite"),
    ("time 1e300", _marker_head(time_s=1e300), "range"),
    ("u inf", _bad_row(math.inf, 0), "non-finite"),
    ("v 1e300", _bad_row(1e300, 1), "range"),
    ("sigma 0", _bad_row(0.0, 2), "sigma"),
    ("sigma negative", _bad_row(-1.0, 2), "sigma"),
    ("sigma NaN on a present point", _bad_row(math.nan, 2), "non-finite"),
    ("sigma 1e300", _bad_row(1e300, 2), "range"),
    ("a joint datagram", _joint_datagram(3), "magic"),
]


@pytest.fixture(scope="module")
def markers_socket():
    with MarkerReceiver(port=0, n_points=P, n_views=2) as receiver, socket.socket(
        socket.AF_INET, socket.SOCK_DGRAM
    ) as sender:
        yield receiver, sender


@pytest.mark.parametrize(("name", "bad", "reason"), MARKER_FAULTS, ids=[c[0] for c in MARKER_FAULTS])
def test_marker_datagram_faults_are_counted_and_the_good_ones_kept(markers_socket, name, bad, reason):
    receiver, sender = markers_socket
    before = dict(receiver.counts.malformed)
    accepted = receiver.counts.accepted
    for data in (_marker_datagram(1), bad, _marker_datagram(2)):
        sender.sendto(data, receiver.address)
    got = []
    deadline = time.monotonic() + 5.0
    while len(got) < 2 and time.monotonic() < deadline:
        got += receiver.receive(0.1)
    assert [round(m.time_s, 6) for m in got] == [1000.05, 1000.1]
    assert receiver.counts.accepted == accepted + 2
    after = receiver.counts.malformed
    assert {k: after[k] - before.get(k, 0) for k in after if after[k] != before.get(k, 0)} == {
        reason: 1
    }


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


# ------------------------------------------------------------------------ estimator inputs
@pytest.fixture(scope="module")
def observations():
    s = simulated_session(duration_s=2.5, seed=1)
    scene = s.scene
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    return scene.catheter, reconstructor.observe_batch(s.frames)


K = 30  # the bad observation replaces this one
I3 = np.eye(3)
ESTIMATOR_FAULTS = [
    # Only the cases the UKF already handles; the rest are the estimator API's own work.
    ("tip covariance zero", dict(tip_cov_b=np.zeros((3, 3)))),
    ("tip covariance singular", dict(tip_cov_b=np.diag([1.0, 0.0, 0.0]))),
    ("tip covariance negative", dict(tip_cov_b=-I3)),
    ("tip covariance NaN", dict(tip_cov_b=np.full((3, 3), np.nan))),
    ("tip 1e10 mm", dict(tip_b_mm=np.full(3, 1e10))),
    ("tip 1e300 mm", dict(tip_b_mm=np.full(3, 1e300))),
    ("tip inf", dict(tip_b_mm=np.array([np.inf, 0.0, 0.0]))),
    ("joint value NaN", dict(q=np.array([np.nan, 0.5, 0.2]))),
    ("time NaN", dict(time_s=np.nan)),
    ("time before the last frame", dict(time_s=-1.0)),
    ("marker covariance zero", "markers_cov_b"),
    ("markers 1e10 mm", "markers_b_mm"),
    ("markers of the wrong shape", dict(markers_b_mm=np.zeros((5, 3)))),
    ("tip covariance tiny", dict(tip_cov_b=1e-30 * I3)),
    ("tip covariance huge", dict(tip_cov_b=1e300 * I3)),
    ("tip covariance not symmetric", dict(tip_cov_b=I3 + np.triu(np.ones((3, 3)), 1))),
    ("q_r 1e300", dict(q=np.array([1e300, 0.5, 0.2]))),
    ("q_dot 1e300", dict(q_dot=np.array([0.0, 1e300, 0.0]))),
    ("q_dot NaN", dict(q_dot=np.array([np.nan, 0.0, 0.0]))),
    ("velocity 1e300", dict(velocity_b_mm_s=np.full(3, 1e300))),
    ("velocity covariance zero", dict(velocity_cov_b=np.zeros((3, 3)))),
    ("time equal to the last frame", "same time"),
    ("time 1e9 s ahead", "far future"),
]


def _bad_observation(observation, change, previous=None):
    if change == "markers_cov_b":
        change = dict(markers_cov_b=np.zeros_like(observation.markers_cov_b))
    elif change == "markers_b_mm":
        change = dict(markers_b_mm=np.full_like(observation.markers_b_mm, 1e10))
    elif change == "same time":
        change = dict(time_s=previous.time_s)
    elif change == "far future":
        change = dict(time_s=observation.time_s + 1e9)
    return dataclasses.replace(observation, **change)


def _run(catheter, sequence):
    estimator = make_estimator("ukf", catheter)
    out = []
    for observation in sequence:
        try:
            out.append(estimator.step(observation))
        except ValueError as error:
            out.append(error)
    return out


@pytest.fixture(scope="module")
def reference(observations):
    """The UKF on the frames without the K-th (the bad one, skipped)."""
    catheter, obs = observations
    return _run(catheter, obs[:K] + obs[K + 1 :])


@pytest.mark.parametrize(("name", "change"), ESTIMATOR_FAULTS, ids=[c[0] for c in ESTIMATOR_FAULTS])
def test_estimator_input_faults_are_flagged_and_do_not_poison_the_filter(
    observations, reference, name, change
):
    catheter, obs = observations
    out = _run(catheter, obs[:K] + [_bad_observation(obs[K], change, obs[K - 1])] + obs[K + 1 :])
    step = out[K]
    if isinstance(step, ValueError):
        assert "\n" not in str(step)
    else:
        assert step.flags or not step.valid, step
    later, expected = out[K + 1 :], reference[K:]
    assert not any(isinstance(e, Exception) for e in later), later
    assert all(e.valid for e in later[5:])
    error = np.array([e.delta_L_rad - r.delta_L_rad for e, r in zip(later, expected, strict=True)])
    assert np.max(np.abs(error)) < 0.02  # rad: the filter goes on as if the frame was skipped


# ---------------------------------------------------------------------------- command line
def test_track_prints_what_the_reader_lost(session, tmp_path, capsys):
    data = bytearray(session.read_bytes())
    offset, *_ = _chunks(data)[3]
    data[offset : offset + 64] = bytes(64)
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    code = main(["track", "--recording", str(path), "--speed", "0", "--estimate-to", "off"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    warnings = [line for line in captured.err.splitlines() if "warning" in line]
    assert len(warnings) == 1 and str(path) in warnings[0] and "no readable record" in warnings[0]
    assert "between t = " in warnings[0]  # the span lost
    assert "Traceback" not in captured.err


def test_a_bad_file_in_a_batch_is_reported_and_the_rest_evaluated(session, tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + bytes(50))
    damaged = tmp_path / "damaged.mcap"
    data = bytearray(session.read_bytes())
    offset, *_ = _chunks(data)[3]
    data[offset : offset + 64] = bytes(64)
    damaged.write_bytes(bytes(data))
    items = evaluate_batch(
        [bad, session, damaged], tmp_path / "out", workers=1, progress=False, rrd=False,
        figures=False, methods=["tip-position"],
    )  # fmt: skip
    assert [item.error is not None for item in items] == [True, False, False]
    batch = (tmp_path / "out" / "batch.md").read_text()
    assert f"| {bad} |" in batch and "error:" in batch and str(damaged) in batch
    assert "no readable record" in batch  # the damaged file's loss is named


def _interrupt(argv: list[str], signals: int) -> subprocess.CompletedProcess:
    """Run ``cathtrack ARGV`` in a fresh interpreter and Ctrl-C it ``signals`` times as soon
    as ``main`` starts building the parser (rerun and the command are not imported yet)."""
    script = (
        "import sys\n"
        "import replay.cli as cli\n"
        "build_parser = cli.build_parser\n"
        "def announced():\n"
        "    print('building the parser', file=sys.stderr, flush=True)\n"
        "    return build_parser()\n"
        "cli.build_parser = announced\n"
        f"sys.exit(cli.main({argv!r}))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    process = subprocess.Popen(
        [sys.executable, "-c", script], stderr=subprocess.PIPE, stdout=subprocess.PIPE, env=env
    )
    try:
        line = process.stderr.readline().decode()
        assert "building the parser" in line, line
        for k in range(signals):
            process.send_signal(signal.SIGINT)
            if k + 1 < signals:
                time.sleep(0.05)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)


@pytest.mark.parametrize("signals", [1, 2])
def test_ctrl_c_while_starting_is_one_line_and_exit_130(tmp_path, signals):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG_TOML)
    argv = ["track", "--markers-port", "0", "--joints-port", "0", "--rig", str(rig),
            "--estimate-to", "off", "--idle-timeout", "30"]  # fmt: skip
    result = _interrupt(argv, signals)
    stderr = result.stderr.decode().strip().splitlines()
    assert result.returncode == EXIT_INTERRUPTED, stderr
    assert len(stderr) == 1 and stderr[0].endswith("interrupted"), stderr
