"""The recording reader's bulk paths (tracker.io.recording.scan, .decode) against the ways
they replace: the library's chunk reader, the joined joint columns, one message at a time."""

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
from tracker.io.recording import decode, open_recording
from tracker.io.recording.scan import McapScan, _ChunkStream, _unpack
from tracker.io.recording.schema import TOPIC_TRUTH

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


@pytest.mark.parametrize("seed", range(3))
def test_joint_stream_checks_count_what_the_row_checks_count(seed):
    """The whole-array shortcuts of joint_stream drop and count what the row-by-row rules
    (NaN, range, order, repeats) do."""
    blocks = _blocks(np.random.default_rng(seed), "all")
    problems = decode.Problems()
    t, q, q_dot = decode.joint_stream(blocks, problems, "test", SESSION_NS)
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
