"""Image-to-estimate latency of the live loop (prints only; no asserts).

Run from the repository root: ``python benchmarks/bench_latency.py [--frames N]``.

Two 640x480 rendered frames per step (replay.simulation.render, the default render rig), fed to
:class:`tracker.live.loop.LiveTracker` as they would come from two cameras: joint datagrams at
1 kHz over loopback UDP (33 per frame, drained by the loop), the UKF, and the estimate
datagram sent back over UDP. Latency is from the moment the image pair is handed to the loop
to the estimate being ready (the number sent in the estimate datagram), and to every sink
being done. Two runs:

- ``segmentation``: the images are segmented in the loop (tracker.vision.segmentation);
- ``markers``: the same points segmented beforehand and handed over as
  :class:`tracker.io.udp.SegmentedMarkers` (what an external segmenter sends).

Target: p99 <= 5 ms image -> estimate. The first 10 frames (UKF start) are left out.
"""

from __future__ import annotations

import argparse
import platform
import socket
import sys
import time

import numpy as np
from _common import verdict  # noqa: E402,F401  (puts the repository on sys.path)

from models.catheter import default_catheter  # noqa: E402
from models.rotations import wrap_angle  # noqa: E402
from replay.simulation.render import Renderer, default_render_rig
from replay.simulation.simulator import default_scene
from replay.simulation.sources import session_joints, simulated_session
from tracker.estimators import make_estimator
from tracker.io.datagrams import SegmentedMarkers, encode_joints
from tracker.io.udp import EstimateSender, JointReceiver
from tracker.live.loop import LiveTracker
from tracker.live.sources import ImageSet
from tracker.reconstruction import Reconstructor

TARGET_P99_MS = 5.0
FRAME_RATE_HZ = 30.0
JOINT_RATE_HZ = 1000
WARM_UP = 10


def percentiles_ms(values_s) -> tuple[float, float, float]:
    v = 1e3 * np.asarray(values_s)
    return float(np.median(v)), float(np.percentile(v, 99)), float(v.max())


def run(label, items, scene, truth, segmenter=None) -> None:
    """Feed items through a fresh loop; print the latency percentiles."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as controller:
        controller.bind(("127.0.0.1", 0))
        controller.setblocking(False)
        joints = JointReceiver(port=0, clock="sender")
        tracker = LiveTracker(
            Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm),
            make_estimator("ukf", scene.catheter),
            [EstimateSender(controller.getsockname())],
            joints=joints,
            segmenter=segmenter,
        )
        sample = 0
        latency, cycle, errors = [], [], []
        for k, item in enumerate(items):
            t = item[0] if isinstance(item, tuple) else item.time_s
            while sample / JOINT_RATE_HZ <= t + 0.001:  # the controller streams on meanwhile
                ts = sample / JOINT_RATE_HZ
                controller.sendto(encode_joints(sample, ts, *session_joints(ts)), joints.address)
                sample += 1
            handed = time.perf_counter()
            result = tracker.step(item, tracker.monotonic())
            done = time.perf_counter()
            try:
                while True:
                    controller.recv(256)
            except BlockingIOError:
                pass
            if k >= WARM_UP and result is not None:
                latency.append(result.latency_s)
                cycle.append(done - handed)
                errors.append(wrap_angle(result.estimate.delta_L_rad - truth[k]))
        tracker.close()
    p50, p99, worst = percentiles_ms(latency)
    c50, c99, _ = percentiles_ms(cycle)
    rms = float(np.degrees(np.sqrt(np.nanmean(np.square(errors)))))
    passed = verdict(p99 <= TARGET_P99_MS)
    print(
        f"{label:>13}: image -> estimate p50 {p50:6.2f} ms, p99 {p99:6.2f} ms (max {worst:6.2f})"
        f" [{passed} p99 <= {TARGET_P99_MS:g} ms]; -> sinks done p50 {c50:5.2f} ms,"
        f" p99 {c99:5.2f} ms; delta_L RMS error {rms:.2f} deg over {len(latency)} frames"
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="frames per run (300)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    catheter = default_catheter()
    scene = default_scene(catheter, default_render_rig())
    session = simulated_session(
        args.frames / FRAME_RATE_HZ, FRAME_RATE_HZ, noise=0.0, catheter=catheter, rig=scene.rig
    )
    renderer = Renderer(catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    started = time.perf_counter()
    pairs = [
        ImageSet(f.time_s, tuple(renderer.render(f.q, f.delta_L_true_rad, rng).images))
        for f in session.frames
    ]
    h, w = pairs[0].images[0].shape
    print(f"rendered {len(pairs)} pairs of {w}x{h} images in {time.perf_counter() - started:.1f} s")
    try:
        from tracker.vision.pair import PairSegmenter
    except ImportError:
        PairSegmenter = None
    truth = session.delta_L_true_rad
    if PairSegmenter is not None:
        segmenter = PairSegmenter(
            catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds
        )
        run("segmentation", pairs, scene, truth, segmenter)
        markers = []
        for i, pair in enumerate(pairs):
            seg = segmenter.segment(pair.images)
            markers.append(SegmentedMarkers(pair.time_s, tuple(seg.uv), tuple(seg.cov), i))
        source = "segmented beforehand"
    else:
        print("tracker.vision.segmentation is not available: markers only (true points + 0.5 px)")
        cov = np.tile(0.25 * np.eye(2), (3, 1, 1))
        markers = [
            SegmentedMarkers(
                f.time_s, tuple(renderer.render(f.q, f.delta_L_true_rad, rng).points_px),
                (cov, cov), i
            )
            for i, f in enumerate(session.frames)
        ]
        source = "true projections"
    print(f"markers: {source}")
    run("markers", markers, scene, truth)
    return 0


if __name__ == "__main__":
    sys.exit(main())
