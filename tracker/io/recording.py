"""Recordings of bi-plane tracking sessions in MCAP, written and read back (docs/recording.md).

A recording is one MCAP file (the ROS 2 bag format) with

- metadata records ``cathtrack`` (format name and version, start time), ``model`` (the model
  TOML text), ``rig`` (the rig TOML text: views and registered base pose) and ``settings``
  (JSON of whatever made the recording);
- JSON channels with JSON-schema schemas for the joint values (``/joints``, blocks of samples
  at up to 1 kHz), the segmented markers of each view with their covariances and quality
  (``/markers/front``, ``/markers/side``), the ground truth and the labels of the experiment
  (``/truth``) and the estimates of any method (``/estimates/<method>``);
- the camera frames as Foxglove ``foxglove.RawImage`` (protobuf, ``mono8``) on
  ``/camera/<view>/image``, and the empty-scene prior of each camera, which the segmentation
  subtracts, on ``/camera/<view>/background``: rerun and Foxglove show both as images.

Crash safety: the writer closes a chunk when it holds one second of log time or 4 MiB,
whichever comes first, and writes it out, so a crash loses at most the last second.

The reader scans the file record by record and validates as it goes. A file that is not
MCAP, is not a cathtrack recording, has an unknown format version or lacks the joint values
raises :class:`RecordingError` with one clear message. Everything else that can be read is
kept: a truncated file is read up to the last complete chunk (the report says how many
seconds were lost), out-of-order messages are sorted, duplicated time stamps keep the first
message, NaN values mark the points (or joint samples) as missing; each of these is counted
once in :class:`ReadReport`. Frames come back as :class:`tracker.types.Frame` -- the type
the live loop consumes -- with their joint values interpolated to the frame time, together
with the experiment's labels.
"""

from __future__ import annotations

import gc
import json
import math
import os
import struct
import tomllib
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from models.catheter import Catheter
from models.imaging import BiplaneRig, OrthographicPlane
from models.model_file import ModelFileError, catheter_from_dict
from models.rig_file import RIG_FORMAT, RIG_VERSION
from tracker.types import Estimate, Flag, Frame

Array = np.ndarray

FORMAT = "cathtrack-recording"
FORMAT_VERSION = 1
"""Version of the recording format that this module writes and reads."""

VIEWS = ("front", "side")
TOPIC_JOINTS = "/joints"
TOPIC_TRUTH = "/truth"
CHUNK_SECONDS = 1.0
"""A chunk is closed and written once it spans this much log time, s."""
CHUNK_BYTES = 4 * 1024 * 1024
"""...or once it holds this many (uncompressed) bytes."""
JOINT_BLOCK_SAMPLES = 50
"""Joint samples per /joints message at most (50 ms at 1 kHz)."""
MAX_JOINT_GAP_S = 0.1
"""Frames farther than this from the nearest joint samples get no joint values (skipped)."""
RATE_WINDOW_S = 0.02
"""Without recorded rates, a frame's joint rates are the slope over this window (as live)."""

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 1, 2, 3, 4, 5, 6
_OP_METADATA, _OP_DATA_END = 0x0C, 0x0F


def markers_topic(view: str) -> str:
    return f"/markers/{view}"


def image_topic(view: str) -> str:
    return f"/camera/{view}/image"


def background_topic(view: str) -> str:
    return f"/camera/{view}/background"


def estimate_topic(name: str) -> str:
    return f"/estimates/{name}"


class RecordingError(ValueError):
    """A file that cannot be read as a cathtrack recording (one message says why)."""


# ------------------------------------------------------------------------------- schemas
_NUMBER_OR_NULL = {"type": ["number", "null"]}
_XY = {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 2, "maxItems": 2}
_MATRIX_2X2 = {
    "type": ["array", "null"],
    "items": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2},
    "minItems": 2,
    "maxItems": 2,
}
_COLUMN = {"type": "array", "items": {"type": ["number", "null"]}}
JOINT_COLUMNS = ("q_r_rad", "q_p_mm", "q_d_mm")
"""Columns of the joint values in /joints (q_r, q_p, q_d)."""
RATE_COLUMNS = ("q_r_dot_rad_s", "q_p_dot_mm_s", "q_d_dot_mm_s")
"""Columns of the joint rates in /joints (optional)."""

SCHEMAS: dict[str, dict] = {
    "cathtrack.JointSamples": {
        "title": "cathtrack.JointSamples",
        "description": (
            "A block of joint samples in time order, one column per quantity (all columns of "
            "the same length): sample times on the clock of the MCAP log_time, the joint "
            "values, and their rates when the source measures them (all three rate columns, "
            "or none). null: a value that was not available."
        ),
        "type": "object",
        "properties": {
            "time_ns": {"type": "array", "items": {"type": "integer"}},
            **{name: _COLUMN for name in JOINT_COLUMNS + RATE_COLUMNS},
        },
        "required": ["time_ns", *JOINT_COLUMNS],
    },
    "cathtrack.Markers": {
        "title": "cathtrack.Markers",
        "description": (
            "Points segmented in one view at the frame time (= the message log_time). Rows "
            "[tip, marker_0, marker_1, ...] in the order of the model's marker_arclengths_mm; "
            "null rows for points not found. unit: px (pinhole rig) or mm (orthographic planes)."
        ),
        "type": "object",
        "properties": {
            "view": {"type": "string", "enum": list(VIEWS)},
            "unit": {"type": "string", "enum": ["px", "mm"]},
            "uv": {"type": "array", "items": _XY},
            "cov": {"type": "array", "items": _MATRIX_2X2},
            "quality": {
                "type": "object",
                "properties": {
                    "flags": {"type": "integer"},
                    "flag_names": {"type": "array", "items": {"type": "string"}},
                    "noise_sigma_gray": _NUMBER_OR_NULL,
                },
            },
        },
        "required": ["view", "unit", "uv", "cov"],
    },
    "cathtrack.Truth": {
        "title": "cathtrack.Truth",
        "description": (
            "Ground truth and experiment labels of the frame at this log_time. delta_L_rad is "
            "the true torsional loss and delta_1_rad = q_r + delta_L the true bending plane "
            "(wrapped to [-pi, pi)); null where unknown. plane and configuration index the "
            "experimental protocol; deflection_mm is the tip deflection by contact; "
            "noise_level the nominal segmentation noise (unit in the settings metadata)."
        ),
        "type": "object",
        "properties": {
            "delta_L_rad": _NUMBER_OR_NULL,
            "delta_1_rad": _NUMBER_OR_NULL,
            "plane": {"type": ["integer", "null"]},
            "configuration": {"type": ["integer", "null"]},
            "deflection_mm": _NUMBER_OR_NULL,
            "noise_level": _NUMBER_OR_NULL,
        },
        "required": ["delta_L_rad"],
    },
    "cathtrack.Estimate": {
        "title": "cathtrack.Estimate",
        "description": (
            "One estimator step at this log_time: delta_L and its standard deviation (rad), "
            "the bending plane delta_1 = q_r + delta_L, flags (bit set of tracker.Flag, with "
            "their names), and the normalised innovation squared where the method has one."
        ),
        "type": "object",
        "properties": {
            "delta_L_rad": _NUMBER_OR_NULL,
            "std_rad": _NUMBER_OR_NULL,
            "delta_1_rad": _NUMBER_OR_NULL,
            "q_r_rad": {"type": "number"},
            "flags": {"type": "integer"},
            "flag_names": {"type": "array", "items": {"type": "string"}},
            "nis": _NUMBER_OR_NULL,
            "nis_dof": {"type": "integer"},
            "informative_radius_mm": {"type": "number"},
        },
        "required": ["delta_L_rad", "std_rad", "q_r_rad", "flags"],
    },
}
_TOPIC_SCHEMA = {
    TOPIC_JOINTS: "cathtrack.JointSamples",
    TOPIC_TRUTH: "cathtrack.Truth",
    markers_topic("front"): "cathtrack.Markers",
    markers_topic("side"): "cathtrack.Markers",
}


