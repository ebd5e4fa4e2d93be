"""Soak test of the live loop (not part of the test run; prints only).

Run from the repository root: ``python benchmarks/soak.py --seconds 600``.

For ``--seconds`` of wall time, as on the bench:

- a controller thread streams joint datagrams at ``--joint-rate`` Hz (1 kHz) over loopback
  UDP, stamped with ``time.monotonic()`` (the loop's JointReceiver uses the ``aligned``
  clock), and drains the estimate datagrams that come back;
- a camera thread delivers image pairs at ``--fps`` (30) into a one-slot buffer, stamped at
  the scheduled exposure time, like two triggered cameras; a pair that the loop has not taken
  before the next one arrives is dropped (counted), as a camera driver does. Images are
  rendered for a pool of ``--pool`` poses of one period of a periodic motion
  and cycled, or synthetic (``--images synthetic``: blank images and the true points handed
  over as already-segmented markers);
- the loop segments (rendered images), reconstructs, runs the UKF and sends the estimates.

At the end: frames captured / processed / dropped, datagram counts, latency percentiles
(capture time stamp -> estimate ready), the delta_L error against the truth, and memory: the
resident set size (``resource.getrusage`` peak and ``/proc/self/statm`` over time), plus
tracemalloc's current and peak with ``--tracemalloc`` (which slows Python down).
"""

from __future__ import annotations

import argparse
import resource
import socket
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np
from _common import verdict  # noqa: E402,F401  (puts the repository on sys.path)

from models.catheter import default_catheter  # noqa: E402
from models.rotations import wrap_angle  # noqa: E402
from replay.simulation.render import Renderer, default_render_rig
from replay.simulation.simulator import default_scene
from replay.simulation.sources import session_joints
from tracker.estimators import make_estimator
from tracker.io.datagrams import SegmentedMarkers, decode_estimate, encode_joints
from tracker.io.udp import EstimateSender, JointReceiver
from tracker.live.loop import LiveTracker
from tracker.live.sources import ImageSet
from tracker.reconstruction import Reconstructor

DELTA_L_TRUE_RAD = 2.0


