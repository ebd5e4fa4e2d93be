"""Soak of ``cathtrack track`` under bad input (not part of the test run; prints only).

Run from the repository root: ``python benchmarks/soak.py --minutes 10``.

``cathtrack track`` runs as its own process, as on the bench, taking markers segmented
elsewhere and joint values over loopback UDP and recording everything (``--record``). This
script plays the controller and the external segmenter for ``--minutes``:

- joint datagrams at ``--joint-rate`` Hz (1 kHz) stamped with ``time.monotonic()`` (track
  uses the sender clock), values of the simulated session's periodic motion;
- one marker datagram per frame at ``--fps`` (20): both views' points of the catheter at that
  motion and a fixed true delta_L, with 0.5 px of noise, sent 2 ms after the frame time;
- after ``--garbage`` (1 %) of the good datagrams of each stream, one bad datagram, taking
  every kind of garbage in turn (truncated, too long, bad magic, bad version, NaN, values
  beyond the robot's or the cameras' ranges, a time stamp 1e6 s ahead, a repeat, an old
  one, random bytes, wrong point or view counts, a zero sigma); never instead of a good one.

At the end it checks, from track's summary and the estimate datagrams it received:

- memory: track's resident set size over time (``/proc/<pid>/status``) does not grow;
- every bad item counted: each kind of garbage sent is in track's counts under its reason;
- latency: its median in the last third of the run within a frame period of the first's;
- every good frame estimated: one estimate datagram per good marker datagram, valid once the
  filter has started, and the recording reads back complete with every frame and estimate.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from _common import ROOT, verdict

from models.catheter import default_catheter  # noqa: E402
from models.pose import Pose  # noqa: E402
from models.rig_file import rig_toml  # noqa: E402
from models.rotations import wrap_angle  # noqa: E402
from replay.simulation.render import default_render_rig  # noqa: E402
from replay.simulation.simulator import (  # noqa: E402
    NoiseSettings,
    default_scene,
    simulate_frames,
)
from replay.simulation.sources import (  # noqa: E402
    SESSION_PERIOD_S,
    session_joints,
    session_trajectory,
)
from tracker.io.datagrams import (  # noqa: E402
    JOINT_STRUCT,
    VERSION,
    decode_estimate,
    encode_joints,
    encode_markers,
)
from tracker.io.recording import open_recording  # noqa: E402

DELTA_L_TRUE_RAD = 2.0
PERIOD_S = float(np.lcm.reduce(np.round(SESSION_PERIOD_S).astype(int)))
"""The session's motion repeats after this (periods of 16, 9 and 6 s: 144 s)."""
FRAME_DELAY_S = 0.002  # exposure to marker datagram: the joints are there first
JOINT_GARBAGE = {
    # kind: the counter of track's joint receiver it goes to
    "truncated": "size",
    "too long": "size",
    "bad magic": "magic",
    "bad version": "version",
    "NaN": "non-finite",
    "q_r 1e300": "range",
    "stamped 1e6 s ahead": "time",
    "repeat": "duplicate",
    "old": "stale",
    "random bytes": "magic",
}
MARKER_GARBAGE = {
    # kind: the counter it goes to (datagrams by reason; frames dropped by the loop)
    "truncated": "size",
    "bad magic": "magic",
    "bad version": "version",
    "wrong point count": "points",
    "wrong view count": "views",
    "NaN time": "non-finite",
    "u 1e300": "range",
    "zero sigma": "sigma",
    "repeat": "frame duplicate",
    "old": "frame out of order",
    "stamped 1e6 s ahead": "frame too far ahead of the stream",
}