def schema_for_topic(topic: str) -> str | None:
    """Name of the JSON schema of a cathtrack topic (None for image topics and unknown ones)."""
    if topic.startswith("/estimates/"):
        return "cathtrack.Estimate"
    return _TOPIC_SCHEMA.get(topic)


def _finite_or_none(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _rows(a: Array) -> list:
    """Rows of a float array as nested lists with None for rows that contain a non-finite value."""
    a = np.asarray(a, dtype=float)
    ok = np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)
    return [row if good else None for row, good in zip(a.tolist(), ok.tolist(), strict=True)]


def encode_json(obj: Any) -> bytes:
    """JSON bytes of a message (strict JSON: callers write NaN as null)."""
    if _orjson is not None:
        return _orjson.dumps(obj)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


try:  # orjson parses the joint blocks about five times faster than json
    import orjson as _orjson
except ImportError:  # pragma: no cover - orjson is a dependency
    _orjson = None


def _loads(data: bytes) -> Any:
    """Parse JSON; non-standard NaN/Infinity literals (other writers) are accepted too."""
    if _orjson is not None:
        try:
            return _orjson.loads(data)
        except _orjson.JSONDecodeError:
            pass
    return json.loads(data)


# ------------------------------------------------------------------------------ labels
@dataclass(frozen=True)
class FrameLabels:
    """What the experiment says about a frame, beyond the Frame itself (from ``/truth``).

    Parameters
    ----------
    plane : int, optional
        Index of the bending plane of the protocol.
    configuration : int, optional
        Index of the joint configuration (over the whole protocol).
    deflection_mm : float, optional
        Tip deflection by contact, mm (0: free).
    noise_level : float, optional
        Nominal segmentation noise of the configuration (unit in the settings metadata).
    delta_1_true_rad : float, optional
        True bending plane q_r + delta_L, wrapped to [-pi, pi).
    """

    plane: int | None = None
    configuration: int | None = None
    deflection_mm: float | None = None
    noise_level: float | None = None
    delta_1_true_rad: float | None = None


@dataclass(frozen=True)
class MarkerQuality:
    """Quality of one view's segmentation: flags (bit set, with names) and its noise estimate."""

    flags: int = 0
    flag_names: tuple[str, ...] = ()
    noise_sigma_gray: float | None = None

    def to_json(self) -> dict:
        sigma = None if self.noise_sigma_gray is None else _finite_or_none(self.noise_sigma_gray)
        return {
            "flags": int(self.flags),
            "flag_names": list(self.flag_names),
            "noise_sigma_gray": sigma,
        }

    @classmethod
    def from_segmentation(cls, view_segmentation) -> MarkerQuality:
        """From a :class:`tracker.vision.segmentation.ViewSegmentation`."""
        flags = view_segmentation.flags
        names = tuple(f.name for f in type(flags) if f and f in flags and f.name)
        return cls(int(flags), names, float(view_segmentation.noise_sigma_gray))


@dataclass(frozen=True)
class RecordedFrame:
    """A frame read from a recording, its labels, and each view's segmentation quality."""

    frame: Frame
    labels: FrameLabels
    quality: tuple[MarkerQuality | None, MarkerQuality | None] = (None, None)


@dataclass(frozen=True)
class RecordedEstimate:
    """An estimate read from ``/estimates/<method>``."""

    time_s: float
    estimate: Estimate


# --------------------------------------------------------------------------- rig files
def _matrix(table: Mapping, key: str, shape: tuple[int, ...], where: str) -> Array:
    if key not in table:
        raise RecordingError(f"{where}: missing key '{key}'")
    try:
        value = np.array(table[key], dtype=float)
    except (TypeError, ValueError):
        raise RecordingError(f"{where}: '{key}' must be numbers of shape {shape}") from None
    if value.shape != shape:
        raise RecordingError(f"{where}: '{key}' must have shape {shape}, got {value.shape}")
    return value


def _toml_value(x) -> str:
    if isinstance(x, str):
        return json.dumps(x)
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, int | np.integer):
        return str(int(x))
    if isinstance(x, float | np.floating):
        return repr(float(x))
    return "[" + ", ".join(_toml_value(v) for v in x) + "]"


def rig_toml(rig: BiplaneRig, R_w_b: Array, o_b_w_mm: Array) -> str:
    """A rig file (models.rig_file, docs/vision.md) with the registered base pose in ``[base]``.

    Cameras are written as calibrated pinhole views, planes by their normal and in-plane
    rotation. Floats are written with ``repr``, so reading the text back gives the same
    numbers (planes up to rounding of the in-plane rotation).
    """
    lines = [
        "# Bi-plane rig and registered catheter base pose. Units: mm, rad, px.",
        f'format = "{RIG_FORMAT}"',
        f"version = {RIG_VERSION}",
        "",
        "[base]  # registered pose of the catheter base {B} in {W}",
        f"R_w_b = {_toml_value(np.asarray(R_w_b, float).tolist())}",
        f"o_b_w_mm = {_toml_value(np.asarray(o_b_w_mm, float).tolist())}",
    ]
    for name, view in (("front", rig.front), ("side", rig.side)):
        lines += ["", f"[{name}]"]
        if isinstance(view, OrthographicPlane):
            n = view.normal_w
            reference = OrthographicPlane.from_normal(n).R_w_view
            u = np.asarray(view.R_w_view)[:, 0]
            angle = float(np.arctan2(u @ reference[:, 1], u @ reference[:, 0]))
            lines += [
                f"normal_w = {_toml_value(n.tolist())}",
                f"in_plane_rotation_rad = {_toml_value(angle)}",
            ]
        else:
            lines += [
                f"image_size = {_toml_value(list(view.image_size))}",
                f"K = {_toml_value(np.asarray(view.K).tolist())}",
                f"dist = {_toml_value(np.asarray(view.dist).tolist())}",
                f"R_cam_w = {_toml_value(np.asarray(view.R_cam_w).tolist())}",
                f"t_cam_w = {_toml_value(np.asarray(view.t_cam_w).tolist())}",
                f"normal_w = {_toml_value((-np.asarray(view.R_cam_w)[2]).tolist())}",
            ]
    return "\n".join(lines) + "\n"


def rig_from_toml(text: str, source: str = "rig") -> tuple[BiplaneRig, Array, Array]:
    """The rig and base pose ``(rig, R_w_b, o_b_w_mm)`` of :func:`rig_toml` text.

    Views with a camera (``K``) are pinhole views, views with only ``normal_w`` planes.
    """
    from models.rig_file import rig_from_dict

    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RecordingError(f"{source}: malformed TOML: {exc}") from None
    front = data.get("front")
    model = "pinhole" if isinstance(front, dict) and "K" in front else "orthographic"
    try:
        rig = rig_from_dict(data, source, model)
        base = data.get("base")
        if not isinstance(base, dict):
            raise RecordingError(f"{source}: missing table [base] (registered base pose)")
        R_w_b = _matrix(base, "R_w_b", (3, 3), f"{source} [base]")
        o_b_w_mm = _matrix(base, "o_b_w_mm", (3,), f"{source} [base]")
    except RecordingError:
        raise
    except ValueError as exc:
        raise RecordingError(str(exc)) from None
    return rig, R_w_b, o_b_w_mm


# ------------------------------------------------------------------------------ images
def _image_schema():
    from foxglove.messages import RawImage

    return RawImage.get_schema()


