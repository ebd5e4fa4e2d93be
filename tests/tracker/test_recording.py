"""Recordings (tracker.io.recording): round trip, other readers, crash safety and bad input."""

from __future__ import annotations

import json
import math
import re
import shutil
import struct
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from models.model_file import DEFAULT_MODEL_PATH, load_catheter
from models.pose import Pose
from models.rig_file import rig_toml
from replay.simulation.render import default_render_rig
from tracker.io import recording as rec
from tracker.io.recording import (
    FrameLabels,
    MarkerQuality,
    RecordingError,
    RecordingWriter,
    joint_samples,
    open_recording,
)
from tracker.types import Estimate, Flag, Frame

REPO = Path(__file__).resolve().parents[2]
RIG = default_render_rig()
R_W_B, O_B_W = np.eye(3), np.array([0.0, 0.0, -15.0])
MODEL_TOML = DEFAULT_MODEL_PATH.read_text()
RIG_TOML = rig_toml(RIG, Pose(R_W_B, O_B_W))
CATHETER = load_catheter(DEFAULT_MODEL_PATH)
P = 1 + len(CATHETER.marker_arclengths_mm)  # points per view: the tip, then the markers


def _joints(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = np.column_stack([0.3 + 0.2 * np.sin(t), 0.6 + 0.1 * t, -0.4 + 0.05 * np.cos(3 * t)])
    q_dot = np.column_stack([0.2 * np.cos(t), np.full_like(t, 0.1), -0.15 * np.sin(3 * t)])
    return q, q_dot


def _frames(n: int, rng: np.random.Generator, images: bool) -> list[Frame]:
    """n frames at 20 Hz; their joint values are those of the 1 kHz grid of _write."""
    q_grid, q_dot_grid = _joints(np.arange(50 * n + 50) / 1000.0)
    frames = []
    for k in range(n):
        t = 0.05 * k
        q, q_dot = q_grid[50 * k : 50 * k + 1], q_dot_grid[50 * k : 50 * k + 1]
        uv_f = rng.uniform(0, 640, (P, 2))
        uv_s = rng.uniform(0, 640, (P, 2))
        cov = np.tile(np.diag(rng.uniform(0.1, 2.0, 2)), (P, 1, 1))
        if k % 7 == 3:  # a point not found in the side view
            uv_s[-1] = np.nan
        pair = None
        if images:
            pair = tuple(rng.integers(0, 256, (48, 64), dtype=np.uint8) for _ in range(2))
        frames.append(
            Frame(
                time_s=t,
                q=q[0],
                q_dot=q_dot[0],
                uv=(uv_f, uv_s),
                cov=(cov, cov.copy()),
                images=pair,
                delta_L_true_rad=float(rng.uniform(-np.pi, np.pi)),
            )
        )
    return frames


def _write(path: Path, frames: list[Frame], joint_rate_hz: float = 1000.0, **kwargs) -> dict:
    """A recording of the frames with joints at joint_rate_hz over their time span."""
    t_joint = np.arange(50 * len(frames) + 50) / joint_rate_hz
    q, q_dot = _joints(t_joint)
    labels = [
        FrameLabels(
            plane=k // 10,
            configuration=k // 5,
            deflection_mm=1.5 * (k % 2),
            noise_level=0.5,
            delta_1_true_rad=0.25,
        )
        for k in range(len(frames))
    ]
    quality = (MarkerQuality(0, (), 2.1), MarkerQuality(272, ("MARKER_MISSING", "OVERLAP"), 2.3))
    settings = {"protocol": "test", "nested": {"a": [1, 2.5]}}
    estimates = []
    with RecordingWriter(
        path, model_toml=MODEL_TOML, rig_toml=RIG_TOML, settings=settings, **kwargs
    ) as writer:
        if frames[0].images is not None:
            writer.write_background("front", frames[0].images[0])
            writer.write_background("side", frames[0].images[1])
        j = 0
        for k, frame in enumerate(frames):
            upto = int(np.searchsorted(t_joint, frame.time_s + 1e-12, side="right"))
            writer.write_joints(t_joint[j:upto], q[j:upto], q_dot[j:upto])
            j = upto
            writer.write_frame(frame, labels[k], quality)
            estimate = Estimate(
                time_s=frame.time_s,
                delta_L_rad=0.1 * k,
                std_rad=0.01,
                q_r_rad=float(frame.q[0]),
                flags=Flag.PARTIAL | Flag.HELD,
                informative_radius_mm=7.5,
                nis=1.5,
                nis_dof=3,
            )
            writer.write_estimate("ukf", estimate)
            estimates.append(estimate)
        writer.write_joints(t_joint[j:], q[j:], q_dot[j:])
    return dict(
        t_joint=t_joint,
        q=q,
        q_dot=q_dot,
        labels=labels,
        quality=quality,
        settings=settings,
        estimates=estimates,
    )


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    rng = np.random.default_rng(7)
    frames = _frames(40, rng, images=True)
    path = tmp_path_factory.mktemp("rec") / "round.mcap"
    written = _write(path, frames)
    return path, frames, written


# ------------------------------------------------------------------------------ round trip
def test_round_trip_is_identical(recorded):
    path, frames, written = recorded
    with open_recording(path) as r:
        assert r.report.warnings == []
        assert r.metadata.format_version == rec.FORMAT_VERSION
        assert r.metadata.model_toml == MODEL_TOML
        assert r.metadata.rig_toml == RIG_TOML
        assert r.metadata.settings == written["settings"]
        # joint values: every sample, bit for bit
        np.testing.assert_array_equal(r.joints.q, written["q"])
        np.testing.assert_array_equal(r.joints.q_dot, written["q_dot"])
        np.testing.assert_array_equal(
            np.round(r.joints.time_s * 1e9), np.round(written["t_joint"] * 1e9)
        )
        out = list(r.frames())
        assert len(out) == len(frames) == r.report.frames
        for k, (got, sent) in enumerate(zip(out, frames, strict=True)):
            f = got.frame
            assert isinstance(f, Frame)
            assert math.isclose(f.time_s, sent.time_s, abs_tol=1e-9)
            np.testing.assert_array_equal(f.uv[0], sent.uv[0])
            np.testing.assert_array_equal(f.uv[1], sent.uv[1])  # NaN rows included
            np.testing.assert_array_equal(f.cov[0], sent.cov[0])
            np.testing.assert_array_equal(
                f.cov[1][~np.isnan(sent.uv[1][:, 0])],
                sent.cov[1][~np.isnan(sent.uv[1][:, 0])],
            )
            np.testing.assert_array_equal(f.images[0], sent.images[0])
            np.testing.assert_array_equal(f.images[1], sent.images[1])
            # the frame is on the joint grid: its joint values are the samples', exactly
            np.testing.assert_array_equal(f.q, sent.q)
            np.testing.assert_array_equal(f.q_dot, sent.q_dot)
            assert f.delta_L_true_rad == sent.delta_L_true_rad
            assert got.labels == written["labels"][k]
            assert got.quality == written["quality"]
        np.testing.assert_array_equal(r.backgrounds[0], frames[0].images[0])
        est = r.estimates["ukf"]
        assert len(est) == len(written["estimates"])
        for got, sent in zip(est, written["estimates"], strict=True):
            # times are stored in integer ns
            assert math.isclose(got.time_s, sent.time_s, abs_tol=1e-9)
            assert replace(got.estimate, time_s=sent.time_s) == sent
        rig, base = r.rig()
        np.testing.assert_array_equal(rig.views[0].K, RIG.views[0].K)
        np.testing.assert_array_equal(base.R_w_b, R_W_B)
        np.testing.assert_array_equal(base.o_b_w_mm, O_B_W)
        assert r.catheter().marker_arclengths_mm == CATHETER.marker_arclengths_mm


def test_joints_are_interpolated_to_frame_times(tmp_path):
    """Frames between joint samples get linearly interpolated joints and, without recorded
    rates, the slope between the bracketing samples."""
    path = tmp_path / "interp.mcap"
    t_joint = np.arange(0, 2.0, 0.001)
    a, b = np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.25, -0.125])
    frame_times = np.arange(0.0103, 1.9, 0.05)
    with RecordingWriter(path, model_toml=MODEL_TOML, rig_toml=RIG_TOML) as writer:
        j = 0
        for t in frame_times:
            upto = int(np.searchsorted(t_joint, t, side="right")) + 1
            writer.write_joints(t_joint[j:upto], a + np.outer(t_joint[j:upto], b))
            j = upto
            uv = np.full((P, 2), 100.0)
            cov = np.tile(np.eye(2), (P, 1, 1))
            frame = Frame(t, np.zeros(3), None, (uv, uv), (cov, cov))
            writer.write_frame(frame)
        writer.write_joints(t_joint[j:], a + np.outer(t_joint[j:], b))
    with open_recording(path) as r:
        assert r.joints.q_dot is None
        frames = [x.frame for x in r.frames()]
    assert len(frames) == frame_times.size
    for f, t in zip(frames, frame_times, strict=True):
        np.testing.assert_allclose(f.q, a + t * b, rtol=0, atol=1e-12)
        np.testing.assert_allclose(f.q_dot, b, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------ other readers
def _validate(value, schema: dict, where: str) -> None:
    """The subset of JSON Schema the documented schemas use."""
    types = schema.get("type")
    if types is not None:
        types = [types] if isinstance(types, str) else types
        python = {
            "object": dict,
            "array": list,
            "string": str,
            "null": type(None),
            "integer": int,
            "number": (int, float),
        }
        ok = any(
            isinstance(value, python[t])
            and not (t in ("integer", "number") and isinstance(value, bool))
            for t in types
        )
        assert ok, f"{where}: {value!r} is not {types}"
    if isinstance(value, dict):
        for key in schema.get("required", []):
            assert key in value, f"{where}: missing {key}"
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                _validate(value[key], sub, f"{where}.{key}")
    if isinstance(value, list) and "items" in schema:
        assert len(value) >= schema.get("minItems", 0)
        assert len(value) <= schema.get("maxItems", 10**9)
        for k, item in enumerate(value):
            _validate(item, schema["items"], f"{where}[{k}]")
    if "enum" in schema:
        assert value in schema["enum"]


def _documented_schemas() -> dict[str, dict]:
    """The JSON schemas printed in docs/recording.md, by name."""
    doc = (REPO / "docs" / "recording.md").read_text()
    found = re.findall(r"### `([\w.]+)`\n\n```json\n(.*?)\n```", doc, flags=re.S)
    return {name: json.loads(text) for name, text in found}


def test_mcap_reader_reads_every_channel_with_the_documented_schemas(recorded):
    """The plain ``mcap`` reader, the schemas in the file and docs/recording.md suffice."""
    from mcap.reader import make_reader

    path, frames, _ = recorded
    documented = _documented_schemas()
    assert set(documented) == set(rec.SCHEMAS)
    doc = (REPO / "docs" / "recording.md").read_text()
    seen: dict[str, int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count > 0
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        for schema, channel, message in reader.iter_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            assert schema.name in doc, f"schema {schema.name} is not documented"
            if schema.encoding == "jsonschema":
                assert channel.message_encoding == "json"
                assert json.loads(schema.data) == documented[schema.name]
                _validate(json.loads(message.data), documented[schema.name], channel.topic)
            elif channel.topic == "/joints":
                assert (schema.name, schema.encoding, channel.message_encoding) == (
                    "cathtrack.JointSamples",
                    "protobuf",
                    "protobuf",
                )
                assert schema.data == joint_samples.FILE_DESCRIPTOR_SET
            else:
                assert (schema.name, schema.encoding, channel.message_encoding) == (
                    "foxglove.RawImage",
                    "protobuf",
                    "protobuf",
                )
                # the documented field numbers: 2 width, 3 height, 4 encoding, 5 step, 6 data
                image = rec.decode_image(message.data)
                assert image.dtype == np.uint8 and image.shape == (48, 64)
    assert metadata["cathtrack"]["format_version"] == str(rec.FORMAT_VERSION) == "2"
    assert set(metadata) == {"cathtrack", "model", "rig", "settings"}
    # the message definition printed in the docs is the one the schema describes
    assert f"```proto\n{joint_samples.PROTO}```" in doc
    for topic in (
        "/joints",
        "/markers/front",
        "/markers/side",
        "/truth",
        "/estimates/ukf",
        "/camera/front/image",
        "/camera/side/image",
        "/camera/front/background",
    ):
        assert seen.get(topic, 0) > 0, topic
    assert seen["/camera/front/image"] == len(frames)


def test_rerun_reads_the_images(recorded):
    """rerun's own MCAP loader turns the camera channels into images (no mock)."""
    from rerun.chunk import McapReader

    path, frames, _ = recorded
    reader = McapReader(path, timeline_type="duration_ns")
    images = {}
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        # a static chunk per channel describes it (McapChannel, McapSchema); the messages
        # come in chunks of Image components
        if chunk.entity_path != "/camera/front/image" or "Image:buffer" not in batch.schema.names:
            continue
        times = batch.column("message_log_time").cast("int64").to_pylist()
        buffers = batch.column("Image:buffer").to_pylist()
        for t, buffer in zip(times, buffers, strict=True):
            images[t] = np.asarray(buffer[0], dtype=np.uint8)
    assert len(images) == len(frames)
    for frame in frames:
        got = images[int(round(frame.time_s * 1e9))]
        np.testing.assert_array_equal(got.reshape(48, 64), frame.images[0])


# ------------------------------------------------------------------------------ versions
def _write_session(path: Path, frames: list[Frame], rates: bool, version: int) -> dict:
    """A session with one NaN joint sample, joints with or without rates, in one version."""
    t_joint = np.arange(0, 0.05 * len(frames) + 0.05, 0.001)
    q, q_dot = _joints(t_joint)
    q[700, 1] = np.nan
    quality = (MarkerQuality(0, (), 2.1), None)
    with RecordingWriter(
        path, model_toml=MODEL_TOML, rig_toml=RIG_TOML, format_version=version
    ) as writer:
        j = 0
        for k, frame in enumerate(frames):
            upto = int(np.searchsorted(t_joint, frame.time_s + 1e-12, side="right"))
            writer.write_joints(t_joint[j:upto], q[j:upto], q_dot[j:upto] if rates else None)
            j = upto
            writer.write_frame(frame, FrameLabels(plane=k // 10, noise_level=0.5), quality)
        writer.write_joints(t_joint[j:], q[j:], q_dot[j:] if rates else None)
    return dict(t_joint=t_joint, q=q, q_dot=q_dot)


@pytest.mark.parametrize("rates", [True, False], ids=["rates", "no rates"])
def test_version_1_and_version_2_files_read_identically(tmp_path, rates):
    """The same session written in format version 1 (joint blocks in JSON) and 2 (protobuf)
    reads back the same: joint stream, frames, labels, quality and warnings."""
    from mcap.reader import make_reader

    frames = _frames(30, np.random.default_rng(11), images=False)
    read = {}
    for version in (1, 2):
        path = tmp_path / f"v{version}.mcap"
        written = _write_session(path, frames, rates, version)
        with open(path, "rb") as f:
            reader = make_reader(f)
            metadata = {m.name: m.metadata for m in reader.iter_metadata()}
            channels = reader.get_summary().channels.values()
            encodings = {c.topic: c.message_encoding for c in channels}
        assert metadata["cathtrack"]["format_version"] == str(version)
        assert encodings["/joints"] == {1: "json", 2: "protobuf"}[version]
        with open_recording(path) as r:
            assert r.metadata.format_version == version
            read[version] = (r.report.warnings, r.joints, list(r.frames()))
    (warnings_1, joints_1, frames_1), (warnings_2, joints_2, frames_2) = read[1], read[2]
    assert warnings_1 == warnings_2 and len(warnings_1) == 1 and "NaN" in warnings_1[0]
    np.testing.assert_array_equal(joints_1.time_s, joints_2.time_s)
    np.testing.assert_array_equal(joints_1.q, joints_2.q)
    if rates:
        np.testing.assert_array_equal(joints_1.q_dot, joints_2.q_dot)
    else:
        assert joints_1.q_dot is None and joints_2.q_dot is None
    keep = np.ones(written["t_joint"].size, dtype=bool)
    keep[700] = False  # the NaN sample, dropped
    np.testing.assert_array_equal(joints_2.q, written["q"][keep])
    assert len(frames_1) == len(frames_2) == len(frames)
    for one, two in zip(frames_1, frames_2, strict=True):
        assert one.labels == two.labels and one.quality == two.quality
        a, b = one.frame, two.frame
        assert a.time_s == b.time_s and a.delta_L_true_rad == b.delta_L_true_rad
        for x, y in zip((a.q, a.q_dot, *a.uv, *a.cov), (b.q, b.q_dot, *b.uv, *b.cov), strict=True):
            np.testing.assert_array_equal(x, y)


def test_joint_blocks_hold_up_to_50_samples_and_copy_the_callers_arrays(tmp_path):
    """Samples given one at a time (as live) make blocks of 50; a change between samples
    with and without rates starts a block; the caller's arrays may be reused at once."""
    from mcap.reader import make_reader

    path = tmp_path / "blocks.mcap"
    q = np.zeros(3)
    rates = np.zeros(3)
    with RecordingWriter(path, model_toml=MODEL_TOML, rig_toml=RIG_TOML) as writer:
        for k in range(130):
            q[:] = (0.001 * k, 0.01 * k, -0.01 * k)
            rates[:] = k
            writer.write_joints(0.001 * k, q, rates if k < 120 else None)
    with open(path, "rb") as f:
        messages = [m for _, _, m in make_reader(f).iter_messages(topics=["/joints"])]
    sizes = [joint_samples._block(m.data)[0].size for m in messages]
    assert sizes == [50, 50, 20, 10]
    assert [joint_samples._block(m.data)[2] is None for m in messages] == [False] * 3 + [True]
    with open_recording(path) as r:
        # The samples without rates in a stream with rates have no rates: dropped (as in
        # version 1); the others are each sample as it was given.
        assert any("10 joint sample(s) hold NaN" in w for w in r.report.warnings)
        np.testing.assert_array_equal(r.joints.q[:, 1], 0.01 * np.arange(120))
        np.testing.assert_array_equal(r.joints.q_dot[:, 0], np.arange(120))
        np.testing.assert_array_equal(np.round(r.joints.time_s * 1e9), 1e6 * np.arange(120))


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, pos


def _wire_fields(data: bytes) -> list[tuple[int, int, object]]:
    """The top-level fields of a protobuf message: (number, wire type, int or bytes); this
    test's own reading of protobuf.dev's encoding rules, no cathtrack code."""
    out, pos = [], 0
    while pos < len(data):
        key, pos = _varint(data, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(data, pos)
            out.append((number, wire, value))
            continue
        if wire == 2:  # length-delimited
            size, pos = _varint(data, pos)
        else:  # 8 or 4 bytes
            size = {1: 8, 5: 4}[wire]
        out.append((number, wire, bytes(data[pos : pos + size])))
        pos += size
    return out


def test_joint_channel_decodes_with_the_schema_stored_in_the_file(recorded):
    """The /joints blocks decoded from the FileDescriptorSet of their schema record and
    protobuf's encoding rules alone (no cathtrack code, no protobuf runtime): the field
    names, numbers and types come from the file, the values are those written."""
    from mcap.reader import make_reader

    path, _, written = recorded
    with open(path, "rb") as f:
        messages = list(make_reader(f).iter_messages(topics=["/joints"]))
    schema = messages[0][0]
    assert (schema.name, schema.encoding) == ("cathtrack.JointSamples", "protobuf")
    # FileDescriptorSet.file (1): FileDescriptorProto package (2), message_type (4):
    # DescriptorProto name (1), field (2): FieldDescriptorProto name 1, number 3, label 4,
    # type 5, json_name 10 (the name itself: JSON exports keep the names of version 1)
    ((_, _, file),) = _wire_fields(schema.data)
    file_fields = _wire_fields(file)
    package = [v for n, _, v in file_fields if n == 2][0].decode()
    types = {
        package + "." + [v for n, _, v in _wire_fields(m) if n == 1][0].decode(): m
        for n, _, m in file_fields
        if n == 4
    }
    columns = {}
    for number, _, field in _wire_fields(types[schema.name]):
        if number == 2:
            f = {n: v for n, _, v in _wire_fields(field)}
            columns[f[1].decode()] = (f[3], f[4], f[5], f[10].decode())
    DOUBLE, SFIXED64, REPEATED = 1, 16, 3  # descriptor.proto's enums
    names = [
        "time_ns",
        "q_r_rad",
        "q_p_mm",
        "q_d_mm",
        "q_r_dot_rad_s",
        "q_p_dot_mm_s",
        "q_d_dot_mm_s",
    ]
    assert columns == {
        name: (k + 1, REPEATED, SFIXED64 if k == 0 else DOUBLE, name)
        for k, name in enumerate(names)
    }
    by_number = {
        number: (name, {DOUBLE: "<f8", SFIXED64: "<i8"}[kind])
        for name, (number, _, kind, _) in columns.items()
    }
    got: dict[str, list] = {name: [] for name in columns}
    for _, _, message in messages:
        for number, wire, value in _wire_fields(message.data):
            name, dtype = by_number[number]
            assert wire == 2  # packed
            got[name].append(np.frombuffer(value, dtype))
        assert message.log_time == got["time_ns"][-1][-1]  # a block's time: its last sample
    got = {name: np.concatenate(parts) for name, parts in got.items()}
    np.testing.assert_array_equal(
        got["time_ns"], np.round(written["t_joint"] * 1e9).astype(np.int64)
    )
    np.testing.assert_array_equal(np.column_stack([got[n] for n in names[1:4]]), written["q"])
    np.testing.assert_array_equal(np.column_stack([got[n] for n in names[4:]]), written["q_dot"])


def test_joint_channel_decodes_with_a_protobuf_library(recorded):
    """Google's protobuf runtime, given the schema record's FileDescriptorSet, decodes the
    blocks, and its own encoding of them is byte for byte the file's (the protobuf package is
    a test dependency only: cathtrack does not need it)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory
    from mcap.reader import make_reader

    path, _, written = recorded
    with open(path, "rb") as f:
        messages = list(make_reader(f).iter_messages(topics=["/joints"]))
    schema = messages[0][0]
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(file)
    JointSamples = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    blocks = [JointSamples.FromString(message.data) for _, _, message in messages]
    assert all(
        b.SerializeToString() == m.data for b, (_, _, m) in zip(blocks, messages, strict=True)
    )
    t_ns = np.concatenate([np.array(b.time_ns, dtype=np.int64) for b in blocks])
    np.testing.assert_array_equal(t_ns, np.round(written["t_joint"] * 1e9).astype(np.int64))
    q_d = np.concatenate([np.array(b.q_d_mm) for b in blocks])
    np.testing.assert_array_equal(q_d, written["q"][:, 2])
    r_p = np.concatenate([np.array(b.q_p_dot_mm_s) for b in blocks])
    np.testing.assert_array_equal(r_p, written["q_dot"][:, 1])
    # protobuf's JSON mapping (what `mcap cat --json` prints) keeps the field names
    exported = json_format.MessageToDict(blocks[1])
    assert list(exported) == list(joint_samples.COLUMNS)
    assert exported["q_r_rad"] == list(blocks[1].q_r_rad)


# ------------------------------------------------------------------------------ crash safety
def test_chunks_span_at_most_a_second_and_a_crash_loses_at_most_that(tmp_path):
    from mcap.reader import make_reader

    rng = np.random.default_rng(3)
    frames = _frames(100, rng, images=False)  # 5 s at 20 Hz, joints at 1 kHz
    path = tmp_path / "chunks.mcap"
    _write(path, frames)
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 5
    assert max(c.message_end_time - c.message_start_time for c in chunks) < 1_000_000_000
    # A crash at t = 3.5 s: what is on disk while the writer is still open.
    crash = tmp_path / "crash.mcap"
    writer = RecordingWriter(
        path.with_suffix(".live.mcap"), model_toml=MODEL_TOML, rig_toml=RIG_TOML
    )
    try:
        for frame in frames:
            if frame.time_s > 3.5:
                break
            writer.write_joints(frame.time_s, frame.q, frame.q_dot)
            writer.write_frame(frame)
        shutil.copyfile(path.with_suffix(".live.mcap"), crash)
    finally:
        writer.close()
    with open_recording(crash) as r:
        assert r.report.truncated
        kept = r.frame_times_s()
    assert kept.size > 0 and kept.max() >= 3.5 - 1.0 - 1e-9


# ------------------------------------------------------------------------------ bad input
def _one(warnings: list[str], word: str) -> str:
    hits = [w for w in warnings if word in w]
    assert len(hits) == 1, (word, warnings)
    return hits[0]


def test_truncated_file_keeps_the_readable_part(recorded, tmp_path):
    path, frames, _ = recorded
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(0.6 * len(data))])
    with open_recording(cut) as r:
        message = _one(r.report.warnings, "truncated")
        assert "lost" in message and r.report.truncated
        assert 0 < r.report.lost_seconds <= 1.0
        out = list(r.frames())
    assert 0 < len(out) < len(frames)
    # what was read is exactly the beginning of the session
    for got, sent in zip(out, frames, strict=False):
        np.testing.assert_array_equal(got.frame.uv[0], sent.uv[0])
        np.testing.assert_array_equal(got.frame.images[1], sent.images[1])


def test_not_mcap_and_unknown_version_and_missing_joints(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("this is not a recording\n")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        open_recording(text)
    with pytest.raises(RecordingError, match="cannot read recording"):
        open_recording(tmp_path / "absent.mcap")
    rng = np.random.default_rng(5)
    frames = _frames(5, rng, images=False)
    with pytest.raises(ValueError, match="format_version"):
        RecordingWriter(
            tmp_path / "v3.mcap", model_toml=MODEL_TOML, rig_toml=RIG_TOML, format_version=3
        )
    future = tmp_path / "future.mcap"
    _write(future, frames)
    # The metadata record is outside the chunks and has no CRC: its value "2" becomes "9".
    data = future.read_bytes()
    key = b"format_version" + struct.pack("<I", 1)
    assert data.count(key + b"2") == 1
    future.write_bytes(data.replace(key + b"2", key + b"9"))
    with pytest.raises(RecordingError, match="unknown recording format version '9'"):
        open_recording(future)
    no_joints = tmp_path / "no_joints.mcap"
    with RecordingWriter(no_joints, model_toml=MODEL_TOML, rig_toml=RIG_TOML) as writer:
        for frame in frames:
            writer.write_frame(frame)
    with pytest.raises(RecordingError, match="missing channel /joints"):
        open_recording(no_joints)


def test_missing_view_channel_keeps_the_other_view(tmp_path):
    rng = np.random.default_rng(6)
    frames = _frames(20, rng, images=False)
    path = tmp_path / "front_only.mcap"
    with RecordingWriter(path, model_toml=MODEL_TOML, rig_toml=RIG_TOML) as writer:
        for frame in frames:
            writer.write_joints(frame.time_s, frame.q, frame.q_dot)
            writer.write_raw(
                "/markers/front",
                int(round(frame.time_s * 1e9)),
                rec.encode_json(
                    {
                        "view": "front",
                        "unit": "px",
                        "uv": frame.uv[0].tolist(),
                        "cov": frame.cov[0].tolist(),
                    }
                ),
            )
    with open_recording(path) as r:
        _one(r.report.warnings, "/markers/side")
        _one(r.report.warnings, "/truth")
        out = list(r.frames())
    assert len(out) == len(frames)
    assert all(np.isnan(x.frame.uv[1]).all() for x in out)
    np.testing.assert_array_equal(out[4].frame.uv[0], frames[4].uv[0])


def test_out_of_order_duplicates_and_nan_are_counted_once_and_lose_nothing(tmp_path):
    rng = np.random.default_rng(8)
    frames = _frames(30, rng, images=False)
    path = tmp_path / "messy.mcap"
    order = list(range(30))
    order[10], order[11], order[12] = 12, 10, 11  # out of order
    with RecordingWriter(path, model_toml=MODEL_TOML, rig_toml=RIG_TOML) as writer:
        t_joint = np.arange(0, 1.6, 0.001)
        q, q_dot = _joints(t_joint)
        q[500] = np.nan  # one NaN joint sample
        writer.write_joints(t_joint, q, q_dot)
        for k in order:
            writer.write_frame(frames[k])
        writer.write_frame(
            replace(frames[20], uv=(frames[20].uv[0] + 1.0, frames[20].uv[1]))
        )  # duplicate
        stamp = int(round(frames[25].time_s * 1e9))
        nan_uv = frames[25].uv[0].copy()
        nan_uv[0] = [float("nan"), 1.0]
        writer.write_raw(
            "/markers/front",
            stamp + 1,
            json.dumps(  # NaN written by another tool
                {
                    "view": "front",
                    "unit": "px",
                    "uv": nan_uv.tolist(),
                    "cov": frames[25].cov[0].tolist(),
                }
            ).encode(),
        )
        # messages that do not fit their schema: skipped, the rest is read
        writer.write_raw("/joints", int(1.7e9), b'{"time_ns": [1700000000], "q": [[1, 2]]}')
        writer.write_raw("/truth", stamp + 2, b"[1, 2, 3]")
    with open_recording(path) as r:
        warnings = r.report.warnings
        _one(warnings, "out of time order")
        duplicate = _one(warnings, "repeat an earlier time stamp")
        assert "/markers/front" in duplicate or "/truth" in duplicate or "markers" in duplicate
        _one(warnings, "NaN or infinite")
        _one(warnings, "joint sample(s) hold NaN")
        malformed = _one(warnings, "do not match their schema")
        assert "/joints" in malformed and "/truth" in malformed
        out = list(r.frames())
    times = [x.frame.time_s for x in out]
    assert times == sorted(times)
    assert len(out) == 31  # 30 frames and the extra NaN frame: nothing lost
    by_time = {round(x.frame.time_s * 1e9): x.frame for x in out}
    np.testing.assert_array_equal(
        by_time[round(frames[20].time_s * 1e9)].uv[0], frames[20].uv[0]
    )  # the first of the duplicates
    nan_frame = by_time[stamp + 1]
    assert np.isnan(nan_frame.uv[0][0]).all() and np.isfinite(nan_frame.uv[0][1:]).all()
    # the joint value next to the dropped NaN sample is interpolated from its neighbours
    assert r.joints.time_s.size == t_joint.size - 1


def _chunks(data: bytes) -> list[tuple[int, int]]:
    """(offset, record length) of the chunk records of an MCAP file's data section."""
    out, offset = [], 8
    while offset < len(data):
        opcode, length = struct.unpack_from("<BQ", data, offset)
        if opcode == 0x0F:  # data end: the summary follows
            break
        if opcode == 6:
            out.append((offset, length))
        offset += 9 + length
    return out


def test_corrupt_chunk_is_skipped_and_the_rest_is_read(recorded, tmp_path):
    path, frames, _ = recorded
    data = bytearray(path.read_bytes())
    # flip bytes inside the third chunk's compressed data
    offset, length = _chunks(data)[2]
    middle = offset + 9 + length // 2
    data[middle : middle + 16] = bytes(16)
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(data))
    with open_recording(bad) as r:
        _one(r.report.warnings, "corrupt chunk")
        assert r.report.damage[0].kind in ("bad_crc", "bad_compression")
        assert not r.report.truncated
        n = len(list(r.frames()))
    assert 0 < n < len(frames)


@pytest.mark.parametrize("damaged", ["past the end", "longer", "shorter"])
def test_damaged_chunk_length_is_named_and_nothing_is_lost(recorded, tmp_path, damaged):
    """A chunk whose record length is damaged is read by its own content (its CRC checks
    it), and the report calls it a damaged length, not a truncated file."""
    path, frames, _ = recorded
    data = bytearray(path.read_bytes())
    offset, length = _chunks(data)[-2]  # the first second of frames
    wrong = {"past the end": 10**12, "longer": length + 5000, "shorter": length // 2}[damaged]
    struct.pack_into("<Q", data, offset + 1, wrong)
    bad = tmp_path / "length.mcap"
    bad.write_bytes(bytes(data))
    with open_recording(bad) as r:
        message = _one(r.report.warnings, "damaged record length")
        assert r.report.warnings == [message]
        assert [(d.kind, d.offset, d.lost) for d in r.report.damage] == [
            ("bad_length", offset, False)
        ]
        assert not r.report.truncated and r.report.lost_bytes == 0
        out = list(r.frames(images=False))
    assert len(out) == len(frames)


def test_garbage_is_skipped_up_to_the_next_chunk(recorded, tmp_path):
    path, frames, _ = recorded
    data = bytearray(path.read_bytes())
    (offset, _), (next_chunk, _) = _chunks(data)[-2:]
    # No record starts here any more (opcode 0 is reserved): the first second is lost.
    data[offset : offset + 64] = bytes(64)
    bad = tmp_path / "garbage.mcap"
    bad.write_bytes(bytes(data))
    with open_recording(bad) as r:
        message = _one(r.report.warnings, "no readable record")
        assert f"bytes {offset} to {next_chunk}" in message
        assert [d.kind for d in r.report.damage] == ["bad_record"]
        assert not r.report.truncated and r.report.lost_bytes == next_chunk - offset
        out = list(r.frames(images=False))
    assert 0 < len(out) < len(frames)
    # what follows the damage is read intact
    by_time = {round(f.time_s, 6): f for f in frames}
    for got in out:
        np.testing.assert_array_equal(got.frame.uv[0], by_time[round(got.frame.time_s, 6)].uv[0])