def rss_mb() -> float:
    """Current resident set size, MB (Linux)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except OSError:
        return float("nan")
    return pages * resource.getpagesize() / 2**20


class Camera:
    """Two triggered cameras: a pair per tick into a one-slot buffer (overwrites count)."""

    time_is_monotonic = True

    def __init__(self, items, fps: float, start_s: float, stop: threading.Event):
        self.items, self.fps, self.start_s, self.stop = items, fps, start_s, stop
        self.slot = None
        self.captured = self.dropped = self.late = 0
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        n = 0
        while not self.stop.is_set():
            stamp = self.start_s + n / self.fps
            delay = stamp - time.monotonic()
            if delay > 0 and self.stop.wait(delay):
                break
            if delay < -1.0 / self.fps:  # this thread woke up late: skip, as a camera would
                skipped = int(-delay * self.fps)
                self.late += skipped
                n += skipped
                continue
            item = self.items[n % len(self.items)]
            with self.cond:
                if self.slot is not None:
                    self.dropped += 1
                self.slot = item(stamp) if callable(item) else item
                self.captured += 1
                self.cond.notify()
            n += 1

    def __iter__(self):
        while not self.stop.is_set():
            with self.cond:
                if self.slot is None:
                    self.cond.wait(0.05)
                item, self.slot = self.slot, None
            yield item


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--joint-rate", type=float, default=1000.0, help="Hz (1000)")
    parser.add_argument("--fps", type=float, default=30.0, help="image pairs per second (30)")
    parser.add_argument("--images", choices=("rendered", "synthetic"), default="rendered")
    parser.add_argument("--pool", type=int, default=90, help="distinct poses cycled (90)")
    parser.add_argument("--tracemalloc", action="store_true", help="also trace allocations")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    catheter = default_catheter()
    scene = default_scene(catheter, default_render_rig())
    period_s = args.pool / args.fps

    def joints_at(tau_s):
        """A periodic motion: the session's motion over the first period, repeated."""
        return session_joints(np.mod(tau_s, period_s))

    renderer = Renderer(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    segmenter = None
    pool = []
    started = time.perf_counter()
    for k in range(args.pool):
        q, _ = joints_at(k / args.fps)
        pair = renderer.render(q, DELTA_L_TRUE_RAD, rng)
        if args.images == "rendered":
            images = pair.images
            pool.append(lambda stamp, images=images: ImageSet(stamp, tuple(images)))
        else:
            cov = np.tile(0.25 * np.eye(2), (pair.points_px[0].shape[0], 1, 1))
            uv = [p + 0.5 * rng.standard_normal(p.shape) for p in pair.points_px]
            pool.append(
                lambda stamp, uv=uv, cov=cov: SegmentedMarkers(stamp, tuple(uv), (cov, cov))
            )
    if args.images == "rendered":
        from tracker.vision.pair import PairSegmenter

        segmenter = PairSegmenter(
            catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds
        )
    print(
        f"{args.images} images: {args.pool} poses ({period_s:.1f} s of motion) prepared in"
        f" {time.perf_counter() - started:.1f} s; soaking for {args.seconds:g} s"
        f" ({args.joint_rate:g} Hz joints, {args.fps:g} fps pairs)",
        flush=True,
    )

    if args.tracemalloc:
        tracemalloc.start()
    stop = threading.Event()
    controller = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    controller.bind(("127.0.0.1", 0))
    controller.settimeout(0.0005)
    joints = JointReceiver(port=0, clock="aligned")
    start_s = time.monotonic() + 0.2
    estimates = []
    sent = [0]

    def run_controller() -> None:
        k = 0
        while not stop.is_set():
            now = time.monotonic()
            while start_s + k / args.joint_rate <= now:
                t = start_s + k / args.joint_rate
                controller.sendto(encode_joints(k, t, *joints_at(t - start_s)), joints.address)
                k += 1
            try:
                while True:
                    estimates.append(decode_estimate(controller.recv(256)))
            except (TimeoutError, BlockingIOError):
                pass
        sent[0] = k

    camera = Camera(pool, args.fps, start_s, stop)
    tracker = LiveTracker(
        Reconstructor(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
        make_estimator("ukf", catheter),
        [EstimateSender(controller.getsockname())],
        joints=joints,
        segmenter=segmenter,
    )
    memory = [(0.0, rss_mb())]
    threads = [threading.Thread(target=run_controller, daemon=True), camera.thread]
    for thread in threads:
        thread.start()
    timer = threading.Timer(args.seconds, stop.set)
    timer.start()

    def progress():
        last = time.monotonic()
        for item in camera:
            now = time.monotonic()
            if now - last >= max(10.0, args.seconds / 10):
                last = now
                memory.append((now - start_s, rss_mb()))
                s = tracker.summary
                print(
                    f"  {now - start_s:6.0f} s: {s.frames_processed} frames, {camera.dropped}"
                    f" dropped, RSS {memory[-1][1]:.1f} MB",
                    flush=True,
                )
            yield item

    summary = tracker.run(progress())
    timer.cancel()
    stop.set()
    for thread in threads:
        thread.join(5.0)
    controller.close()
    memory.append((time.monotonic() - start_s, rss_mb()))

    print(summary)
    print(
        f"camera: {camera.captured} pairs captured, {camera.dropped} dropped by the one-slot"
        f" buffer (loop too slow), {summary.frames_processed} processed; {camera.late} ticks"
        f" skipped because the camera thread itself woke up late"
    )
    print(f"controller: {sent[0]} joint datagrams sent, {len(estimates)} estimates received")
    valid = [m for m in estimates[len(estimates) // 10 :] if m.valid]
    if valid:
        err = np.degrees(wrap_angle(np.array([m.delta_L_rad for m in valid]) - DELTA_L_TRUE_RAD))
        lat = 1e3 * np.array([m.latency_s for m in estimates])
        print(
            f"delta_L error after the first 10 %: RMS {np.sqrt(np.mean(err**2)):.2f} deg,"
            f" max {np.max(np.abs(err)):.2f} deg; latency in the datagrams p50"
            f" {np.median(lat):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms"
        )
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    first = memory[1][1] if len(memory) > 2 else memory[0][1]
    print(
        f"memory: RSS {memory[0][1]:.1f} MB at start, {first:.1f} MB at the first report,"
        f" {memory[-1][1]:.1f} MB at the end, peak {peak_mb:.1f} MB (getrusage)"
    )
    if args.tracemalloc:
        current, peak = tracemalloc.get_traced_memory()
        print(f"tracemalloc: {current / 2**20:.2f} MB current, {peak / 2**20:.2f} MB peak")
    return 0


if __name__ == "__main__":
    sys.exit(main())
