"""The recording reader's bulk paths (tracker.io.recording.scan, .decode, .joint_samples)
against the ways they replace: the library's chunk reader, the joined joint columns, one
message at a time; the protobuf joint blocks against the JSON ones, and their damage."""

from __future__ import annotations

import io
import itertools
import struct
import zlib

import numpy as np
import orjson
import pytest
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.records import Chunk
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from tests.tracker.test_recording import _frames, _write
from tracker.io.limits import joints_in_range
from tracker.io.recording import decode, joint_samples, open_recording, protobuf
from tracker.io.recording.scan import McapScan, _ChunkStream, _unpack
from tracker.io.recording.schema import TOPIC_TRUTH, RecordingError

SESSION_NS = (-(2**62), 2**62)


# ------------------------------------------------------------------------ chunk records
def _outcome(call):
    """What a read gives: its value, or the type of what it raised."""
    try:
        return call()
    except (EndOfFile, struct.error) as exc:
        return type(exc).__name__


@pytest.mark.parametrize("seed", range(5))
def test_chunk_stream_reads_as_the_library_stream_does(seed):
    """Random reads of random lengths, past the end too: the same bytes, values and errors."""
    rng = np.random.default_rng(seed)
    data = rng.bytes(int(rng.integers(0, 40)))
    ours, library = _ChunkStream(data), ReadDataStream(io.BytesIO(data))
    for _ in range(30):
        kind = int(rng.integers(0, 6))
        if kind == 5:
            n = int(rng.integers(-3, 12))
            ours_call, library_call = (lambda n=n: ours.read(n)), (lambda n=n: library.read(n))
        else:
            name = ("read1", "read2", "read4", "read8", "read8")[kind]
            ours_call, library_call = getattr(ours, name), getattr(library, name)
        assert _outcome(ours_call) == _outcome(library_call)
        if ours.count < len(data) or library.count < len(data):
            assert ours.count == library.count


def _chunks(path) -> list[Chunk]:
    with open(path, "rb") as f:
        scan = McapScan(f)
        offsets = [item.offset for item in scan.records() if hasattr(item, "records")]
        out = []
        for offset in offsets:
            f.seek(offset + 9)
            out.append(Chunk.read(ReadDataStream(f)))
        return out


def _small_recording(path, compression=CompressionType.ZSTD):
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=2_000, compression=compression)
        writer.start(profile="", library="test")
        schema = writer.register_schema("s", "jsonschema", b"{}")
        channels = [writer.register_channel(f"/t{k}", "json", schema) for k in range(3)]
        for k in range(200):
            writer.add_message(channels[k % 3], 1000 * k, orjson.dumps({"k": k}), 1000 * k)
        writer.finish()
    return path


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4])
def test_chunk_records_are_the_library_records(tmp_path, compression):
    chunks = _chunks(_small_recording(tmp_path / "small.mcap", compression))
    assert len(chunks) > 3
    for chunk in chunks:
        assert _unpack(chunk) == breakup_chunk(chunk, validate_crc=True)


def test_a_chunk_whose_records_overrun_fails_as_with_the_library(tmp_path):
    """A chunk whose content is damaged byte by byte (its CRC recomputed, so that only the
    records are wrong): the same records, or the same kind of error."""
    chunk = _chunks(_small_recording(tmp_path / "small.mcap"))[1]
    data = bytearray(zstandard.decompress(chunk.data, chunk.uncompressed_size))
    overflows = 0
    for offset in range(0, len(data), 7):
        damaged = bytearray(data)
        damaged[offset] ^= 0xFF
        raw = bytes(damaged)
        bad = Chunk(
            compression="",
            data=raw,
            message_end_time=chunk.message_end_time,
            message_start_time=chunk.message_start_time,
            uncompressed_crc=zlib.crc32(raw),
            uncompressed_size=len(raw),
        )
        ours = _outcome(lambda bad=bad: _unpack(bad))
        try:
            library = _outcome(lambda bad=bad: breakup_chunk(bad, validate_crc=True))
        except OverflowError:
            # A record length of 2^63 or more: the library's BytesIO cannot even try (the
            # reader would stop there); ours reads what is there, as for any overrun.
            assert not isinstance(ours, str)
            overflows += 1
            continue
        assert ours == library, offset
    assert overflows < len(data) // 7 // 2


