"""Camera frames in a recording: ``foxglove.RawImage`` messages (protobuf, ``mono8``).

Encoding uses the ``foxglove-sdk`` message classes. The SDK has no decoder and no protobuf
runtime is installed, so :func:`decode_image` reads the few top-level fields it needs with
the wire-format reader of :mod:`tracker.io.recording.protobuf` (field numbers in
docs/recording.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from foxglove import messages
from foxglove.messages import RawImage

from tracker.io.recording import protobuf

Array = np.ndarray


def image_schema():
    """The ``foxglove.RawImage`` schema (name, encoding, FileDescriptorSet) of the channels."""
    return RawImage.get_schema()


def encode_image(image: Array, frame_id: str, time_ns: int) -> bytes:
    """A grayscale uint8 image as a ``foxglove.RawImage`` protobuf message (``mono8``)."""
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


def _protobuf_fields(data: bytes) -> dict[int, Any]:
    """Top-level fields of a protobuf message: number -> int (varint, fixed32, fixed64) or
    memoryview (length-delimited); the last of a repeated number."""
    out: dict[int, Any] = {}
    for number, wire, value in protobuf.fields(data):
        if wire in (protobuf.WIRE_I64, protobuf.WIRE_I32):
            value = int.from_bytes(value, "little")
        out[number] = value
    return out


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
