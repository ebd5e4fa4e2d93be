"""Per-frame costs of the live loop's inputs (prints only; no asserts).

Run from the repository root: ``python benchmarks/bench_live_inputs.py``.

- One joint datagram decoded, validated and kept (``JointReceiver.add_datagram``), 1 kHz in
  the live loop. Target: <= 5 us median.
- ``JointReceiver.poll`` of a burst of 50 pending datagrams over loopback (the joints between
  two images at 20 fps) and ``JointReceiver.sample`` at an image time, for context.
- ``Reconstructor.observe`` of one frame: two 640x480 cameras (the rendering rig), the tip and
  every marker seen in both. Target: <= 150 us median. The orthographic rig for context.
"""

from __future__ import annotations

import platform
import socket
import time

import numpy as np
from _common import verdict  # noqa: F401  (puts the repository on sys.path)

from models.catheter import default_catheter  # noqa: E402
from models.imaging import default_orthographic_rig  # noqa: E402
from replay.simulation.render import default_render_rig  # noqa: E402
from replay.simulation.simulator import (  # noqa: E402
    NoiseSettings,
    default_scene,
    simulate_frames,
    sinusoidal,
)
from tracker.io.datagrams import encode_joints  # noqa: E402
from tracker.io.udp import JointReceiver  # noqa: E402
from tracker.reconstruction import Reconstructor  # noqa: E402

TARGET_DATAGRAM_US = 5.0
TARGET_OBSERVE_US = 150.0
DATAGRAMS = 20_000
BURST = 50
BURSTS = 300
FRAMES = 200
OBSERVE_CALLS = 2_000


def datagrams(n: int) -> list[bytes]:
    """A 1 kHz joint stream with measured rates."""
    return [
        encode_joints(k, 1000.0 + k * 1e-3, (0.1 + 1e-4 * k, 0.6, -0.4), (0.1, 0.0, 0.0))
        for k in range(n)
    ]


def median_us(seconds) -> str:
    p50, p99 = 1e6 * np.median(seconds), 1e6 * np.percentile(seconds, 99)
    return f"median {p50:6.1f} us, p99 {p99:6.1f} us"


def bench_joints() -> None:
    stream = datagrams(DATAGRAMS)
    receiver = JointReceiver(port=None, clock="aligned")
    seconds = np.empty(DATAGRAMS)
    for k, data in enumerate(stream):
        start = time.perf_counter()
        receiver.add_datagram(data, 5.0 + k * 1e-3)
        seconds[k] = time.perf_counter() - start
    ok = verdict(np.median(seconds) * 1e6 <= TARGET_DATAGRAM_US)
    print(f"JointReceiver.add_datagram, {DATAGRAMS:,} datagrams")
    print(f"  {median_us(seconds)}   target <= {TARGET_DATAGRAM_US:g} us   {ok}")

    stream = datagrams(BURST * BURSTS)
    polls, samples = np.empty(BURSTS), np.empty(BURSTS)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as controller:
        with JointReceiver(port=0, clock="sender") as receiver:
            for i in range(BURSTS):
                for data in stream[i * BURST : (i + 1) * BURST]:
                    controller.sendto(data, receiver.address)
                time.sleep(0.001)  # every datagram of the burst is pending
                start = time.perf_counter()
                receiver.poll()
                polls[i] = time.perf_counter() - start
                start = time.perf_counter()
                receiver.sample(1000.0 + ((i + 1) * BURST - 1.5) * 1e-3)
                samples[i] = time.perf_counter() - start
    print(f"JointReceiver.poll of {BURST} pending datagrams, {BURSTS} bursts: {median_us(polls)}")
    print(f"JointReceiver.sample after each (history up to 2048): {median_us(samples)}")


def bench_observe(label: str, rig, target: bool) -> None:
    scene = default_scene(default_catheter(), rig)
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.3, 0.1, 0.1], [3, 3, 3], FRAMES / 20.0)
    frames = simulate_frames(
        scene, trajectory, 1.0, NoiseSettings(sigma=0.5), np.random.default_rng(0)
    )
    reconstructor = Reconstructor(scene.catheter, rig, scene.R_w_b, scene.o_b_w_mm)
    seconds = np.empty(OBSERVE_CALLS)
    for i in range(OBSERVE_CALLS):
        frame = frames[i % len(frames)]
        start = time.perf_counter()
        reconstructor.observe(frame)
        seconds[i] = time.perf_counter() - start
    points = frames[0].uv[0].shape[0]
    print(f"Reconstructor.observe, {label}, {points} points, {OBSERVE_CALLS:,} calls")
    line = f"  {median_us(seconds)}"
    if target:
        ok = verdict(np.median(seconds) * 1e6 <= TARGET_OBSERVE_US)
        line += f"   target <= {TARGET_OBSERVE_US:g} us   {ok}"
    print(line)


def main() -> None:
    print(f"Python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    print()
    bench_joints()
    print()
    bench_observe("two 640x480 cameras", default_render_rig(), target=True)
    bench_observe("two orthographic planes", default_orthographic_rig(), target=False)


if __name__ == "__main__":
    main()
