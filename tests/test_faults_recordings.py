"""Bad input and faults (issue 14), recordings damaged in their bytes, and the command line.

- a damaged recording that can still be read: a warning naming the problem (for a loss, its
  kind and span), and every frame outside the damage read back unchanged;
- a recording that cannot be used: one error of one line that names the file and the
  problem;
- the command line: one line and the documented exit code.

The byte damage is cut into a file the project's writer made. A fuzz test flips bytes in and
truncates a valid recording: the reader raises nothing but RecordingError, and never hangs.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from replay.cli import EXIT_INTERRUPTED, main
from replay.evaluation import evaluate_batch
from tests.faults_common import (
    FRAMES,
    MODEL_TOML,
    N_FRAMES,
    RIG_TOML,
    T_JOINTS,
    _joints,
    _read,
    assert_frames_intact,
    assert_one_line,
)
from tracker.io.recording import RecordingError, RecordingWriter, open_recording

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------ recordings
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
    (
        "random bytes",
        lambda d: d.__setitem__(slice(None), np.random.default_rng(1).bytes(5000)),
        "not an MCAP file",
    ),  # fmt: skip
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
