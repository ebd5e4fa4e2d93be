"""The protobuf wire format, as far as recordings need it (protobuf.dev, "Encoding").

No protobuf runtime is a dependency of cathtrack: ``foxglove-sdk`` encodes the camera frames,
and the two protobuf messages the reader decodes -- ``foxglove.RawImage`` and
``cathtrack.JointSamples`` -- need only their top-level fields, which :func:`fields` reads.
The writer encodes ``cathtrack.JointSamples`` and its ``FileDescriptorSet`` with
:func:`varint_field` and :func:`len_field`.

A message is a sequence of fields, each a key (a varint: ``number << 3 | wire type``) and a
value: a varint (wire type 0), 8 bytes (1, little-endian), a varint length and that many
bytes (2: strings, bytes, sub-messages and packed repeated numbers), or 4 bytes (5).
"""

from __future__ import annotations

from collections.abc import Iterator

WIRE_VARINT = 0
WIRE_I64 = 1
WIRE_LEN = 2
WIRE_I32 = 5

_MAX_VARINT_BYTES = 10
"""A varint holds at most 64 bits: 10 bytes of 7 bits (longer ones are damage)."""


def read_varint(buf: memoryview | bytes, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` of ``buf`` and the position after it.

    Raises
    ------
    ValueError
        The buffer ends inside the varint, or it is longer than 10 bytes.
    """
    result = shift = 0
    end = min(len(buf), pos + _MAX_VARINT_BYTES)
    while pos < end:
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7
    if end < len(buf):
        raise ValueError("varint longer than 10 bytes")
    raise ValueError("truncated varint")


def fields(data: bytes | memoryview) -> Iterator[tuple[int, int, int | memoryview]]:
    """The top-level fields of a message in order: ``(number, wire type, value)``.

    The value is an int for a varint, and the raw bytes (a memoryview of ``data``) for the
    other wire types: 8 bytes (``WIRE_I64``), the field's content (``WIRE_LEN``), 4 bytes
    (``WIRE_I32``).

    Raises
    ------
    ValueError
        A field that runs past the end of the data, or a wire type that protobuf 3 does not
        write (3 and 4, the deprecated groups; 6, 7).
    """
    buf = memoryview(data)
    size = len(buf)
    pos = 0
    while pos < size:
        key, pos = read_varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == WIRE_VARINT:
            value, pos = read_varint(buf, pos)
            yield number, wire, value
            continue
        if wire == WIRE_LEN:
            length, pos = read_varint(buf, pos)
        elif wire == WIRE_I64:
            length = 8
        elif wire == WIRE_I32:
            length = 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        if pos + length > size:
            raise ValueError(f"field {number} runs past the end of the message")
        yield number, wire, buf[pos : pos + length]
        pos += length


# ---------------------------------------------------------------------------------- writing
def varint_bytes(value: int) -> bytes:
    """A non-negative integer as a varint."""
    if value < 0:
        raise ValueError(f"varints here are non-negative, got {value}")
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def key_bytes(number: int, wire: int) -> bytes:
    """The key of field ``number`` with wire type ``wire``."""
    return varint_bytes(number << 3 | wire)


def varint_field(number: int, value: int) -> bytes:
    """A varint field (int32, int64, uint32, uint64, bool, enum)."""
    return key_bytes(number, WIRE_VARINT) + varint_bytes(value)


def len_field(number: int, content: bytes | str) -> bytes:
    """A length-delimited field: a string (UTF-8), bytes, a message or a packed column."""
    if isinstance(content, str):
        content = content.encode()
    return key_bytes(number, WIRE_LEN) + varint_bytes(len(content)) + content
