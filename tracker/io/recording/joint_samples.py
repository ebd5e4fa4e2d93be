"""The joint stream of a recording (format version 2): ``cathtrack.JointSamples`` in protobuf.

One ``/joints`` message is a block of samples, one packed repeated field per quantity
(:data:`PROTO`). The schema record holds the message's ``FileDescriptorSet`` (schema encoding
``protobuf``), as for the Foxglove image schemas, so that any protobuf library decodes the
channel (docs/recording.md). :func:`encode_joint_block` writes a block; :func:`joint_columns`
reads every block of a recording back into columns.

Why protobuf with packed fixed-width fields: a packed ``double`` or ``sfixed64`` field is the
column's values as little-endian 8-byte numbers, so the reader takes each column straight
from the message bytes (``numpy.frombuffer``) instead of parsing text. At 1 kHz (50 samples
per frame) the JSON blocks of format version 1 cost about 35 us per frame to parse and
convert, these about 5 us (most of it the page faults of the output arrays); they are 2.8 kB
per frame instead of 6.7 kB before compression, and 15 % smaller after it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from tracker.io.recording import protobuf

Array = np.ndarray

PROTO = """\
syntax = "proto3";
package cathtrack;

// A block of joint samples in time order, one packed column per quantity; all columns
// present have the same length. The rates are empty when the source does not measure them
// (all three, or none). NaN: a value that was not available. json_name keeps the field
// names in JSON exports (protobuf's default would be lowerCamelCase).
message JointSamples {
  // sample times on the clock of the MCAP log_time, ns
  repeated sfixed64 time_ns = 1 [json_name = "time_ns"];
  repeated double q_r_rad = 2 [json_name = "q_r_rad"];              // base rotation, rad
  repeated double q_p_mm = 3 [json_name = "q_p_mm"];                // proximal wire, mm
  repeated double q_d_mm = 4 [json_name = "q_d_mm"];                // distal wire, mm
  repeated double q_r_dot_rad_s = 5 [json_name = "q_r_dot_rad_s"];  // rad/s
  repeated double q_p_dot_mm_s = 6 [json_name = "q_p_dot_mm_s"];    // mm/s
  repeated double q_d_dot_mm_s = 7 [json_name = "q_d_dot_mm_s"];    // mm/s
}
"""
"""The message definition (the text of the ``.proto`` file the schema describes)."""

COLUMNS = (
    "time_ns",
    "q_r_rad",
    "q_p_mm",
    "q_d_mm",
    "q_r_dot_rad_s",
    "q_p_dot_mm_s",
    "q_d_dot_mm_s",
)
"""Field names in the order of their field numbers (1 to 7)."""

_TYPE_DOUBLE, _TYPE_SFIXED64 = 1, 16  # google.protobuf.FieldDescriptorProto.Type
_LABEL_REPEATED = 3  # google.protobuf.FieldDescriptorProto.Label
_COLUMN_TAGS = [protobuf.key_bytes(number, protobuf.WIRE_LEN) for number in range(1, 8)]
_BATCH_BYTES = 2**18
"""Blocks are converted together in batches of about this many bytes."""


def _file_descriptor_set() -> bytes:
    """The serialized ``google.protobuf.FileDescriptorSet`` of :data:`PROTO` (what ``protoc
    --descriptor_set_out`` writes, without source comments)."""
    field, message = protobuf.len_field, protobuf.varint_field
    columns = b"".join(
        field(
            2,  # DescriptorProto.field
            field(1, name)  # name
            + message(3, number)  # number
            + message(4, _LABEL_REPEATED)  # label
            + message(5, _TYPE_SFIXED64 if number == 1 else _TYPE_DOUBLE)  # type
            + field(10, name),  # json_name
        )
        for number, name in enumerate(COLUMNS, start=1)
    )
    joint_samples = field(1, "JointSamples") + columns  # DescriptorProto
    proto_file = (
        field(1, "cathtrack/JointSamples.proto")  # name
        + field(2, "cathtrack")  # package
        + field(4, joint_samples)  # message_type
        + field(12, "proto3")  # syntax
    )
    return field(1, proto_file)  # FileDescriptorSet.file


FILE_DESCRIPTOR_SET = _file_descriptor_set()
"""The schema record's data: the ``FileDescriptorSet`` of ``cathtrack.JointSamples``."""