# ------------------------------------------------------------------------------ messages
def test_store_keeps_the_first_message_of_each_time_and_counts_the_rest():
    problems = decode.Problems()
    stamps = np.array([30, 10, 30, 20, 10, 10], dtype=np.int64)
    store = decode.Store.first_of(stamps, ["a", "b", "c", "d", "e", "f"], "/x", problems)
    assert store.stamps.tolist() == [10, 20, 30] and store.values == ["b", "d", "a"]
    assert problems.counts == {("duplicate", "/x"): 3}
    assert store.get(20) == "d" and store.get(25) is None and store.get(99) is None
    assert store.at(np.array([5, 10, 30, 31])) == [None, "b", "a", None]
    assert decode.Store(np.zeros(0, np.int64), []).at(np.array([1, 2])) == [None, None]


def test_json_messages_are_those_of_one_message_at_a_time():
    data = [b'{"a": 1}', b"[1, 2]", b'{"b": NaN}', b"\x00", b"[" * 2000 + b"]" * 2000, b"{}"]
    problems = decode.Problems()
    payloads = decode.json_messages(data, "/x", problems)
    assert payloads[0] == {"a": 1} and payloads[5] == {}
    assert payloads[1] is None and payloads[3] is None and payloads[4] is None
    assert np.isnan(payloads[2]["b"])
    assert problems.counts == {("malformed", "/x"): 3}


# -------------------------------------------------------------------------------- joints
def _blocks(rng: np.random.Generator, rates: str, n_blocks: int = 40) -> list[dict]:
    """Joint blocks of random lengths, some values null or NaN, times partly out of order
    and repeated."""
    blocks, t = [], 0
    for _ in range(n_blocks):
        n = int(rng.integers(0, 8))
        times = (t + 1_000_000 * np.arange(n)).tolist()
        t += 1_000_000 * max(n - int(rng.integers(0, 3)), 0)
        block = {"time_ns": times}
        for name in ("q_r_rad", "q_p_mm", "q_d_mm"):
            block[name] = rng.uniform(-1, 1, n).tolist()
        with_rates = rates == "all" or (rates == "some" and rng.random() < 0.5)
        for name in ("q_r_dot_rad_s", "q_p_dot_mm_s", "q_d_dot_mm_s"):
            block[name] = rng.uniform(-5, 5, n).tolist() if with_rates else None
        if n and rng.random() < 0.2:
            block["q_p_mm"][int(rng.integers(0, n))] = None
        if n and rng.random() < 0.1:
            block["q_d_mm"][0] = 500.0  # beyond the range
        blocks.append(orjson.loads(orjson.dumps(block)))
    return blocks


@pytest.mark.parametrize("rates", ["all", "none", "some"])
@pytest.mark.parametrize("seed", range(4))
def test_joint_columns_are_the_joined_columns(rates, seed):
    blocks = _blocks(np.random.default_rng(seed), rates)
    fast = decode._joint_columns(blocks)
    joined = decode._joint_columns_joined(blocks, decode.Problems(), "test")
    if rates == "some":
        assert fast is None  # rates in some blocks only: the joined path
        return
    t, q, r, any_rates = fast
    np.testing.assert_array_equal(t, joined[0])
    np.testing.assert_array_equal(q, joined[1])
    np.testing.assert_array_equal(r, joined[2])
    assert any_rates == joined[3] == (rates == "all")


