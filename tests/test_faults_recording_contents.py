"""Bad input and faults (issue 14), what a recording holds: damaged messages, joint blocks
(JSON and protobuf), images, metadata and the embedded model and rig files.

A recording whose damage can be read past gives a warning naming the problem, and every
frame outside the damage reads back unchanged; one that cannot be used is one error of one
line that names the file and the problem. The damage is made here with the ``mcap`` library
(not the project's writer).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import orjson
import pytest
from mcap.writer import CompressionType, Writer

from tests.faults_common import (
    FRAME_DT_S,
    FRAMES,
    JOINT_BLOCK,
    MODEL_TOML,
    N_FRAMES,
    RIG_TOML,
    T_JOINTS,
    P,
    _joints,
    _read,
    assert_frames_intact,
    assert_one_line,
)
from tracker.io.recording import (
    RecordingError,
    RecordingWriter,
    encode_image,
    open_recording,
    schema_for_topic,
)
from tracker.io.recording.images import image_schema
from tracker.io.recording.joint_samples import FILE_DESCRIPTOR_SET, _block, encode_joint_block
from tracker.io.recording.protobuf import len_field, varint_bytes
from tracker.io.recording.schema import SCHEMAS_V1


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
                    protobuf_joints = (
                        self.metadata.get("cathtrack", {}).get("format_version") == "2"
                    )
                    if topic == "/joints" and protobuf_joints:
                        encoding, blob, kind = "protobuf", FILE_DESCRIPTOR_SET, "protobuf"
                    elif name is None:
                        schema = image_schema()
                        name, encoding, blob, kind = (
                            schema.name, schema.encoding, bytes(schema.data), "protobuf"
                        )  # fmt: skip
                    else:
                        encoding, blob, kind = (
                            "jsonschema",
                            json.dumps(SCHEMAS_V1[name]).encode(),
                            "json",
                        )
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
    (
        "marker log_time 2^64-1",
        _set_message("/markers/front", log_time=2**64 - 1),
        "outside the session",
        FRAME_10,
    ),
    (
        "marker log_time 0",
        _set_message("/markers/front", log_time=0),
        "outside the session",
        FRAME_10,
    ),
    (
        "truth log_time 2^63",
        _set_message("/truth", log_time=2**63),
        "outside the session",
        FRAME_10,
    ),
    (
        "joint block log_time 2^64-1",
        _set_message("/joints", log_time=2**64 - 1),
        "outside the session",
        BLOCK_10,
    ),
    ("joint q_r 1e300", _joint_sample("q_r_rad", 1e300), "beyond the physical ranges", NOTHING),
    ("joint q_p -1e300", _joint_sample("q_p_mm", -1e300), "beyond the physical ranges", NOTHING),
    ("joint q_d 1e3 mm", _joint_sample("q_d_mm", 1e3), "beyond the physical ranges", NOTHING),
    (
        "joint rate 1e300",
        _joint_sample("q_r_dot_rad_s", 1e300),
        "beyond the physical ranges",
        NOTHING,
    ),
    ("joint time 2^64", _joint_sample("time_ns", 2**64), "outside the session", NOTHING),
    ("joint time -1", _joint_sample("time_ns", -1), "outside the session", NOTHING),
    ("joint time a string", _joint_sample("time_ns", "soon"), "do not match", BLOCK_10),
    ("joint value null", _joint_sample("q_r_rad", None), "NaN or null", NOTHING),
    ("joint value NaN literal", _joint_sample("q_p_mm", math.nan), "NaN or null", NOTHING),
    (
        "joint columns of unequal length",
        _joint_column("q_d_mm", [0.0, 1.0]),
        "do not match",
        BLOCK_10,
    ),
    ("joint block not JSON", _joint_block(b'{"time_ns": [1, 2'), "do not match", BLOCK_10),
    (
        "joint block nested too deeply",
        _joint_block(b"[" * 5000 + b"]" * 5000),
        "do not match",
        BLOCK_10,
    ),
    ("joint block a list", _joint_block(b"[1, 2, 3]"), "do not match", BLOCK_10),
    (
        "marker u 1e300",
        _set_message("/markers/front", _markers(uv=[1e300, 5.0])),
        "beyond the physical ranges",
        FRAME_10,
    ),
    (
        "marker cov negative",
        _set_message("/markers/front", _markers(cov=[[-1.0, 0], [0, 1.0]])),
        "beyond the physical ranges",
        FRAME_10,
    ),
    (
        "marker cov 1e300",
        _set_message("/markers/front", _markers(cov=[[1e300, 0], [0, 1.0]])),
        "beyond the physical ranges",
        FRAME_10,
    ),
    (
        "marker cov asymmetric",
        _set_message("/markers/front", _markers(cov=[[1, 0.5], [0, 1]])),
        "beyond the physical ranges",
        FRAME_10,
    ),
    (
        "marker cov indefinite",
        _set_message("/markers/front", _markers(cov=[[1, 2], [2, 1]])),
        "beyond the physical ranges",
        FRAME_10,
    ),
    (
        "marker u a string",
        _set_message("/markers/front", _markers(uv=["a", 5.0])),
        "do not match",
        FRAME_10,
    ),
    (
        "marker NaN literal",
        _set_message(
            "/markers/front",
            b'{"view": "front", "unit": "px",'
            b' "uv": [[NaN, 1.0], [1.0, 2.0]], "cov": [[[1, 0], [0, 1]], [[1, 0], [0, 1]]]}',
        ),
        "NaN or infinite",
        FRAME_10,
    ),
    ("marker not JSON", _set_message("/markers/side", b"\x00\x01"), "do not match", FRAME_10),
    (
        "marker nested too deeply",
        _set_message("/markers/side", b"[" * 5000 + b"]" * 5000),
        "do not match",
        FRAME_10,
    ),
    (
        "marker rows missing",
        _set_message("/markers/side", {"view": "side", "unit": "px"}),
        "do not match",
        FRAME_10,
    ),
    (
        "marker one row too many",
        _set_message(
            "/markers/side",
            {
                "view": "side",
                "unit": "px",
                "uv": [[1.0, 2.0]] * (P + 1),
                "cov": [[[1.0, 0.0], [0.0, 1.0]]] * (P + 1),
            },
        ),
        "do not match",
        FRAME_10,
    ),
    (
        "marker repeated",
        _insert("/markers/front", FRAME_10_NS, orjson.dumps(_markers()), 400),
        "repeat an earlier time stamp",
        NOTHING,
    ),
    (
        "marker out of order",
        _move("/markers/side", FRAME_10_NS, FRAME_10_NS),
        "out of time order",
        NOTHING,
    ),
    (
        "marker 1e6 s in the future",
        _insert("/markers/front", START_NS + 10**15, orjson.dumps(_markers()), 400),
        "no joint values",
        NOTHING,
    ),
    (
        "truth 1e300",
        _set_message("/truth", {"delta_L_rad": 1e300}),
        "beyond the physical ranges",
        FRAME_10,
    ),
    ("truth not JSON", _set_message("/truth", b"delta_L = 1"), "do not match", FRAME_10),
    ("truth NaN literal", _set_message("/truth", b'{"delta_L_rad": NaN}'), "NaN truth", FRAME_10),
    ("truth a string", _set_message("/truth", {"delta_L_rad": "one"}), "do not match", FRAME_10),
    (
        "estimate malformed",
        _insert("/estimates/ukf", FRAME_10_NS, b'{"delta_L_rad": 1}'),
        "do not match",
        NOTHING,
    ),
    (
        "message on an undeclared channel",
        _insert("#999", FRAME_10_NS, b"{}"),
        "undeclared channel",
        NOTHING,
    ),
    ("settings not JSON", lambda c: c.metadata["settings"].update(json="{"), "settings", NOTHING),
    (
        "settings nested too deeply",
        lambda c: c.metadata["settings"].update(json="[" * 100_000),
        "settings",
        NOTHING,
    ),
    (
        "no /truth at all",
        lambda c: c.messages.__setitem__(slice(None), [m for m in c.messages if m[0] != "/truth"]),
        "no ground truth",
        lambda t: True,
    ),
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
    (
        "truncated block",
        _binary_joints(lambda t, q, r: encode_joint_block(t, q, r)[:-5]),
        "do not match",
        BLOCK_10,
    ),
    ("columns of unequal length", _binary_joints(_unequal_columns), "do not match", BLOCK_10),
    (
        "rate column q_d_dot missing",
        _binary_joints(lambda t, q, r: encode_joint_block(t, q, r)[: -_column_bytes(t.size)]),
        "do not match",
        BLOCK_10,
    ),  # fmt: skip
    ("not protobuf", _binary_joints(lambda t, q, r: b"\xff" * 64), "do not match", BLOCK_10),
    (
        "a JSON block",
        _binary_joints(lambda t, q, r: orjson.dumps({"time_ns": t.tolist()})),
        "do not match",
        BLOCK_10,
    ),
    (
        "joint value NaN",
        _binary_joints(lambda t, q, r: encode_joint_block(t, _set(q, (7, 1), math.nan), r)),
        "NaN or null",
        NOTHING,
    ),  # fmt: skip
    (
        "joint rate infinite",
        _binary_joints(lambda t, q, r: encode_joint_block(t, q, _set(r, (3, 0), math.inf))),
        "NaN or null",
        NOTHING,
    ),  # fmt: skip
    (
        "joint times unsorted",
        _binary_joints(lambda t, q, r: encode_joint_block(t[::-1], q[::-1], r[::-1])),
        "out of time order",
        NOTHING,
    ),  # fmt: skip
    (
        "joint time -1",
        _binary_joints(lambda t, q, r: encode_joint_block(_set(t, 7, -1), q, r)),
        "outside the session",
        NOTHING,
    ),
    (
        "joint q_d 1e3 mm",
        _binary_joints(lambda t, q, r: encode_joint_block(t, _set(q, (7, 2), 1e3), r)),
        "beyond the physical ranges",
        NOTHING,
    ),  # fmt: skip
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
    (
        "image of another encoding",
        encode_image(np.zeros((4, 4), np.uint8), "front", 0).replace(b"mono8", b"rgba8"),
    ),
    (
        "image data shorter than its size",
        encode_image(np.zeros((48, 64), np.uint8), "front", 0)[:-100],
    ),
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


@pytest.mark.parametrize(
    ("name", "change", "word"), METADATA_DAMAGE, ids=[c[0] for c in METADATA_DAMAGE]
)
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
    (
        "model quadrature order 3000",
        "model",
        "quadrature_order = 3000\n" + MODEL_TOML,
        "catheter",
        "quadrature_order",
    ),  # fmt: skip
    ("rig TOML malformed", "rig", "[front", "rig", "malformed TOML"),
    (
        "rig distortion k1 1e30",
        "rig",
        RIG_TOML.replace("dist = [0.0,", "dist = [1e30,", 1),
        "rig",
        "dist",
    ),  # fmt: skip
    ("rig base 1e300 mm away", "rig", RIG_TOML.replace("-15.0]", "1e300]"), "rig", "o_b_w_mm"),
    (
        "rig without a base",
        "rig",
        RIG_TOML.split("[base]")[0] + "[front]" + RIG_TOML.split("[front]")[1],
        "rig",
        "[base]",
    ),  # fmt: skip
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