# ---------------------------------------------------------------------------------- writing
def encode_joint_block(time_ns: Array, q: Array, q_dot: Array | None = None) -> bytes:
    """One ``cathtrack.JointSamples`` message.

    Parameters
    ----------
    time_ns : int array, shape (n,)
        Sample times, ns, on the clock of the MCAP log_time.
    q : array, shape (n, 3)
        Joint values q_r (rad), q_p (mm), q_d (mm); NaN where not available.
    q_dot : array, shape (n, 3), optional
        Their rates (rad/s, mm/s, mm/s); None: not measured (the fields stay empty).

    Returns
    -------
    bytes
        The message: each column present as one packed field, in field-number order (empty
        columns omitted, as protobuf 3 encoders do).
    """
    t = np.ascontiguousarray(time_ns, dtype="<i8").reshape(-1)
    n = t.size
    columns = [t.tobytes()]
    for values in (q,) if q_dot is None else (q, q_dot):
        values = np.asarray(values, dtype="<f8").reshape(n, 3)
        columns += [np.ascontiguousarray(values[:, k]).tobytes() for k in range(3)]
    if n == 0:
        return b""
    length = protobuf.varint_bytes(8 * n)
    tags = _COLUMN_TAGS[: len(columns)]
    return b"".join(tag + length + column for tag, column in zip(tags, columns, strict=True))