@pytest.mark.parametrize(
    "edit",
    [
        lambda b: b.__setitem__("q_r_rad", b["q_r_rad"][:-1]),  # a short column
        lambda b: b.__setitem__("time_ns", "soon"),
        lambda b: b["q_p_mm"].__setitem__(0, [1.0]),
        lambda b: b["time_ns"].__setitem__(0, 2**64),
        lambda b: b.pop("q_d_mm"),
    ],
)
def test_joint_blocks_that_do_not_fit_go_the_joined_way(edit):
    blocks = _blocks(np.random.default_rng(9), "all")
    edit(next(b for b in blocks if len(b["time_ns"]) > 1))
    assert decode._joint_columns(blocks) is None


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("seed", range(3))
def test_joint_stream_checks_count_what_the_row_checks_count(seed, version):
    """The whole-array shortcuts of joint_stream drop and count what the row-by-row rules
    (NaN, range, order, repeats) do, on the JSON blocks and on the same blocks in protobuf."""
    blocks = _blocks(np.random.default_rng(seed), "all")
    problems = decode.Problems()
    if version == 1:
        columns = decode.json_joint_columns(blocks, problems, "test")
    else:
        columns = decode.protobuf_joint_columns(_encoded(blocks), problems, "test")
    t, q, q_dot = decode.joint_stream(columns, problems, "test", SESSION_NS)
    joined = decode._joint_columns_joined(blocks, decode.Problems(), "test")
    t_all, q_all, r_all = joined[:3]
    good = np.isfinite(q_all).all(axis=1) & np.isfinite(r_all).all(axis=1)
    in_range = joints_in_range(q_all[good], r_all[good])
    kept_t = t_all[good][in_range]
    assert problems.counts.get(("nan_joints", "/joints"), 0) == np.count_nonzero(~good)
    assert problems.counts.get(("out_of_range", "/joints (samples)"), 0) == np.count_nonzero(
        ~in_range
    )
    np.testing.assert_array_equal(t, np.unique(kept_t))
    assert q.shape == q_dot.shape == (t.size, 3) and np.isfinite(q).all()