def rss_mb(pid: int) -> float:
    """Resident set size of a process, MB (Linux)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return math.nan


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Garbage:
    """Bad datagrams of every kind, in turn."""

    def __init__(self, kinds: dict[str, str], rng: np.random.Generator) -> None:
        self.kinds = list(kinds)
        self.sent: Counter[str] = Counter()
        self.rng = rng
        self._next = 0

    def kind(self) -> str:
        kind = self.kinds[self._next % len(self.kinds)]
        self._next += 1
        self.sent[kind] += 1
        return kind


def bad_joint(kind: str, k: int, t: float, good: bytes, history: list[bytes], rng) -> bytes:
    q, q_dot = session_joints(t % PERIOD_S)
    if kind == "truncated":
        return good[:40]
    if kind == "too long":
        return good + b"\x00"
    if kind == "bad magic":
        return b"XXXX" + good[4:]
    if kind == "bad version":
        return good[:4] + (VERSION + 1).to_bytes(2, "little") + good[6:]
    if kind == "NaN":
        return encode_joints(k + 1, math.nan, q, q_dot)
    if kind == "q_r 1e300":
        return encode_joints(k + 1, t, [1e300, q[1], q[2]], q_dot)
    if kind == "stamped 1e6 s ahead":
        return encode_joints(k + 1, t + 1e6, q, q_dot)
    if kind == "repeat":
        return good
    if kind == "old":
        return history[0]
    return rng.bytes(JOINT_STRUCT.size)


def bad_marker(kind: str, j: int, good: bytes, history: list[bytes], uv, time_s: float) -> bytes:
    if kind == "truncated":
        return good[:30]
    if kind == "bad magic":
        return b"XXXX" + good[4:]
    if kind == "bad version":
        return good[:4] + (VERSION + 1).to_bytes(2, "little") + good[6:]
    if kind == "wrong point count":
        return encode_markers(j, time_s, [u[:1] for u in uv], (0.5, 0.5))
    if kind == "wrong view count":
        return encode_markers(j, time_s, [*uv, uv[0]], (0.5, 0.5, 0.5))
    if kind == "NaN time":
        return good[:16] + np.float64(math.nan).tobytes() + good[24:]
    if kind == "u 1e300":
        bad = [u.copy() for u in uv]
        bad[0][0, 0] = 1e300
        return encode_markers(j, time_s, bad, (0.5, 0.5))
    if kind == "zero sigma":
        return encode_markers(j, time_s, uv, (0.0, 0.5))
    if kind == "repeat":
        return good
    if kind == "old":
        return history[0]
    return encode_markers(j, time_s + 1e6, uv, (0.5, 0.5))  # stamped 1e6 s ahead


def parse_summary(text: str) -> dict:
    """The counts of track's summary (the lines it prints when it ends)."""
    out: dict = {}
    m = re.search(r"(\d+) of (\d+) frames processed, (\d+) with an estimate", text)
    if m:
        out["processed"], out["received"], out["valid"] = map(int, m.groups())
    m = re.search(r"dropped:(.*)", text)
    if m:
        for n, what in re.findall(r"(\d+) ([a-z][a-z ]*?)(?:,|$| \()", m.group(1)):
            out[f"frame {what.strip()}"] = int(n)
    for label in ("joint", "marker"):
        m = re.search(rf"{label} datagrams: (.*)", text)
        if not m:
            continue
        line = m.group(1)
        words = r"(\d+) (stale|duplicate|received|used)"
        counts = {what: int(n) for n, what in re.findall(words, line)}
        tail = line.split("dropped by reason:", 1)[-1] if "dropped by reason:" in line else ""
        for what, n in re.findall(r"([a-z-]+) (\d+)", tail):
            counts[what] = int(n)
        out[label] = counts
    m = re.search(r"p50 in each third of the run: ([\d.]+) / ([\d.]+) / ([\d.]+) ms", text)
    if m:
        out["latency thirds"] = tuple(map(float, m.groups()))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the soak (10)")
    parser.add_argument("--seconds", type=float, help="length in seconds (instead of minutes)")
    parser.add_argument("--joint-rate", type=float, default=1000.0, help="Hz (1000)")
    parser.add_argument("--fps", type=float, default=20.0, help="frames per second (20)")
    parser.add_argument("--garbage", type=float, default=0.01, help="fraction of bad items (0.01)")
    parser.add_argument("--out", help="folder of the rig, recording and track's output (temp)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    duration_s = args.seconds if args.seconds is not None else 60.0 * args.minutes

    catheter = default_catheter()
    rig = default_render_rig()
    scene = default_scene(catheter, rig)
    trajectory = session_trajectory(PERIOD_S, args.fps)
    rng = np.random.default_rng(args.seed)
    pool = simulate_frames(
        scene,
        trajectory,
        np.full(trajectory.q.shape[0], DELTA_L_TRUE_RAD),
        NoiseSettings(sigma=0.5),
        rng,
    )
    out = Path(args.out or tempfile.mkdtemp(prefix="cathtrack-soak-"))
    out.mkdir(parents=True, exist_ok=True)
    rig_path, record_path = out / "rig.toml", out / "soak.mcap"
    rig_path.write_text(rig_toml(rig, Pose(scene.R_w_b, scene.o_b_w_mm)))
    joints_port, markers_port = free_port(), free_port()
    controller = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    controller.bind(("127.0.0.1", 0))
    controller.setblocking(False)
    command = [
        sys.executable, "-m", "replay.cli", "track",
        "--rig", str(rig_path),
        "--markers-port", str(markers_port),
        "--joints-port", str(joints_port),
        "--joint-clock", "sender",
        "--estimate-to", f"127.0.0.1:{controller.getsockname()[1]}",
        "--record", str(record_path),
        "--idle-timeout", "3",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    track_out = open(out / "track.txt", "w+")  # noqa: SIM115 - read back at the end
    track = subprocess.Popen(command, stdout=track_out, stderr=subprocess.STDOUT, env=env)
    print(
        f"soak of cathtrack track (pid {track.pid}) for {duration_s:g} s: {args.joint_rate:g} Hz"
        f" joints, {args.fps:g} fps markers, {100 * args.garbage:g} % garbage; files in {out}",
        flush=True,
    )
    deadline = time.monotonic() + 60.0
    while "Ctrl-C to stop" not in (out / "track.txt").read_text():
        if track.poll() is not None or time.monotonic() > deadline:
            print((out / "track.txt").read_text())
            return 1
        time.sleep(0.05)

    joint_garbage, marker_garbage = Garbage(JOINT_GARBAGE, rng), Garbage(MARKER_GARBAGE, rng)
    sent = Counter()
    estimates = []
    memory: list[tuple[float, float]] = []
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    start_s = time.monotonic() + 0.2

    def drain() -> None:
        while True:
            try:
                estimates.append(decode_estimate(controller.recv(256)))
            except BlockingIOError:
                return

    k = j = 0
    joint_history: list[bytes] = []
    marker_history: list[bytes] = []
    next_report = 0.0
    joint_to, marker_to = ("127.0.0.1", joints_port), ("127.0.0.1", markers_port)
    while True:
        now = time.monotonic()
        elapsed = now - start_s
        if elapsed >= duration_s:
            break
        while start_s + k / args.joint_rate <= now:
            t = start_s + k / args.joint_rate
            good = encode_joints(k, t, *session_joints((t - start_s) % PERIOD_S))
            sender.sendto(good, joint_to)
            sent["joints"] += 1
            joint_history = (joint_history + [good])[-10:]
            if rng.random() < args.garbage:
                kind = joint_garbage.kind()
                sender.sendto(bad_joint(kind, k, t, good, joint_history, rng), joint_to)
            k += 1
        while start_s + j / args.fps + FRAME_DELAY_S <= now:
            frame = pool[j % len(pool)]
            time_s = start_s + j / args.fps
            good = encode_markers(j, time_s, frame.uv, (0.5, 0.5))
            sender.sendto(good, marker_to)
            sent["frames"] += 1
            marker_history = (marker_history + [good])[-5:]
            if rng.random() < args.garbage:
                kind = marker_garbage.kind()
                bad = bad_marker(kind, j, good, marker_history, frame.uv, time_s)
                sender.sendto(bad, marker_to)
            j += 1
        drain()
        if elapsed >= next_report:
            memory.append((elapsed, rss_mb(track.pid)))
            if next_report > 0:
                print(
                    f"  {elapsed:6.0f} s: {sent['frames']} frames, {len(estimates)} estimates,"
                    f" track RSS {memory[-1][1]:.1f} MB",
                    flush=True,
                )
            next_report += max(10.0, duration_s / 20)
        time.sleep(0.0005)
    memory.append((time.monotonic() - start_s, rss_mb(track.pid)))
    try:
        track.wait(timeout=60.0)
    except subprocess.TimeoutExpired:
        track.send_signal(signal.SIGINT)
        track.wait(timeout=60.0)
    time.sleep(0.2)
    drain()
    sender.close()
    controller.close()
    track_out.seek(0)
    text = track_out.read()
    track_out.close()
    print(text.rstrip())

    # ---- memory: after the first minute (imports done, buffers warmed up) the resident set
    # may creep while the allocator settles, then stays flat: judged over the second half.
    # The MCAP writer keeps one chunk index per second of recording for the file's summary:
    # about 0.1 MB a minute, which tracemalloc shows as the only growth left.
    times = np.array([m[0] for m in memory])
    rss = np.array([m[1] for m in memory])
    settled = times >= min(60.0, 0.25 * duration_s)
    late = times >= 0.5 * times[-1]
    trend = np.polyfit(times[late], rss[late], 1)[0] * 60.0 if late.sum() > 2 else 0.0
    growth = rss[-1] - rss[settled][0]
    memory_ok = trend < 0.2 and growth < 10.0
    print(
        f"\nmemory: track RSS {rss[0]:.1f} MB at the start, {rss[settled][0]:.1f} MB after"
        f" {times[settled][0]:.0f} s, {rss[-1]:.1f} MB at the end ({growth:+.1f} MB); trend over"
        f" the second half {trend:+.3f} MB/min: {verdict(memory_ok)}"
    )

    # ---- every bad item counted
    summary = parse_summary(text)
    counted_ok = True
    print("garbage sent -> counted by track:")
    for label, garbage, table in (
        ("joint", joint_garbage, JOINT_GARBAGE),
        ("marker", marker_garbage, MARKER_GARBAGE),
    ):
        expected = Counter()
        for kind, n in garbage.sent.items():
            expected[table[kind]] += n
        counts = summary.get(label, {})
        for reason, n in sorted(expected.items()):
            if reason.startswith("frame "):
                got = summary.get(reason)
            else:
                got = counts.get(reason)
            ok = got == n
            counted_ok &= ok
            kinds = ", ".join(
                f"{kind} {m}" for kind, m in garbage.sent.items() if table[kind] == reason
            )
            print(f"  {label:6s} {reason:20s} sent {n:5d} ({kinds}), counted {got}: {verdict(ok)}")

    # ---- the latency does not grow: the last third's median within a frame period of the
    # first's (a loop falling behind its source gains a period every few frames)
    thirds = summary.get("latency thirds")
    period_ms = 1e3 / args.fps
    latency_ok = thirds is not None and thirds[2] - thirds[0] < period_ms
    print(
        "latency image -> estimate, p50 in each third of the run: "
        + (" / ".join(f"{ms:.2f}" for ms in thirds) + " ms" if thirds else "not in the summary")
        + f" (not growing: the last within {period_ms:g} ms of the first): {verdict(latency_ok)}"
    )

    # ---- every good frame estimated
    good_frames = sent["frames"]
    valid = [m for m in estimates if m.valid]
    first_valid = next((i for i, m in enumerate(estimates) if m.valid), len(estimates))
    late_invalid = sum(1 for m in estimates[first_valid:] if not m.valid)
    estimated_ok = len(estimates) == good_frames and late_invalid == 0
    print(
        f"good frames: {good_frames} sent, {len(estimates)} estimate datagrams received,"
        f" {len(valid)} valid ({first_valid} before the filter started, {late_invalid} invalid"
        f" after): {verdict(estimated_ok)}"
    )
    if valid:
        error = np.degrees(wrap_angle(np.array([m.delta_L_rad for m in valid]) - DELTA_L_TRUE_RAD))
        print(
            f"delta_L error: RMS {np.sqrt(np.mean(error**2)):.2f} deg, max"
            f" {np.max(np.abs(error)):.2f} deg; joints {sent['joints']} good datagrams sent"
        )
    try:
        with open_recording(record_path) as recording:
            n_frames, n_estimates = len(recording), len(recording.estimates.get("ukf", []))
            report_ok = recording.report.ok
            warnings = recording.report.warnings
    except ValueError as error:
        n_frames = n_estimates = -1
        report_ok, warnings = False, [str(error)]
    processed = summary.get("processed")
    recording_ok = report_ok and n_frames == processed == n_estimates
    print(
        f"recording {record_path.name}: {n_frames} frames, {n_estimates} estimates"
        f" (track processed {processed}), read report {'clean' if report_ok else warnings}:"
        f" {verdict(recording_ok)}"
    )
    ok = memory_ok and counted_ok and latency_ok and estimated_ok and recording_ok
    ok = ok and track.returncode == 0
    print(f"soak: {verdict(ok)} (track exit code {track.returncode})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