def encode_image(image: Array, frame_id: str, time_ns: int) -> bytes:
    """A grayscale uint8 image as a ``foxglove.RawImage`` protobuf message (``mono8``)."""
    from foxglove import messages

    image = np.ascontiguousarray(image)
    if image.dtype != np.uint8 or image.ndim != 2:
        raise ValueError(f"images must be 2-D uint8 (mono8), got {image.dtype} {image.shape}")
    height, width = image.shape
    return messages.RawImage(
        timestamp=messages.Timestamp(sec=time_ns // 1_000_000_000, nsec=time_ns % 1_000_000_000),
        frame_id=frame_id,
        width=width,
        height=height,
        encoding="mono8",
        step=width,
        data=image.tobytes(),
    ).encode()


def _varint(buf: memoryview, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("truncated varint")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7


def _protobuf_fields(data: bytes) -> dict[int, Any]:
    """Top-level fields of a protobuf message: number -> int (varint/fixed) or memoryview."""
    buf = memoryview(data)
    fields: dict[int, Any] = {}
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            fields[number], pos = _varint(buf, pos)
        elif wire == 1:
            fields[number] = struct.unpack_from("<Q", buf, pos)[0]
            pos += 8
        elif wire == 2:
            length, pos = _varint(buf, pos)
            if pos + length > len(buf):
                raise ValueError("truncated length-delimited field")
            fields[number] = buf[pos : pos + length]
            pos += length
        elif wire == 5:
            fields[number] = struct.unpack_from("<I", buf, pos)[0]
            pos += 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
    return fields


def decode_image(data: bytes) -> Array:
    """The uint8 array (height, width) of a ``foxglove.RawImage`` message in ``mono8``.

    foxglove.RawImage fields: 1 timestamp, 7 frame_id, 2 width (fixed32), 3 height (fixed32),
    4 encoding, 5 step (fixed32), 6 data.
    """
    fields = _protobuf_fields(data)
    width, height, step = fields.get(2, 0), fields.get(3, 0), fields.get(5, 0)
    encoding = bytes(fields.get(4, b"")).decode()
    if encoding != "mono8":
        raise ValueError(f"image encoding {encoding!r} is not supported (cathtrack writes mono8)")
    pixels = np.frombuffer(fields.get(6, b""), dtype=np.uint8)
    if width < 1 or height < 1 or step < width or pixels.size < step * height:
        raise ValueError(f"image of {pixels.size} bytes does not fit {width}x{height}, step {step}")
    return pixels[: step * height].reshape(height, step)[:, :width].copy()


# ------------------------------------------------------------------------------ writing
class RecordingWriter:
    """Writes a recording; use as a context manager (the file is complete after ``close``).

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file to create.
    model_toml, rig_toml : str
        Text of the model file (docs/model-file.md) and of the rig (:func:`rig_toml`).
    settings : mapping, optional
        What made the recording, stored as JSON (e.g. the protocol settings).
    point_unit : {"px", "mm"}
        Unit of the marker coordinates: px for a pinhole rig, mm for orthographic planes.
    start_time_ns : int
        Log time of session time 0 (0 for simulations; ``time.time_ns()`` when live).
    chunk_seconds, chunk_bytes : float, int
        A chunk is written when it spans ``chunk_seconds`` of log time or holds ``chunk_bytes``.
    fsync : bool
        Also ``os.fsync`` at every chunk (survives a power cut, not only a crash).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        model_toml: str,
        rig_toml: str,
        settings: Mapping[str, Any] | None = None,
        point_unit: str = "px",
        start_time_ns: int = 0,
        chunk_seconds: float = CHUNK_SECONDS,
        chunk_bytes: int = CHUNK_BYTES,
        fsync: bool = False,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        if point_unit not in ("px", "mm"):
            raise ValueError(f"point_unit must be 'px' or 'mm', got {point_unit!r}")
        if not chunk_seconds > 0:
            raise ValueError(f"chunk_seconds must be positive, got {chunk_seconds}")
        self.path = Path(path)
        self.point_unit = point_unit
        self.start_time_ns = int(start_time_ns)
        self._chunk_ns = int(chunk_seconds * 1e9)
        self._fsync = fsync
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._mcap = Writer(
            self._file, chunk_size=int(chunk_bytes), compression=CompressionType.ZSTD
        )
        self._mcap.start(profile="", library=f"cathtrack {_version()}")
        self._mcap.add_metadata(
            "cathtrack",
            {
                "format": FORMAT,
                "format_version": str(FORMAT_VERSION),
                "start_time_ns": str(self.start_time_ns),
                "writer": f"cathtrack {_version()}",
            },
        )
        self._mcap.add_metadata("model", {"toml": model_toml})
        self._mcap.add_metadata("rig", {"toml": rig_toml})
        self._mcap.add_metadata("settings", {"json": json.dumps(dict(settings or {}))})
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._chunk_start_ns: int | None = None
        self._flush_after_next = False
        self._joints: list[tuple[int, list, list | None]] = []
        self._closed = False
        for topic in (TOPIC_JOINTS, markers_topic("front"), markers_topic("side"), TOPIC_TRUTH):
            self._channel(topic)

    # ---------------------------------------------------------------- channels
    def _channel(self, topic: str) -> int:
        channel = self._channels.get(topic)
        if channel is not None:
            return channel
        name = schema_for_topic(topic)
        if name is not None:
            encoding, schema_encoding = "json", "jsonschema"
            schema_data = json.dumps(SCHEMAS[name], indent=1).encode()
        else:
            schema = _image_schema()
            name, schema_encoding, encoding = schema.name, schema.encoding, "protobuf"
            schema_data = bytes(schema.data)
        if name not in self._schemas:
            self._schemas[name] = self._mcap.register_schema(name, schema_encoding, schema_data)
        channel = self._mcap.register_channel(topic, encoding, self._schemas[name])
        self._channels[topic] = channel
        # The channel record sits in the open chunk: write that chunk out with its first
        # message, so that a crash cannot lose the definition of later chunks' channels.
        self._flush_after_next = True
        return channel

    def _time_ns(self, time_s: float) -> int:
        if not math.isfinite(time_s):
            raise ValueError(f"time stamps must be finite, got {time_s}")
        return self.start_time_ns + int(round(time_s * 1e9))

    def write_raw(self, topic: str, time_ns: int, data: bytes) -> None:
        """Write one message as is, on the clock of log_time (tools and tests; no checks)."""
        time_ns = int(time_ns)
        start = self._chunk_start_ns
        if start is not None and abs(time_ns - start) >= self._chunk_ns:
            # The open chunk holds a second of data: write it out, this message starts the next.
            self._flush_chunk()
        channel = self._channel(topic)
        self._mcap.add_message(channel, log_time=time_ns, data=data, publish_time=time_ns)
        if self._chunk_start_ns is None:
            self._chunk_start_ns = time_ns
        if self._flush_after_next:
            self._flush_chunk()

    def _flush_chunk(self) -> None:
        self._mcap.flush()
        if self._fsync:
            os.fsync(self._file.fileno())
        self._chunk_start_ns = None
        self._flush_after_next = False

    # ---------------------------------------------------------------- messages
    def write_joints(self, time_s, q, q_dot=None) -> None:
        """Joint samples: one (``time_s`` float, ``q`` (3,)) or many (``(n,)``, ``(n, 3)``).

        Samples are buffered into blocks of up to :data:`JOINT_BLOCK_SAMPLES`; a frame, an
        estimate or :meth:`close` writes the pending block first.
        """
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        q = np.asarray(q, dtype=float).reshape(t.size, 3)
        rates = None if q_dot is None else np.asarray(q_dot, dtype=float).reshape(t.size, 3)
        if self._joints and (rates is None) != (self._joints[-1][2] is None):
            self._write_joint_block()
        stamps = [self._time_ns(x) for x in t.tolist()]
        q_rows = _rows(q)
        rate_rows = [None] * t.size if rates is None else _rows(rates)
        for stamp, row, rate in zip(stamps, q_rows, rate_rows, strict=True):
            self._joints.append((stamp, row, rate if rates is not None else None))
            if len(self._joints) >= JOINT_BLOCK_SAMPLES:
                self._write_joint_block()

    def _write_joint_block(self) -> None:
        if not self._joints:
            return
        block, self._joints = self._joints, []
        message: dict[str, list] = {"time_ns": [stamp for stamp, _, _ in block]}
        rows = [row if row is not None else [None] * 3 for _, row, _ in block]
        for k, name in enumerate(JOINT_COLUMNS):
            message[name] = [row[k] for row in rows]
        if any(rate is not None for _, _, rate in block):
            rates = [rate if rate is not None else [None] * 3 for _, _, rate in block]
            for k, name in enumerate(RATE_COLUMNS):
                message[name] = [rate[k] for rate in rates]
        self.write_raw(TOPIC_JOINTS, block[-1][0], encode_json(message))

    def write_background(self, view: str, image: Array, time_s: float = 0.0) -> None:
        """The empty-scene prior image of one camera (needed to segment its frames)."""
        if view not in VIEWS:
            raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
        stamp = self._time_ns(time_s)
        self.write_raw(background_topic(view), stamp, encode_image(image, view, stamp))

    def write_frame(
        self,
        frame: Frame,
        labels: FrameLabels | None = None,
        quality: Sequence[MarkerQuality | None] = (None, None),
        images: bool = True,
    ) -> None:
        """One frame: both views' markers, their images (if the frame has them and ``images``),
        and the truth and labels. The frame's joint values are not written here: the joint
        values are their own stream (:meth:`write_joints`)."""
        self._write_joint_block()
        stamp = self._time_ns(frame.time_s)
        views = (
            (frame.uv_front, frame.cov_front),
            (frame.uv_side, frame.cov_side),
        )
        for k, (view, (uv, cov)) in enumerate(zip(VIEWS, views, strict=True)):
            uv = np.asarray(uv, dtype=float)
            cov = np.asarray(cov, dtype=float)
            missing = ~np.all(np.isfinite(uv), axis=-1)
            cov_rows = _rows(cov)
            message = {
                "view": view,
                "unit": self.point_unit,
                "uv": _rows(uv),
                "cov": [
                    None if gone else row
                    for row, gone in zip(cov_rows, missing.tolist(), strict=True)
                ],
            }
            if quality[k] is not None:
                message["quality"] = quality[k].to_json()
            self.write_raw(markers_topic(view), stamp, encode_json(message))
        if images and frame.images is not None:
            for view, image in zip(VIEWS, frame.images, strict=True):
                self.write_raw(image_topic(view), stamp, encode_image(image, view, stamp))
        labels = labels or FrameLabels()
        truth = {
            "delta_L_rad": None
            if frame.delta_L_true_rad is None
            else _finite_or_none(frame.delta_L_true_rad),
            "delta_1_rad": None
            if labels.delta_1_true_rad is None
            else _finite_or_none(labels.delta_1_true_rad),
            "plane": labels.plane,
            "configuration": labels.configuration,
            "deflection_mm": None
            if labels.deflection_mm is None
            else _finite_or_none(labels.deflection_mm),
            "noise_level": None
            if labels.noise_level is None
            else _finite_or_none(labels.noise_level),
        }
        self.write_raw(TOPIC_TRUTH, stamp, encode_json(truth))

    def write_estimate(self, name: str, estimate: Estimate) -> None:
        """One step of estimator ``name`` on ``/estimates/<name>`` at the estimate's time."""
        self._write_joint_block()
        stamp = self._time_ns(estimate.time_s)
        flags = estimate.flags
        message = {
            "delta_L_rad": _finite_or_none(estimate.delta_L_rad),
            "std_rad": _finite_or_none(estimate.std_rad),
            "delta_1_rad": _finite_or_none(estimate.delta_1_rad),
            "q_r_rad": float(estimate.q_r_rad),
            "flags": int(flags.value),
            "flag_names": [f.name for f in Flag if f.value and f in flags],
            "nis": None if estimate.nis is None else _finite_or_none(estimate.nis),
            "nis_dof": int(estimate.nis_dof),
            "informative_radius_mm": float(estimate.informative_radius_mm),
        }
        self.write_raw(estimate_topic(name), stamp, encode_json(message))

    def close(self) -> None:
        """Write the pending joints, the last chunk and the MCAP summary, and close the file."""
        if self._closed:
            return
        self._closed = True
        try:
            self._write_joint_block()
            self._mcap.finish()
        finally:
            self._file.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("cathtrack")
    except metadata.PackageNotFoundError:
        return "0+unknown"


# ------------------------------------------------------------------------------ reading
@dataclass
class ReadReport:
    """What the reader found: message counts, and every problem, counted once per kind."""

    path: str
    messages: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    frames: int = 0
    joint_samples: int = 0
    truncated: bool = False
    lost_seconds: float = 0.0
    lost_bytes: int = 0
    last_time_s: float | None = None

    @property
    def ok(self) -> bool:
        return not self.warnings

    def summary(self) -> str:
        """A few lines for the console and the report."""
        lines = [
            f"{self.path}: {self.frames} frames, {self.joint_samples} joint samples, "
            + ", ".join(f"{topic} {n}" for topic, n in sorted(self.messages.items()))
        ]
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


@dataclass(frozen=True)
class JointSamples:
    """The joint stream of a recording, sorted by time."""

    time_s: Array  # (n,)
    q: Array  # (n, 3)
    q_dot: Array | None  # (n, 3), or None when the recording has no rates


@dataclass(frozen=True)
class RecordingMetadata:
    format_version: int
    start_time_ns: int
    writer: str
    model_toml: str
    rig_toml: str
    settings: dict


@dataclass
class _ImageRef:
    chunk_offset: int  # -1: the message was outside chunks, data kept in memory
    position: int
    length: int
    data: bytes | None = None


@dataclass
class _Counter:
    """Counts of one kind of problem per topic, turned into one warning each."""

    counts: dict[tuple[str, str], int] = field(default_factory=dict)

    def add(self, kind: str, topic: str, n: int = 1) -> None:
        self.counts[(kind, topic)] = self.counts.get((kind, topic), 0) + n


_PROBLEMS = {
    "out_of_order": "message(s) out of time order ({where}): sorted by time",
    "duplicate": "message(s) repeat an earlier time stamp ({where}): kept the first of each",
    "nan": "message(s) hold NaN or infinite values ({where}): those points count as missing",
    "nan_joints": "joint sample(s) hold NaN or null values ({where}): skipped",
    "nan_truth": "message(s) hold a NaN truth ({where}): truth unknown for those frames",
    "malformed": "message(s) do not match their schema ({where}): skipped",
    "bad_image": "image(s) cannot be decoded ({where}): those frames have no images",
    "unknown_channel": "message(s) on an undeclared channel ({where}): skipped",
}
"""One warning per kind of problem, whatever the number of topics it touches."""


def _problem_warnings(counts: dict[tuple[str, str], int]) -> list[str]:
    by_kind: dict[str, dict[str, int]] = {}
    for (kind, topic), n in counts.items():
        by_kind.setdefault(kind, {})[topic] = n
    out = []
    for kind in _PROBLEMS:
        topics = by_kind.get(kind)
        if topics:
            where = ", ".join(f"{n} on {topic}" for topic, n in sorted(topics.items()))
            out.append(f"{sum(topics.values())} " + _PROBLEMS[kind].format(where=where))
    return out


class Recording:
    """A recording read from an MCAP file (see :func:`open_recording`)."""

    def __init__(self, path: str | Path, max_joint_gap_s: float = MAX_JOINT_GAP_S) -> None:
        self.path = Path(path)
        self.max_joint_gap_s = float(max_joint_gap_s)
        self.report = ReadReport(str(self.path))
        self._problems = _Counter()
        self._metadata_raw: dict[str, dict[str, str]] = {}
        self._joints_raw: list[tuple[int, Any, Any]] = []
        self._per_frame: dict[str, dict[int, Any]] = {}
        self._estimates_raw: dict[str, dict[int, dict]] = {}
        self._chunk_cache: tuple[int, bytes] | None = None
        # The scan allocates many small objects and frees none: the cyclic garbage collector
        # would only rescan them (a third of the reading time), so it waits until the end.
        self._file: BinaryIO | None = None
        collecting = gc.isenabled()
        gc.disable()
        try:
            self._scan()
            self.metadata = self._check_metadata()
            self._assemble()
        except BaseException:
            self.close()
            raise
        finally:
            if collecting:
                gc.enable()

    # ---------------------------------------------------------------- scanning
    def _scan(self) -> None:
        try:
            self._file = open(self.path, "rb")  # noqa: SIM115 - kept open for lazy images
        except OSError as exc:
            raise RecordingError(f"cannot read recording {self.path}: {exc.strerror}") from None
        f = self._file
        size = os.fstat(f.fileno()).st_size
        magic = f.read(len(_MCAP_MAGIC))
        if magic != _MCAP_MAGIC:
            raise RecordingError(
                f"{self.path} is not an MCAP file (it does not start with the MCAP magic bytes)"
            )
        self._channels: dict[int, tuple[str, str]] = {}  # id -> (topic, encoding)
        self._schemas: dict[int, tuple[str, str]] = {}
        self._last_time: dict[str, int] = {}
        self._max_time: int | None = None
        footer = False
        while True:
            offset = f.tell()
            head = f.read(9)
            if len(head) == 0:
                break
            if len(head) < 9:
                self._truncated(offset, size, None)
                break
            opcode, length = struct.unpack("<BQ", head)
            if offset + 9 + length > size:
                self._truncated(offset, size, opcode)
                break
            if opcode == _OP_CHUNK:
                self._read_chunk(offset + 9, length)
                continue
            body = f.read(length)
            if opcode in (_OP_DATA_END, _OP_FOOTER):
                # The data section is complete; what follows is the summary (indexes).
                footer = True
                break
            self._record(opcode, body, -1, 0)
        if not footer and not self.report.truncated:
            self._truncated(f.tell(), size, None)

    def _truncated(self, offset: int, size: int, opcode: int | None) -> None:
        report = self.report
        report.truncated = True
        report.lost_bytes = max(size - offset, 0)
        lost = ""
        if opcode == _OP_CHUNK and size - offset >= 9 + 16:
            self._file.seek(offset + 9)
            start_ns, end_ns = struct.unpack("<QQ", self._file.read(16))
            start0 = self._start_ns()
            report.lost_seconds = max((end_ns - start_ns) / 1e9, 0.0)
            lost = (
                f"; the incomplete chunk held t = {(start_ns - start0) / 1e9:.3f} to"
                f" {(end_ns - start0) / 1e9:.3f} s ({report.lost_seconds:.3f} s of data),"
                " which is lost"
            )
        end = (
            ""
            if self._max_time is None
            else f" up to t = {(self._max_time - self._start_ns()) / 1e9:.3f} s"
        )
        report.warnings.append(
            f"the file is truncated (no MCAP footer; {report.lost_bytes} bytes at the end form"
            f" no complete record): read everything{end}{lost}"
        )

    def _start_ns(self) -> int:
        try:
            return int(self._metadata_raw.get("cathtrack", {}).get("start_time_ns", 0))
        except ValueError:
            return 0

    def _read_chunk(self, body_offset: int, length: int) -> None:
        f = self._file
        head = f.read(8 + 8 + 8 + 4 + 4)
        start_ns, end_ns, uncompressed_size, crc, n = struct.unpack("<QQQII", head)
        compression = f.read(n).decode()
        (data_length,) = struct.unpack("<Q", f.read(8))
        data = f.read(data_length)
        f.seek(body_offset + length)
        try:
            records = _decompress(compression, data, uncompressed_size)
            if crc and zlib.crc32(records) != crc:
                raise ValueError("CRC mismatch")
        except (ValueError, OSError, RuntimeError) as exc:
            start0 = self._start_ns()
            self.report.lost_seconds += (end_ns - start_ns) / 1e9
            self.report.warnings.append(
                f"a corrupt chunk at byte {body_offset - 9} ({exc}) was skipped: data from"
                f" t = {(start_ns - start0) / 1e9:.3f} to {(end_ns - start0) / 1e9:.3f} s lost"
            )
            return
        buf = memoryview(records)
        size = len(buf)
        chunk_offset = body_offset - 9
        record_head, message_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
        message = self._message
        pos = 0
        while pos + 9 <= size:
            opcode, rlen = record_head(buf, pos)
            start = pos + 9
            pos = start + rlen
            if pos > size:
                break
            if opcode == _OP_MESSAGE:
                channel_id, _sequence, log_time = message_head(buf, start)
                message(channel_id, log_time, buf[start + 22 : pos], chunk_offset, start + 22)
            else:
                self._record(opcode, buf[start:pos], chunk_offset, start)

    def _record(self, opcode: int, body, chunk_offset: int, position: int) -> None:
        if opcode == _OP_MESSAGE:
            channel_id, _sequence, log_time, _publish = struct.unpack_from("<HIQQ", body, 0)
            self._message(channel_id, log_time, body[22:], chunk_offset, position + 22)
        elif opcode == _OP_CHANNEL:
            (channel_id,) = struct.unpack_from("<H", body, 0)
            (schema_id,) = struct.unpack_from("<H", body, 2)
            topic, pos = _string(body, 4)
            encoding, pos = _string(body, pos)
            self._channels[channel_id] = (topic, encoding)
            self.report.messages.setdefault(topic, 0)
        elif opcode == _OP_SCHEMA:
            (schema_id,) = struct.unpack_from("<H", body, 0)
            name, pos = _string(body, 2)
            encoding, pos = _string(body, pos)
            self._schemas[schema_id] = (name, encoding)
        elif opcode == _OP_METADATA:
            name, pos = _string(body, 0)
            (nbytes,) = struct.unpack_from("<I", body, pos)
            pos += 4
            end = pos + nbytes
            entries = {}
            while pos < end:
                key, pos = _string(body, pos)
                value, pos = _string(body, pos)
                entries[key] = value
            self._metadata_raw[name] = entries
        elif opcode == _OP_HEADER:
            profile, _ = _string(body, 0)
            self._profile = profile

    def _message(self, channel_id: int, log_time: int, data, chunk_offset: int, position: int):
        channel = self._channels.get(channel_id)
        if channel is None:
            self._problems.add("unknown_channel", f"channel {channel_id}")
            return
        topic = channel[0]
        messages = self.report.messages
        messages[topic] = messages.get(topic, 0) + 1
        last = self._last_time.get(topic)
        if last is None or log_time >= last:
            self._last_time[topic] = log_time
        else:
            self._problems.add("out_of_order", topic)
        if self._max_time is None or log_time > self._max_time:
            self._max_time = log_time
        if topic == TOPIC_JOINTS:
            payload = self._json(topic, data)
            if payload is not None:
                self._joints_raw.append((log_time, payload, topic))
            return
        if topic.startswith("/camera/"):
            ref = _ImageRef(chunk_offset, position, len(data))
            if chunk_offset < 0:
                ref.data = bytes(data)
            self._store(topic, log_time, ref)
            return
        if topic.startswith("/estimates/"):
            payload = self._json(topic, data)
            if payload is not None:
                store = self._estimates_raw.setdefault(topic[len("/estimates/") :], {})
                if log_time in store:
                    self._problems.add("duplicate", topic)
                else:
                    store[log_time] = payload
            return
        if topic in (TOPIC_TRUTH, markers_topic("front"), markers_topic("side")):
            payload = self._json(topic, data)
            if payload is not None:
                self._store(topic, log_time, payload)

    def _store(self, topic: str, log_time: int, value) -> None:
        store = self._per_frame.setdefault(topic, {})
        if log_time in store:
            self._problems.add("duplicate", topic)
        else:
            store[log_time] = value

    def _json(self, topic: str, data) -> dict | None:
        try:
            payload = _loads(bytes(data))
        except (ValueError, UnicodeDecodeError):
            self._problems.add("malformed", topic)
            return None
        if not isinstance(payload, dict):
            self._problems.add("malformed", topic)
            return None
        return payload

    # ---------------------------------------------------------------- checks
    def _check_metadata(self) -> RecordingMetadata:
        info = self._metadata_raw.get("cathtrack")
        if info is None or info.get("format") != FORMAT:
            raise RecordingError(
                f"{self.path} is an MCAP file but not a cathtrack recording (no 'cathtrack'"
                f' metadata record naming the format "{FORMAT}")'
            )
        version = info.get("format_version", "")
        if version != str(FORMAT_VERSION):
            raise RecordingError(
                f"{self.path}: unknown recording format version {version!r}; this cathtrack"
                f" reads version {FORMAT_VERSION}"
            )
        for name in ("model", "rig"):
            if "toml" not in self._metadata_raw.get(name, {}):
                raise RecordingError(f"{self.path}: missing the '{name}' metadata record")
        try:
            settings = json.loads(self._metadata_raw.get("settings", {}).get("json", "{}"))
        except ValueError:
            settings = {}
            self.report.warnings.append("the settings metadata is not valid JSON: ignored")
        return RecordingMetadata(
            format_version=int(version),
            start_time_ns=self._start_ns(),
            writer=info.get("writer", ""),
            model_toml=self._metadata_raw["model"]["toml"],
            rig_toml=self._metadata_raw["rig"]["toml"],
            settings=settings if isinstance(settings, dict) else {},
        )

    # ---------------------------------------------------------------- assembly
    def _assemble(self) -> None:
        start_ns = self.metadata.start_time_ns
        if not self.report.messages.get(TOPIC_JOINTS):
            raise RecordingError(
                f"{self.path}: missing channel {TOPIC_JOINTS}: a recording needs the joint values"
            )
        self.joints = self._joint_samples(start_ns)
        views_present = []
        for view in VIEWS:
            has_markers = bool(self._per_frame.get(markers_topic(view)))
            has_images = bool(self._per_frame.get(image_topic(view)))
            if has_markers or has_images:
                views_present.append(view)
            if not self.report.messages.get(markers_topic(view)):
                self.report.warnings.append(
                    f"missing channel {markers_topic(view)}: frames have no {view} markers"
                    + (" (the images can be segmented)" if has_images else "")
                )
        if not views_present:
            raise RecordingError(
                f"{self.path}: no marker or image channel of either view: nothing to track"
            )
        if not self.report.messages.get(TOPIC_TRUTH):
            self.report.warnings.append(f"missing channel {TOPIC_TRUTH}: no ground truth")
        stamps = set()
        for view in VIEWS:
            stamps.update(self._per_frame.get(markers_topic(view), {}))
            stamps.update(self._per_frame.get(image_topic(view), {}))
        stamps = np.array(sorted(stamps), dtype=np.int64)
        times = (stamps - start_ns) / 1e9
        q, q_dot, ok = self._interpolate(times)
        if np.any(~ok):
            self.report.warnings.append(
                f"{int(np.count_nonzero(~ok))} frame(s) have no joint values within"
                f" {self.max_joint_gap_s:g} s: skipped"
            )
        self._stamps = stamps[ok]
        self._times = times[ok]
        self._q, self._q_dot = q[ok], None if q_dot is None else q_dot[ok]
        self.backgrounds = tuple(self._background(view) for view in VIEWS)
        self.estimates = self._read_estimates(start_ns)
        self._n_points = self._point_count()
        stamps = [int(x) for x in self._stamps]
        self._uv, self._cov, self._quality = {}, {}, {}
        for view in VIEWS:
            self._uv[view], self._cov[view], self._quality[view] = self._marker_arrays(view, stamps)
        self._truth = [self._labels(stamp) for stamp in stamps]
        # The parsed JSON is now in arrays: drop it (millions of small objects that every
        # later garbage collection would walk). Image references stay, for lazy decoding.
        self._joints_raw = []
        for topic in (TOPIC_TRUTH, markers_topic("front"), markers_topic("side")):
            self._per_frame.pop(topic, None)
        self._estimates_raw = {}
        self.report.warnings += _problem_warnings(self._problems.counts)
        self.report.frames = len(self._stamps)
        self.report.joint_samples = int(self.joints.time_s.size)
        if self._max_time is not None:
            self.report.last_time_s = (self._max_time - start_ns) / 1e9

    def _joint_samples(self, start_ns: int) -> JointSamples:
        # Gather the blocks' columns and convert each once (one numpy call per block was a
        # third of the reading time at 1 kHz); a block that does not fit the schema is
        # dropped whole.
        stamps: list = []
        q_r, q_p, q_d, r_r, r_p, r_d = ([] for _ in range(6))
        any_rates = False
        consistent = True
        for _log_time, payload, _topic in self._joints_raw:
            try:
                t = payload["time_ns"]
                q_r += payload["q_r_rad"]
                q_p += payload["q_p_mm"]
                q_d += payload["q_d_mm"]
                if payload.get("q_r_dot_rad_s") is None:
                    r_r += [None] * len(t)
                    r_p += [None] * len(t)
                    r_d += [None] * len(t)
                else:
                    any_rates = True
                    r_r += payload["q_r_dot_rad_s"]
                    r_p += payload["q_p_dot_mm_s"]
                    r_d += payload["q_d_dot_mm_s"]
                stamps += t
            except (KeyError, TypeError):
                consistent = False  # the slow path below names the block
                break
        # Columns of unequal length (a block that does not fit the schema) also go the slow way.
        consistent = consistent and all(
            len(c) == len(stamps) for c in (q_r, q_p, q_d, r_r, r_p, r_d)
        )
        columns = dict(
            zip(JOINT_COLUMNS + RATE_COLUMNS, (q_r, q_p, q_d, r_r, r_p, r_d), strict=True)
        )
        if not stamps and consistent:
            raise RecordingError(f"{self.path}: channel {TOPIC_JOINTS} holds no joint samples")
        try:
            if not consistent:
                raise ValueError
            t = np.array(stamps, dtype=np.int64)
            # numpy turns null (None) into NaN: such samples are dropped below.
            q = np.column_stack([np.array(columns[n], dtype=float) for n in JOINT_COLUMNS])
            r = np.column_stack([np.array(columns[n], dtype=float) for n in RATE_COLUMNS])
            if t.ndim != 1 or q.shape != (t.size, 3) or r.shape != (t.size, 3):
                raise ValueError
        except (TypeError, ValueError, OverflowError):
            t, q, r = self._joint_blocks_one_by_one()
            any_rates = bool(np.isfinite(r).any())
        bad = ~np.all(np.isfinite(q), axis=1)
        if any_rates:
            bad |= ~np.all(np.isfinite(r), axis=1)
        if bad.any():
            self._problems.add("nan_joints", TOPIC_JOINTS, int(np.count_nonzero(bad)))
            t, q, r = t[~bad], q[~bad], r[~bad]
        if t.size > 1 and np.any(np.diff(t) < 0):
            self._problems.add(
                "out_of_order", TOPIC_JOINTS + " (samples)", int(np.sum(np.diff(t) < 0))
            )
        order = np.argsort(t, kind="stable")
        t, q, r = t[order], q[order], r[order]
        keep = np.ones(t.size, dtype=bool)
        keep[1:] = t[1:] != t[:-1]
        if not keep.all():
            self._problems.add(
                "duplicate", TOPIC_JOINTS + " (samples)", int(np.count_nonzero(~keep))
            )
            t, q, r = t[keep], q[keep], r[keep]
        if t.size == 0:
            raise RecordingError(f"{self.path}: channel {TOPIC_JOINTS} holds no valid joint sample")
        self._joint_ns = t
        return JointSamples((t - start_ns) / 1e9, q, r if any_rates else None)

    def _joint_blocks_one_by_one(self) -> tuple[Array, Array, Array]:
        """The joint blocks converted one at a time, skipping those that do not fit the schema
        (the slow path, taken only when the fast one fails)."""
        stamps, qs, rates = [], [], []
        for _log_time, payload, topic in self._joints_raw:
            try:
                t = np.array(payload["time_ns"], dtype=np.int64)
                q = np.column_stack([np.array(payload[n], dtype=float) for n in JOINT_COLUMNS])
                if payload.get(RATE_COLUMNS[0]) is None:
                    r = np.full((t.size, 3), np.nan)
                else:
                    r = np.column_stack([np.array(payload[n], float) for n in RATE_COLUMNS])
                if t.ndim != 1 or q.shape != (t.size, 3) or r.shape != (t.size, 3):
                    raise ValueError
            except (KeyError, TypeError, ValueError, OverflowError):
                self._problems.add("malformed", topic)
                continue
            stamps.append(t)
            qs.append(q)
            rates.append(r)
        if not stamps:
            raise RecordingError(f"{self.path}: channel {TOPIC_JOINTS} holds no valid samples")
        return np.concatenate(stamps), np.concatenate(qs), np.concatenate(rates)

    def _interpolate(self, times: Array) -> tuple[Array, Array | None, Array]:
        """Joint values (and rates) at the frame times: linear between the bracketing samples.

        Rates come from the recorded rates, interpolated likewise, or, when the recording has
        none, from the slope of the values over :data:`RATE_WINDOW_S` around the frame time
        (what the live loop's joint receiver does).
        """
        js = self.joints
        t = js.time_s
        n = t.size
        if times.size == 0:
            return (
                np.zeros((0, 3)),
                None if js.q_dot is None else np.zeros((0, 3)),
                np.zeros(0, bool),
            )
        hi = np.clip(np.searchsorted(t, times, side="left"), 0, n - 1)
        exact = t[hi] == times
        lo = np.where(exact, hi, np.clip(hi - 1, 0, n - 1))
        gap = t[hi] - t[lo]
        inside = (t[lo] <= times) & (times <= t[hi])
        ok = exact | (inside & (gap <= self.max_joint_gap_s))
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(gap > 0, (times - t[lo]) / np.where(gap > 0, gap, 1.0), 0.0)
        w = np.clip(w, 0.0, 1.0)[:, None]
        q = (1 - w) * js.q[lo] + w * js.q[hi]
        q[exact] = js.q[hi[exact]]
        if js.q_dot is not None:
            q_dot = (1 - w) * js.q_dot[lo] + w * js.q_dot[hi]
            q_dot[exact] = js.q_dot[hi[exact]]
        else:
            # As the live loop's joint receiver does: the slope of the values over a window
            # of RATE_WINDOW_S around the frame, moved inside the samples at either end.
            window = RATE_WINDOW_S
            lo_t = np.maximum(t[0], np.minimum(times - window / 2, t[-1] - window))
            hi_t = np.minimum(t[-1], lo_t + window)
            span = hi_t - lo_t
            q_dot = np.full((times.size, 3), np.nan)
            usable = span > 0
            for k in range(3):
                q_lo = np.interp(lo_t, t, js.q[:, k])
                q_hi = np.interp(hi_t, t, js.q[:, k])
                q_dot[usable, k] = (q_hi - q_lo)[usable] / span[usable]
        return q, q_dot, ok

    def _point_count(self) -> int:
        counts = set()
        for view in VIEWS:
            for payload in self._per_frame.get(markers_topic(view), {}).values():
                uv = payload.get("uv") if isinstance(payload, dict) else None
                if isinstance(uv, list):
                    counts.add(len(uv))
        if len(counts) > 1:
            self.report.warnings.append(
                f"marker messages have different numbers of rows {sorted(counts)}: using the most"
                " common"
            )
        if not counts:
            try:
                catheter = self.catheter()
                return 1 + len(catheter.marker_arclengths_mm)
            except RecordingError:
                return 1
        lengths = [
            len(p.get("uv", []))
            for view in VIEWS
            for p in self._per_frame.get(markers_topic(view), {}).values()
            if isinstance(p, dict) and isinstance(p.get("uv"), list)
        ]
        return int(np.bincount(lengths).argmax())

    def _markers(self, view: str, stamp: int) -> tuple[Array, Array, MarkerQuality | None]:
        P = self._n_points
        uv = np.full((P, 2), np.nan)
        cov = np.full((P, 2, 2), np.nan)
        topic = markers_topic(view)
        payload = self._per_frame.get(topic, {}).get(stamp)
        if payload is None:
            return uv, cov, None
        try:
            rows, covs = payload["uv"], payload["cov"]
            if len(rows) != P or len(covs) != P:
                raise ValueError
            present = [k for k in range(P) if rows[k] is not None and covs[k] is not None]
            if present:
                # One conversion for all rows found (a null row is a point not found).
                points = np.array([rows[k] for k in present], dtype=float)
                matrices = np.array([covs[k] for k in present], dtype=float)
                if points.shape != (len(present), 2) or matrices.shape != (len(present), 2, 2):
                    raise ValueError
                finite = np.isfinite(points).all(axis=1) & np.isfinite(matrices).all(axis=(1, 2))
                if not finite.all():
                    self._problems.add("nan", topic)
                index = np.array(present)[finite]
                uv[index], cov[index] = points[finite], matrices[finite]
            quality = self._quality_of(payload, topic)
        except (KeyError, TypeError, ValueError):
            self._problems.add("malformed", topic)
            return np.full((P, 2), np.nan), np.full((P, 2, 2), np.nan), None
        return uv, cov, quality

    def _labels(self, stamp: int) -> tuple[float | None, FrameLabels]:
        payload = self._per_frame.get(TOPIC_TRUTH, {}).get(stamp)
        if payload is None:
            return None, FrameLabels()

        def number(key):
            value = payload.get(key)
            if value is None:
                return None
            value = float(value)
            return value if math.isfinite(value) else None

        def index(key):
            value = payload.get(key)
            return None if value is None else int(value)

        try:
            delta_L = payload.get("delta_L_rad")
            if delta_L is not None and not math.isfinite(float(delta_L)):
                self._problems.add("nan_truth", TOPIC_TRUTH)
            labels = FrameLabels(
                plane=index("plane"),
                configuration=index("configuration"),
                deflection_mm=number("deflection_mm"),
                noise_level=number("noise_level"),
                delta_1_true_rad=number("delta_1_rad"),
            )
            return number("delta_L_rad"), labels
        except (TypeError, ValueError, AttributeError):
            self._problems.add("malformed", TOPIC_TRUTH)
            return None, FrameLabels()

    def _marker_arrays(self, view: str, stamps: list[int]) -> tuple[Array, Array, list]:
        """Every frame's points and covariances of one view, (F, P, 2) and (F, P, 2, 2).

        Frames whose rows are all present (the common case) are converted in one go; the
        others row by row (:meth:`_markers`).
        """
        P, F = self._n_points, len(stamps)
        uv = np.full((F, P, 2), np.nan)
        cov = np.full((F, P, 2, 2), np.nan)
        quality: list[MarkerQuality | None] = [None] * F
        store = self._per_frame.get(markers_topic(view), {})
        full, full_uv, full_cov = [], [], []
        for i, stamp in enumerate(stamps):
            payload = store.get(stamp)
            if payload is None:
                continue
            rows, covs = payload.get("uv"), payload.get("cov")
            if (
                isinstance(rows, list)
                and isinstance(covs, list)
                and len(rows) == P
                and len(covs) == P
                and None not in rows
                and None not in covs
            ):
                full.append(i)
                full_uv.append(rows)
                full_cov.append(covs)
                quality[i] = self._quality_of(payload, markers_topic(view))
            else:
                uv[i], cov[i], quality[i] = self._markers(view, stamp)
        if full:
            try:
                points = np.array(full_uv, dtype=float)
                matrices = np.array(full_cov, dtype=float)
                if points.shape != (len(full), P, 2) or matrices.shape != (len(full), P, 2, 2):
                    raise ValueError
            except (TypeError, ValueError):
                for i in full:
                    uv[i], cov[i], quality[i] = self._markers(view, stamps[i])
            else:
                finite = np.isfinite(points).all(axis=2) & np.isfinite(matrices).all(axis=(2, 3))
                bad_frames = int(np.count_nonzero(~finite.all(axis=1)))
                if bad_frames:
                    self._problems.add("nan", markers_topic(view), bad_frames)
                points[~finite] = np.nan
                matrices[~finite] = np.nan
                uv[full], cov[full] = points, matrices
        return uv, cov, quality

    def _quality_of(self, payload: dict, topic: str) -> MarkerQuality | None:
        q = payload.get("quality")
        if not isinstance(q, dict):
            return None
        try:
            sigma = q.get("noise_sigma_gray")
            return MarkerQuality(
                int(q.get("flags", 0)),
                tuple(str(x) for x in q.get("flag_names", [])),
                None if sigma is None else float(sigma),
            )
        except (TypeError, ValueError):
            self._problems.add("malformed", topic)
            return None

    # ---------------------------------------------------------------- images
    def _image_data(self, ref: _ImageRef) -> bytes:
        if ref.data is not None:
            return ref.data
        if self._chunk_cache is None or self._chunk_cache[0] != ref.chunk_offset:
            f = self._file
            f.seek(ref.chunk_offset + 9)
            start_ns, end_ns, uncompressed_size, crc, n = struct.unpack("<QQQII", f.read(32))
            compression = f.read(n).decode()
            (data_length,) = struct.unpack("<Q", f.read(8))
            records = _decompress(compression, f.read(data_length), uncompressed_size)
            self._chunk_cache = (ref.chunk_offset, records)
        return self._chunk_cache[1][ref.position : ref.position + ref.length]

    def _image(self, topic: str, stamp: int) -> Array | None:
        ref = self._per_frame.get(topic, {}).get(stamp)
        if ref is None:
            return None
        try:
            return decode_image(self._image_data(ref))
        except (ValueError, OSError):
            self._problems.add("bad_image", topic)
            return None

    def _background(self, view: str) -> Array | None:
        refs = self._per_frame.get(background_topic(view), {})
        if not refs:
            return None
        return self._image(background_topic(view), min(refs))

    @property
    def has_images(self) -> bool:
        return all(bool(self._per_frame.get(image_topic(v))) for v in VIEWS)

    # ---------------------------------------------------------------- public
    def __len__(self) -> int:
        return len(self._stamps)

    def frames(self, images: bool | Callable[[int], bool] = True) -> Iterator[RecordedFrame]:
        """The frames in time order.

        Parameters
        ----------
        images : bool or callable
            Decode the images (one frame at a time); a callable of the frame index decodes
            them only for the frames it accepts.
        """
        has_images = self.has_images
        for i in range(len(self._stamps)):
            stamp = int(self._stamps[i])
            delta_L, labels = self._truth[i]
            pair = None
            if has_images and (images(i) if callable(images) else images):
                front = self._image(image_topic("front"), stamp)
                side = self._image(image_topic("side"), stamp)
                pair = None if front is None or side is None else (front, side)
            frame = Frame(
                time_s=float(self._times[i]),
                q=self._q[i].copy(),
                q_dot=None
                if self._q_dot is None or not np.all(np.isfinite(self._q_dot[i]))
                else self._q_dot[i].copy(),
                uv_front=self._uv["front"][i].copy(),
                uv_side=self._uv["side"][i].copy(),
                cov_front=self._cov["front"][i].copy(),
                cov_side=self._cov["side"][i].copy(),
                images=pair,
                delta_L_true_rad=delta_L,
            )
            quality = (self._quality["front"][i], self._quality["side"][i])
            yield RecordedFrame(frame, labels, quality)

    def frame_times_s(self) -> Array:
        return self._times.copy()

    def catheter(self) -> Catheter:
        """The catheter model of the ``model`` metadata record."""
        try:
            return catheter_from_dict(tomllib.loads(self.metadata.model_toml), "recorded model")
        except (tomllib.TOMLDecodeError, ModelFileError) as exc:
            raise RecordingError(f"{self.path}: {exc}") from None

    def rig(self) -> tuple[BiplaneRig, Array, Array]:
        """``(rig, R_w_b, o_b_w_mm)`` of the ``rig`` metadata record."""
        return rig_from_toml(self.metadata.rig_toml, f"{self.path} rig")

    def _read_estimates(self, start_ns: int) -> dict[str, list[RecordedEstimate]]:
        out = {}
        for name, store in self._estimates_raw.items():
            rows = []
            for stamp in sorted(store):
                p = store[stamp]
                try:
                    flags = Flag(int(p.get("flags", 0)))
                    nis = p.get("nis")
                    rows.append(
                        RecordedEstimate(
                            (stamp - start_ns) / 1e9,
                            Estimate(
                                time_s=(stamp - start_ns) / 1e9,
                                delta_L_rad=_nan_if_none(p.get("delta_L_rad")),
                                std_rad=_nan_if_none(p.get("std_rad")),
                                q_r_rad=float(p["q_r_rad"]),
                                flags=flags,
                                informative_radius_mm=float(p.get("informative_radius_mm", 0.0)),
                                nis=None if nis is None else float(nis),
                                nis_dof=int(p.get("nis_dof", 0)),
                            ),
                        )
                    )
                except (KeyError, TypeError, ValueError):
                    self._problems.add("malformed", estimate_topic(name))
            out[name] = rows
        return out

    def close(self) -> None:
        if self._file is not None:
            self._file.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_RECORD_HEAD = struct.Struct("<BQ")  # opcode, record length
_MESSAGE_HEAD = struct.Struct("<HIQ")  # channel id, sequence, log time (then publish time)


def _nan_if_none(value) -> float:
    return float("nan") if value is None else float(value)


def _string(buf, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    pos += 4
    return bytes(buf[pos : pos + n]).decode("utf-8"), pos + n


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        import zstandard

        try:
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        except zstandard.ZstdError as exc:
            raise ValueError(f"zstd: {exc}") from None
    if compression == "lz4":
        import lz4.frame

        try:
            return lz4.frame.decompress(data)
        except RuntimeError as exc:
            raise ValueError(f"lz4: {exc}") from None
    raise ValueError(f"unsupported chunk compression {compression!r}")


def open_recording(path: str | Path, max_joint_gap_s: float = MAX_JOINT_GAP_S) -> Recording:
    """Read and validate a recording (images are decoded later, frame by frame).

    Raises
    ------
    RecordingError
        Not an MCAP file, not a cathtrack recording, an unknown format version, no joint
        values, or no marker or image channel. Problems that leave something readable are
        warnings in ``recording.report`` instead.
    """
    return Recording(path, max_joint_gap_s)


__all__ = [
    "FORMAT_VERSION",
    "FrameLabels",
    "JointSamples",
    "MarkerQuality",
    "ReadReport",
    "RecordedEstimate",
    "RecordedFrame",
    "Recording",
    "RecordingError",
    "RecordingMetadata",
    "RecordingWriter",
    "SCHEMAS",
    "decode_image",
    "encode_image",
    "encode_json",
    "open_recording",
    "rig_from_toml",
    "rig_toml",
]