# ---------------------------------------------------------------------------------- reading
def joint_columns(messages: Sequence[bytes]) -> tuple[Array, Array, Array, bool, int]:
    """Every block's samples joined in message order.

    Parameters
    ----------
    messages : sequence of bytes
        The ``/joints`` messages in file order.

    Returns
    -------
    time_ns : int array, shape (n,)
        Sample times, ns, as recorded (neither sorted nor checked).
    q : array, shape (n, 3)
        Joint values, rad and mm.
    q_dot : array, shape (n, 3)
        Rates, rad/s and mm/s; NaN in the blocks that hold none.
    any_rates : bool
        Whether any block holds rates.
    malformed : int
        How many messages were dropped: not protobuf, a column that is not whole 8-byte
        numbers, columns of unequal lengths, or only some rate columns.

    Notes
    -----
    The blocks cathtrack writes have one layout per number of samples (:func:`_layout`):
    the messages of each length are checked and converted together as one byte array, so
    the cost per block is a few array operations for the whole stream. Any other valid
    encoding (fields in another order or split, unpacked numbers, unknown fields: what other
    protobuf writers may produce) is read field by field (:func:`_block`).
    """
    sizes = np.fromiter(map(len, messages), dtype=np.int64, count=len(messages))
    samples = np.zeros(len(messages), dtype=np.int64)
    # Two passes: the first finds which blocks have the layout of their size (their sample
    # counts then give every sample its place), the second converts them. Both go in
    # batches of about 256 kB, so that their temporary copies reuse the memory the batch
    # before freed: one copy of the whole stream would be fresh pages, which cost more than
    # the copying itself.
    batches: list[tuple[Array, tuple[int, int, int]]] = []  # blocks that fit, their layout
    other: list[int] = []
    for size in np.unique(sizes).tolist():
        if size == 0:
            continue  # the empty message: a block of no samples
        index = np.flatnonzero(sizes == size)
        layout = _layout(size)
        if layout is None:
            other += index.tolist()
            continue
        step = max(1, _BATCH_BYTES // size)
        for start in range(0, index.size, step):
            part = index[start : start + step]
            ok = _fits(_rows([messages[i] for i in part.tolist()], *layout), *layout)
            other += part[~ok].tolist()
            batches.append((part[ok], layout))
            samples[part[ok]] = layout[0]
    malformed = 0
    irregular: list[tuple[int, Array, Array, Array | None]] = []
    for i in sorted(other):
        try:
            t, q, rates = _block(messages[i])
        except ValueError:
            malformed += 1
            continue
        irregular.append((i, t, q, rates))
        samples[i] = t.size
    starts = np.cumsum(samples) - samples  # each block's first sample, in message order
    total = int(samples.sum())
    time_ns = np.empty(total, dtype=np.int64)
    q_all = np.empty((total, 3))
    rates_all = np.full((total, 3), np.nan)
    any_rates = False
    for index, (n, k, h) in batches:
        # Each column scattered to its samples' places: one numpy call per column and batch.
        rows = _rows([messages[i] for i in index.tolist()], n, k, h)
        # One aligned copy of the numbers (each column follows its key and length, so that
        # in the message they are not 8-byte aligned): scattering them is three times faster.
        columns = np.ascontiguousarray(rows[:, :, 1 + h :]).view("<f8")  # (m, k, n)
        where = starts[index][:, None] + np.arange(n)
        time_ns[where] = columns[:, 0].view(np.int64)
        for j in range(1, k):
            (q_all if j < 4 else rates_all)[where, (j - 1) % 3] = columns[:, j]
        any_rates |= k == 7
    for i, t, q, rates in irregular:
        where = slice(starts[i], starts[i] + t.size)
        time_ns[where], q_all[where] = t, q
        if rates is not None:
            rates_all[where] = rates
            any_rates = True
    return time_ns, q_all, rates_all, any_rates, malformed


def _layout(size: int) -> tuple[int, int, int] | None:
    """The samples ``n``, columns ``k`` (4 without rates, 7 with) and bytes of the length
    varint ``h`` of the message that :func:`encode_joint_block` writes in ``size`` bytes
    (None: no such message).

    That message is ``k`` fields of ``1 + h + 8 n`` bytes each (key, length, values).
    """
    for k in (4, 7):
        for h in (1, 2, 3):  # 8 n < 2^21: blocks of up to 262,143 samples
            values = size - k * (1 + h)
            if values > 0 and values % (8 * k) == 0:
                n = values // (8 * k)
                if len(protobuf.varint_bytes(8 * n)) == h:
                    return n, k, h
    return None


def _rows(messages: list[bytes], n: int, k: int, h: int) -> Array:
    """The messages of one :func:`_layout` as one byte array, shape (m, k, 1 + h + 8 n):
    per message and field, the key, the length and the values."""
    joined = np.frombuffer(b"".join(messages), dtype=np.uint8)
    return joined.reshape(len(messages), k, 1 + h + 8 * n)


def _fits(rows: Array, n: int, k: int, h: int) -> Array:
    """Which messages (bool, shape (m,)) of :func:`_rows` have their layout's keys and
    lengths (the others are read field by field)."""
    length = protobuf.varint_bytes(8 * n)
    heads = np.frombuffer(b"".join(tag + length for tag in _COLUMN_TAGS[:k]), np.uint8)
    return (rows[:, :, : 1 + h] == heads.reshape(k, 1 + h)).all(axis=(1, 2))


def _block(message: bytes) -> tuple[Array, Array, Array | None]:
    """One message read field by field, as a protobuf library reads it: a repeated field's
    values packed or one by one, in any number of pieces; fields of other numbers skipped.

    Returns
    -------
    time_ns : int array, shape (n,)
    q : array, shape (n, 3)
    rates : array, shape (n, 3), or None without rate columns

    Raises
    ------
    ValueError
        Not a protobuf message; a column whose bytes are not whole 8-byte numbers or whose
        wire type is not that of its type; columns of different lengths; some rate columns
        but not all.
    """
    pieces: list[list[bytes]] = [[] for _ in COLUMNS]
    for number, wire, value in protobuf.fields(message):
        if not 1 <= number <= len(COLUMNS):
            continue  # a field of a later version: skipped, as protobuf readers do
        if wire == protobuf.WIRE_LEN and len(value) % 8 == 0:
            pieces[number - 1].append(bytes(value))
        elif wire == protobuf.WIRE_I64:  # an unpacked value
            pieces[number - 1].append(bytes(value))
        else:
            raise ValueError(f"field {number} ({COLUMNS[number - 1]}) is not 8-byte numbers")
    columns = [b"".join(p) for p in pieces]
    time_ns = np.frombuffer(columns[0], dtype="<i8").astype(np.int64)
    n = time_ns.size
    numbers = [np.frombuffer(c, dtype="<f8").astype(float) for c in columns[1:]]
    if any(column.size != n for column in numbers[:3]):
        raise ValueError("joint columns of different lengths")
    rates = numbers[3:]
    if all(column.size == 0 for column in rates):
        return time_ns, np.column_stack(numbers[:3]), None
    if any(column.size != n for column in rates):
        raise ValueError("rate columns of different lengths")
    return time_ns, np.column_stack(numbers[:3]), np.column_stack(rates)
