"""Writing a recording (docs/recording.md): :class:`RecordingWriter`.

Crash safety: the writer closes a chunk when it holds one second of log time or 4 MiB,
whichever comes first, and writes it out, so a crash loses at most the last second.

It writes format version 2 (the joint blocks in protobuf, :mod:`.joint_samples`); version 1
(the joint blocks in JSON) on request, for tools and tests that need an older file.
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.writer import CompressionType, Writer

from models.rig_file import view_names
from tracker import __version__
from tracker.io.recording import joint_samples
from tracker.io.recording.images import encode_image, image_schema
from tracker.io.recording.schema import (
    FORMAT,
    FORMAT_VERSION,
    JOINT_COLUMNS,
    RATE_COLUMNS,
    READ_VERSIONS,
    SCHEMAS,
    SCHEMAS_V1,
    TOPIC_JOINTS,
    TOPIC_TRUTH,
    FrameLabels,
    MarkerQuality,
    background_topic,
    encode_json,
    estimate_topic,
    finite_or_none,
    image_topic,
    json_rows,
    markers_topic,
    schema_for_topic,
)
from tracker.types import Estimate, Flag, Frame

Array = np.ndarray

CHUNK_SECONDS = 1.0
"""A chunk is closed and written once it spans this much log time, s."""
CHUNK_BYTES = 4 * 1024 * 1024
"""...or once it holds this many (uncompressed) bytes."""
JOINT_BLOCK_SAMPLES = 50
"""Joint samples per /joints message at most (50 ms at 1 kHz)."""


class RecordingWriter:
    """Writes a recording; use as a context manager (the file is complete after ``close``).

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file to create.
    model_toml, rig_toml : str
        Text of the model file (docs/model-file.md) and of the rig
        (:func:`models.rig_file.rig_toml`).
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
    format_version : int, optional
        The format version to write: 2 (default, :data:`FORMAT_VERSION`), or 1 (joint
        blocks in JSON) for a reader that knows only version 1.
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
        format_version: int | None = None,
    ) -> None:
        format_version = FORMAT_VERSION if format_version is None else format_version
        if format_version not in READ_VERSIONS:
            raise ValueError(f"format_version must be one of {READ_VERSIONS}, got {format_version}")
        if point_unit not in ("px", "mm"):
            raise ValueError(f"point_unit must be 'px' or 'mm', got {point_unit!r}")
        if not chunk_seconds > 0:
            raise ValueError(f"chunk_seconds must be positive, got {chunk_seconds}")
        self.path = Path(path)
        self.format_version = int(format_version)
        self.point_unit = point_unit
        self.start_time_ns = int(start_time_ns)
        self._chunk_ns = int(chunk_seconds * 1e9)
        self._fsync = fsync
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._mcap = Writer(
            self._file, chunk_size=int(chunk_bytes), compression=CompressionType.ZSTD
        )
        self._mcap.start(profile="", library=f"cathtrack {__version__}")
        self._mcap.add_metadata(
            "cathtrack",
            {
                "format": FORMAT,
                "format_version": str(self.format_version),
                "start_time_ns": str(self.start_time_ns),
                "writer": f"cathtrack {__version__}",
            },
        )
        self._mcap.add_metadata("model", {"toml": model_toml})
        self._mcap.add_metadata("rig", {"toml": rig_toml})
        self._mcap.add_metadata("settings", {"json": json.dumps(dict(settings or {}))})
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._chunk_start_ns: int | None = None
        self._flush_after_next = False
        # Pending joint samples, in pieces as given: (time stamps ns, values, rates or None).
        self._joints: list[tuple[Array, Array, Array | None]] = []
        self._joint_count = 0
        self._closed = False
        try:
            self.views = view_names(tomllib.loads(rig_toml), "rig")
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"rig_toml is not TOML: {exc}") from None
        for topic in (TOPIC_JOINTS, *(markers_topic(v) for v in self.views), TOPIC_TRUTH):
            self._channel(topic)

    # ---------------------------------------------------------------- channels
    def _channel(self, topic: str) -> int:
        channel = self._channels.get(topic)
        if channel is not None:
            return channel
        name = schema_for_topic(topic)
        if topic == TOPIC_JOINTS and self.format_version >= 2:
            encoding = schema_encoding = "protobuf"
            schema_data = joint_samples.FILE_DESCRIPTOR_SET
        elif name is not None:
            encoding, schema_encoding = "json", "jsonschema"
            schemas = SCHEMAS if self.format_version >= 2 else SCHEMAS_V1
            schema_data = json.dumps(schemas[name], indent=1).encode()
        else:
            schema = image_schema()
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

        Parameters
        ----------
        time_s : float or array, shape (n,)
            Session times of the samples, s.
        q : array, shape (3,) or (n, 3)
            Joint values q_r (rad), q_p (mm), q_d (mm); NaN: not available.
        q_dot : array, shape (3,) or (n, 3), optional
            Their rates (rad/s, mm/s, mm/s), if the source measures them.

        Samples are buffered into blocks of up to :data:`JOINT_BLOCK_SAMPLES`; a frame, an
        estimate or :meth:`close` writes the pending block first, and so does a change
        between samples with and without rates (a block has all three rates or none).
        """
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        # Copies: the samples wait in the buffer while the caller may reuse its arrays.
        q = np.array(q, dtype=float).reshape(t.size, 3)
        rates = None if q_dot is None else np.array(q_dot, dtype=float).reshape(t.size, 3)
        if self._joints and (rates is None) != (self._joints[-1][2] is None):
            self._write_joint_block()
        stamps = np.array([self._time_ns(x) for x in t.tolist()], dtype=np.int64)
        start = 0
        while start < t.size:
            end = min(t.size, start + JOINT_BLOCK_SAMPLES - self._joint_count)
            piece = slice(start, end)
            self._joints.append((stamps[piece], q[piece], None if rates is None else rates[piece]))
            self._joint_count += end - start
            start = end
            if self._joint_count >= JOINT_BLOCK_SAMPLES:
                self._write_joint_block()

    def _write_joint_block(self) -> None:
        if not self._joints:
            return
        pieces, self._joints, self._joint_count = self._joints, [], 0
        stamps = np.concatenate([t for t, _, _ in pieces])
        q = np.concatenate([values for _, values, _ in pieces])
        rates = None if pieces[0][2] is None else np.concatenate([r for _, _, r in pieces])
        if self.format_version >= 2:
            data = joint_samples.encode_joint_block(stamps, q, rates)
        else:
            data = _json_joint_block(stamps, q, rates)
        self.write_raw(TOPIC_JOINTS, int(stamps[-1]), data)

    def write_background(self, view: str, image: Array, time_s: float = 0.0) -> None:
        """The empty-scene prior image of one camera (needed to segment its frames)."""
        if view not in self.views:
            raise ValueError(f"view must be one of the rig's {self.views}, got {view!r}")
        stamp = self._time_ns(time_s)
        self.write_raw(background_topic(view), stamp, encode_image(image, view, stamp))

    def write_frame(
        self,
        frame: Frame,
        labels: FrameLabels | None = None,
        quality: Sequence[MarkerQuality | None] | None = None,
        images: bool = True,
    ) -> None:
        """One frame: every view's markers, their images (if the frame has them and
        ``images``), and the truth and labels. The frame's joint values are not written here:
        the joint values are their own stream (:meth:`write_joints`)."""
        if frame.n_views != len(self.views):
            raise ValueError(
                f"the frame has {frame.n_views} views, the recording's rig {len(self.views)}"
                f" ({', '.join(self.views)})"
            )
        quality = (None,) * len(self.views) if quality is None else tuple(quality)
        self._write_joint_block()
        stamp = self._time_ns(frame.time_s)
        views = zip(frame.uv, frame.cov, strict=True)
        for k, (view, (uv, cov)) in enumerate(zip(self.views, views, strict=True)):
            uv = np.asarray(uv, dtype=float)
            cov = np.asarray(cov, dtype=float)
            missing = ~np.all(np.isfinite(uv), axis=-1)
            cov_rows = json_rows(cov)
            message = {
                "view": view,
                "unit": self.point_unit,
                "uv": json_rows(uv),
                "cov": [
                    None if gone else row
                    for row, gone in zip(cov_rows, missing.tolist(), strict=True)
                ],
            }
            if quality[k] is not None:
                message["quality"] = quality[k].to_json()
            self.write_raw(markers_topic(view), stamp, encode_json(message))
        if images and frame.images is not None:
            for view, image in zip(self.views, frame.images, strict=True):
                self.write_raw(image_topic(view), stamp, encode_image(image, view, stamp))
        labels = labels or FrameLabels()
        truth = {
            "delta_L_rad": finite_or_none(frame.delta_L_true_rad),
            "delta_1_rad": finite_or_none(labels.delta_1_true_rad),
            "plane": labels.plane,
            "configuration": labels.configuration,
            "deflection_mm": finite_or_none(labels.deflection_mm),
            "noise_level": finite_or_none(labels.noise_level),
        }
        self.write_raw(TOPIC_TRUTH, stamp, encode_json(truth))

    def write_estimate(self, name: str, estimate: Estimate) -> None:
        """One step of estimator ``name`` on ``/estimates/<name>`` at the estimate's time."""
        self._write_joint_block()
        stamp = self._time_ns(estimate.time_s)
        flags = estimate.flags
        message = {
            "delta_L_rad": finite_or_none(estimate.delta_L_rad),
            "std_rad": finite_or_none(estimate.std_rad),
            "delta_1_rad": finite_or_none(estimate.delta_1_rad),
            "q_r_rad": float(estimate.q_r_rad),
            "flags": int(flags.value),
            "flag_names": [f.name for f in Flag if f.value and f in flags],
            "nis": None if estimate.nis is None else finite_or_none(estimate.nis),
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


def _json_joint_block(time_ns: Array, q: Array, q_dot: Array | None) -> bytes:
    """A ``/joints`` message of format version 1: JSON columns, null for a sample with a value
    that is not finite (strict JSON has no NaN; a whole row, as in the values' rows)."""
    message: dict[str, list] = {"time_ns": time_ns.tolist()}
    for names, values in ((JOINT_COLUMNS, q), (RATE_COLUMNS, q_dot)):
        rows = [] if values is None else json_rows(values)
        if names is RATE_COLUMNS and all(row is None for row in rows):
            continue  # no rate known in the block: no rate columns (as version 1 wrote)
        rows = [row if row is not None else [None] * 3 for row in rows]
        for k, name in enumerate(names):
            message[name] = [row[k] for row in rows]
    return encode_json(message)