# ------------------------------------------------------------------ joints in protobuf (v2)
def _arrays(block: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A JSON joint block's columns as arrays (null: NaN)."""
    t = np.array(block["time_ns"], dtype=np.int64)
    q = np.array([block[n] for n in ("q_r_rad", "q_p_mm", "q_d_mm")], dtype=float).T
    names = ("q_r_dot_rad_s", "q_p_dot_mm_s", "q_d_dot_mm_s")
    rates = None if block[names[0]] is None else np.array([block[n] for n in names], float).T
    return t, q.reshape(t.size, 3), None if rates is None else rates.reshape(t.size, 3)


def _encoded(blocks: list[dict]) -> list[bytes]:
    return [joint_samples.encode_joint_block(*_arrays(block)) for block in blocks]


@pytest.mark.parametrize("rates", ["all", "none", "some"])
@pytest.mark.parametrize("seed", range(4))
def test_protobuf_joint_columns_are_the_json_ones(rates, seed):
    """The same blocks in protobuf (version 2) and in JSON (version 1) give the same columns;
    the blocks of each size converted at once give what reading each on its own gives."""
    blocks = _blocks(np.random.default_rng(seed), rates)
    messages = _encoded(blocks)
    t, q, r, any_rates, malformed = joint_samples.joint_columns(messages)
    json_t, json_q, json_r, json_any = decode.json_joint_columns(blocks, decode.Problems(), "test")
    assert malformed == 0 and any_rates == json_any
    np.testing.assert_array_equal(t, json_t)
    np.testing.assert_array_equal(q, json_q)
    np.testing.assert_array_equal(r, json_r)
    one_by_one = [joint_samples._block(m) for m in messages]
    np.testing.assert_array_equal(t, np.concatenate([b[0] for b in one_by_one]))
    np.testing.assert_array_equal(q, np.concatenate([b[1] for b in one_by_one]))


def _field(number: int, wire: int, content: bytes) -> bytes:
    if wire == protobuf.WIRE_LEN:
        return protobuf.len_field(number, content)
    return protobuf.key_bytes(number, wire) + content


def _other_encodings(t: np.ndarray, q: np.ndarray, rates: np.ndarray) -> dict[str, bytes]:
    """One block as other protobuf writers may encode it: the same message."""
    columns = [t.astype("<i8")] + [c.astype("<f8") for c in (*q.T, *rates.T)]
    packed = [(k + 1, c.tobytes()) for k, c in enumerate(columns)]
    return {
        "fields in reverse order": b"".join(_field(n, 2, c) for n, c in packed[::-1]),
        "columns in two pieces": b"".join(_field(n, 2, c[:16]) for n, c in packed)
        + b"".join(_field(n, 2, c[16:]) for n, c in packed),
        "unpacked values": b"".join(
            _field(n, protobuf.WIRE_I64, c[i : i + 8])
            for n, c in packed
            for i in range(0, len(c), 8)
        ),
        "unknown fields": protobuf.varint_field(99, 5)
        + b"".join(_field(n, 2, c) for n, c in packed)
        + protobuf.len_field(8, b"later")
        + _field(12, protobuf.WIRE_I32, b"\x00" * 4),
    }


def test_joint_blocks_in_other_valid_encodings_read_the_same():
    rng = np.random.default_rng(3)
    t = 1_000_000 * np.arange(6, dtype=np.int64)
    q, rates = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    good = joint_samples.encode_joint_block(t + 10**9, q, rates)  # a block written by cathtrack
    for name, message in _other_encodings(t, q, rates).items():
        got_t, got_q, got_r, any_rates, malformed = joint_samples.joint_columns(
            [good, message, b""]
        )
        assert malformed == 0 and any_rates, name
        np.testing.assert_array_equal(got_t, np.concatenate([t + 10**9, t]), err_msg=name)
        np.testing.assert_array_equal(got_q, np.vstack([q, q]), err_msg=name)
        np.testing.assert_array_equal(got_r, np.vstack([rates, rates]), err_msg=name)


def _damaged_blocks() -> dict[str, bytes]:
    """A block damaged in each way a reader must survive. The block of 5 samples with rates
    is 7 fields of 42 bytes: key, length 40, five 8-byte numbers."""
    t = 1_000_000 * np.arange(20, dtype=np.int64)
    q = np.ones((20, 3))
    block = joint_samples.encode_joint_block(t[:5], q[:5], q[:5])
    short = joint_samples.encode_joint_block(t[:4], q[:4], q[:4])  # fields of 34 bytes
    long = joint_samples.encode_joint_block(t, q)  # lengths of 2 bytes: 160
    moved = bytearray(block)
    moved[42 + 1], moved[84 + 1] = 32, 48  # q_r one sample short, q_p one long: same size
    return {
        "truncated in a column": block[:-3],
        "truncated after a key": block[: 6 * 42 + 1],
        "truncated inside a length": long[:2],
        "a column one sample short": block[: 3 * 42] + short[3 * 34 : 4 * 34] + block[4 * 42 :],
        "the time column one sample long": protobuf.len_field(1, t[:6].tobytes()) + block[42:],
        "column lengths moved, same size": bytes(moved),
        "a column under another number": block[:42] + b"\x42" + block[43:],
        "only one rate column": block[: 5 * 42],
        "a column of 7-byte numbers": block[:42] + protobuf.len_field(2, b"\x00" * 35) + block[84:],
        "a column as a varint": block[:42] + protobuf.varint_field(2, 1) + block[84:],
        "a deprecated group": block + protobuf.key_bytes(9, 3),
        "not protobuf": b"\xff" * 20,
        "JSON": b'{"time_ns": [1], "q_r_rad": [0.0], "q_p_mm": [0.0], "q_d_mm": [0.0]}',
    }


@pytest.mark.parametrize("name", list(_damaged_blocks()))
def test_a_damaged_protobuf_joint_block_is_one_counted_loss(name):
    """A damaged block is dropped and counted once; the blocks around it are read intact,
    whether the damaged one has the length of a good block or not."""
    damaged = _damaged_blocks()[name]
    rng = np.random.default_rng(4)
    good = []
    for k in range(6):
        t = 10**9 * k + 1_000_000 * np.arange(5, dtype=np.int64)
        good.append((t, rng.normal(size=(5, 3)), rng.normal(size=(5, 3))))
    messages = [joint_samples.encode_joint_block(*block) for block in good]
    messages.insert(3, damaged)
    problems = decode.Problems()
    t, q, r, any_rates = decode.protobuf_joint_columns(messages, problems, "test")
    assert problems.counts == {("malformed", "/joints"): 1}
    np.testing.assert_array_equal(t, np.concatenate([b[0] for b in good]))
    np.testing.assert_array_equal(q, np.concatenate([b[1] for b in good]))
    np.testing.assert_array_equal(r, np.concatenate([b[2] for b in good]))
    with pytest.raises(ValueError):
        joint_samples._block(damaged)


def test_protobuf_joint_samples_nan_and_out_of_order_are_counted_and_dropped_or_sorted():
    t = 1_000_000 * np.arange(10, dtype=np.int64)
    q = np.tile([0.1, 0.2, 0.3], (10, 1))
    q[4, 2] = np.nan
    first = joint_samples.encode_joint_block(t[5:], q[5:])  # the later block first
    second = joint_samples.encode_joint_block(t[:5][::-1], q[:5][::-1])  # unsorted inside
    problems = decode.Problems()
    columns = decode.protobuf_joint_columns([first, second], problems, "test")
    got_t, got_q, got_rates = decode.joint_stream(columns, problems, "test", SESSION_NS)
    assert got_rates is None
    np.testing.assert_array_equal(got_t, np.delete(t, 4))
    np.testing.assert_array_equal(got_q, np.delete(q, 4, axis=0))
    assert problems.counts[("nan_joints", "/joints")] == 1
    assert problems.counts[("out_of_order", "/joints (samples)")] >= 1


def test_protobuf_joint_stream_without_samples_is_a_recording_error():
    with pytest.raises(RecordingError, match="no valid samples"):
        decode.protobuf_joint_columns([b"\xff\xff", b"\x0a\x10"], decode.Problems(), "test")
    with pytest.raises(RecordingError, match="no joint samples"):
        decode.protobuf_joint_columns([b"", b""], decode.Problems(), "test")


def test_protobuf_wire_reader_refuses_damage():
    assert protobuf.read_varint(b"\xac\x02", 0) == (300, 2)
    assert protobuf.varint_bytes(300) == b"\xac\x02"
    with pytest.raises(ValueError, match="truncated"):
        protobuf.read_varint(b"\x80\x80", 0)
    with pytest.raises(ValueError, match="longer than 10"):
        protobuf.read_varint(b"\xff" * 11 + b"\x01", 0)
    with pytest.raises(ValueError, match="past the end"):
        list(protobuf.fields(protobuf.len_field(1, b"abc")[:-1]))
    assert [(n, w, bytes(v)) for n, w, v in protobuf.fields(protobuf.len_field(3, "ab"))] == [
        (3, protobuf.WIRE_LEN, b"ab")
    ]


# --------------------------------------------------------------------------------- truth
def test_truth_labels_of_damaged_messages_are_unknown_not_a_crash():
    problems = decode.Problems()
    payloads = [
        {"delta_L_rad": 0.5, "plane": 1, "configuration": 2, "deflection_mm": 1.5},
        {"delta_L_rad": 0.6, "plane": 1, "configuration": 2, "deflection_mm": 1.5},
        None,
        {"delta_L_rad": 1e300, "delta_1_rad": 0.1},
        {"delta_L_rad": 0.1, "plane": float("inf")},  # int(inf) raises OverflowError
        {"delta_L_rad": "one"},
    ]
    out = decode.all_labels(payloads, problems)
    assert [d for d, _ in out] == [0.5, 0.6, None, None, None, None]
    assert out[0][1] == out[1][1] and out[0][1].plane == 1 and out[0][1].deflection_mm == 1.5
    assert out[3][1].delta_1_true_rad == 0.1
    assert problems.counts == {("out_of_range", TOPIC_TRUTH): 1, ("malformed", TOPIC_TRUTH): 2}


# -------------------------------------------------------------------------------- frames
def test_each_call_of_frames_hands_out_its_own_arrays(tmp_path):
    path = tmp_path / "r.mcap"
    _write(path, _frames(6, np.random.default_rng(2), images=False))
    with open_recording(path) as recording:
        first = [r.frame for r in recording.frames(images=False)]
        for frame in first:
            for array in (frame.q, frame.q_dot, *frame.uv, *frame.cov):
                array[...] = 12345.0
        second = [r.frame for r in recording.frames(images=False)]
    assert len(second) == 6
    for frame in second:
        for array in (frame.q, frame.q_dot, *frame.uv, *frame.cov):
            assert not np.any(array == 12345.0)


def test_chunk_iteration_yields_every_record_once(tmp_path):
    """The scan hands over each chunk's records whole; together they are the file's
    messages in file order."""
    path = _small_recording(tmp_path / "small.mcap")
    with open(path, "rb") as f:
        items = list(McapScan(f).records())
    messages = [
        r.log_time
        for item in items
        if hasattr(item, "records")
        for r in item.records
        if type(r).__name__ == "Message"
    ]
    assert messages == [1000 * k for k in range(200)]
    assert list(itertools.accumulate(messages, max)) == messages
