"""Replay throughput of recordings (prints only; no asserts).

Run from the repository root: ``python benchmarks/bench_replay.py [--quick] [--markers]
[--load N]`` (``--markers``: only the markers-only replay; ``--load N``: it again with N busy
processes).

- Markers only, through the UKF: a simulated paper-protocol recording (11 planes, joints at
  1 kHz) read, reconstructed and run through the UKF (``run``, as ``cathtrack evaluate``
  does). Target: >= 5,000 frames/s overall, also on a machine twice as slow (the rate
  halved is printed with its verdict). Every stage is also reported on its own: reading
  (MCAP scan, message decoding, joint interpolation; split into opening the recording and
  making the Frame objects), reconstruction (one batch), the UKF's run, and for comparison
  the live loop's frame-by-frame reconstruction and UKF step; medians of 5 runs. At 1 kHz each
  frame carries 50 joint samples of 7 numbers: in format version 2 (protobuf, 2.8 kB) they
  are taken from the bytes column by column; in version 1 (JSON, 6.7 kB) their decompression
  and parsing were about half of the reading time.
- With images, through segmentation and the UKF: image decoding, segmentation of both
  views, reconstruction and the UKF.
- The tables of ``cathtrack evaluate`` (replay_tables, median of 5 runs) on 5,000 and 50,000
  frames whose tip deflection and noise labels differ in every frame (binned into a few
  ranges): the time grows linearly with the frames.

Linear algebra runs on one BLAS thread, as in ``cathtrack evaluate`` (replay.parallel.
single_blas_thread): the matrices are tiny and BLAS threads only add contention.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import busy_processes, verdict  # noqa: E402,F401  (puts the repo on sys.path)

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig
from replay.evaluation import MethodResult, Replay, recording_scene, replay_tables  # noqa: E402
from replay.parallel import single_blas_thread  # noqa: E402
from replay.protocol import ProtocolSettings, simulate_protocol  # noqa: E402
from replay.simulation.simulator import default_scene
from tracker.estimators import make_estimator
from tracker.io.recording import FrameLabels, ReadReport, RecordedFrame, open_recording
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Frame

TARGET_FRAMES_PER_S = 5000.0
UKF_BUDGET_US = 1e6 / TARGET_FRAMES_PER_S


def _rate(frames: int, seconds: float) -> str:
    return f"{frames / seconds:10.0f} frames/s  ({1e6 * seconds / frames:7.1f} us/frame)"


def bench_markers(directory: Path, configurations: int, load: int = 0) -> None:
    settings = ProtocolSettings(images=False, configurations=configurations)
    path = directory / "markers.mcap"
    started = time.perf_counter()
    summary = simulate_protocol(settings, path, workers=1, progress=False)
    written_s = time.perf_counter() - started
    print(
        f"markers-only recording: {summary.frames} frames, {summary.joint_samples} joint"
        f" samples at 1 kHz, {summary.bytes / 1e6:.1f} MB (written in {written_s:.1f} s)"
    )

    def measure() -> None:
        runs: dict[str, list[float]] = {}
        for _ in range(5):
            cpu0, t0 = time.process_time(), time.perf_counter()
            with open_recording(path) as recording:
                t_open = time.perf_counter()
                frames = [r.frame for r in recording.frames(images=False)]
                t_frames = time.perf_counter()
                scene = recording_scene(recording)
            cpu1, t1 = time.process_time(), time.perf_counter()
            reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
            observations = reconstructor.observe_batch(frames)
            t2 = time.perf_counter()
            ukf = make_estimator("ukf", scene.catheter)
            ukf.run(observations)
            t3 = time.perf_counter()
            reconstructor.reset()
            for frame in frames:
                reconstructor.observe(frame)
            t4 = time.perf_counter()
            ukf = make_estimator("ukf", scene.catheter)
            for observation in observations:
                ukf.step(observation)
            t5 = time.perf_counter()
            for key, value in (
                ("read", t1 - t0),
                ("read_cpu", cpu1 - cpu0),
                ("open", t_open - t0),
                ("frames", t_frames - t_open),
                ("reconstruct", t2 - t1),
                ("ukf", t3 - t2),
                ("observe", t4 - t3),
                ("step", t5 - t4),
            ):
                runs.setdefault(key, []).append(value)
        # Medians: the machine is shared, and a best run hides how often a stage is slow.
        median = {key: statistics.median(values) for key, values in runs.items()}
        n = len(frames)
        total = median["read"] + median["reconstruct"] + median["ukf"]
        overhead = median["read"] + median["reconstruct"]
        print(f"  (medians of {len(runs['read'])} runs)")
        print(f"  read (scan, decode, interpolate) {_rate(n, median['read'])}")
        print(f"    open: MCAP, messages, joints   {_rate(n, median['open'])}")
        print(f"    frames: Frame objects          {_rate(n, median['frames'])}")
        # CPU time of this process: on a shared machine the wall time also counts the waits.
        print(f"    read, CPU time                 {_rate(n, median['read_cpu'])}")
        print(f"  reconstruction, one batch        {_rate(n, median['reconstruct'])}")
        print(f"  (live loop: frame by frame       {_rate(n, median['observe'])})")
        print(f"  UKF, one run of the recording    {_rate(n, median['ukf'])}")
        print(f"  (live loop: UKF step by step     {_rate(n, median['step'])})")
        passed = verdict(n / total >= TARGET_FRAMES_PER_S)
        print(
            f"  replay through the UKF           {_rate(n, total)}  target"
            f" {TARGET_FRAMES_PER_S:.0f}: {passed}"
        )
        # Margin: the same work on a machine of the class twice as slow.
        halved = verdict(n / (2 * total) >= TARGET_FRAMES_PER_S)
        print(f"  twice as slow a machine          {_rate(n, 2 * total)}  {halved}")
        ukf_us = 1e6 * median["ukf"] / n
        if ukf_us > UKF_BUDGET_US:
            print(
                f"  the UKF alone ({ukf_us:.0f} us) exceeds the {UKF_BUDGET_US:.0f} us"
                f" budget of the target; reading + reconstruction cost"
                f" {1e6 * overhead / n:.0f} us/frame ({n / overhead:.0f} frames/s without the UKF)"
            )

    measure()
    if load:
        with busy_processes(load):
            print(f"  with {load} busy processes:")
            measure()


def bench_images(directory: Path, configurations: int) -> None:
    from tracker.vision.pair import PairSegmenter

    settings = ProtocolSettings(
        images=True,
        planes=min(11, configurations),
        configurations=configurations,
        frames_per_configuration=20,
    )
    path = directory / "images.mcap"
    started = time.perf_counter()
    summary = simulate_protocol(settings, path, progress=False)
    print(
        f"recording with images: {summary.frames} frame pairs of 640x480, "
        f"{summary.bytes / 1e6:.0f} MB (written in {time.perf_counter() - started:.1f} s)"
    )
    t0 = time.perf_counter()
    with open_recording(path) as recording:
        scene = recording_scene(recording)
        segmenter = PairSegmenter(
            scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, recording.backgrounds
        )
        t_read = t_segment = 0.0
        frames = []
        t_last = time.perf_counter()
        for recorded in recording.frames(images=True):
            t_mid = time.perf_counter()
            f = recorded.frame
            frames.append(segmenter.segment(f.images).frame(f.time_s, f.q, f.q_dot))
            t_end = time.perf_counter()
            t_read += t_mid - t_last
            t_segment += t_end - t_mid
            t_last = t_end
    t1 = time.perf_counter()
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    observations = reconstructor.observe_batch(frames)
    make_estimator("ukf", scene.catheter).run(observations)
    t2 = time.perf_counter()
    n = len(frames)
    print(f"  read and decode both images      {_rate(n, t_read)}")
    print(f"  segmentation of both views       {_rate(n, t_segment)}")
    print(f"  reconstruction and UKF           {_rate(n, t2 - t1)}")
    print(f"  replay from images               {_rate(n, t2 - t0)}")


def _labelled_replay(n: int, rng: np.random.Generator) -> Replay:
    """n frames with their own deflection and noise labels, and two methods' estimates."""
    scene = default_scene(default_catheter(), default_orthographic_rig())
    points = np.zeros((1 + len(scene.catheter.marker_arclengths_mm), 2))
    covs = np.tile(np.eye(2), (points.shape[0], 1, 1))
    truth = rng.uniform(-np.pi, np.pi, n)
    deflection, noise = rng.uniform(0, 10, n), rng.uniform(0.1, 3, n)
    frames = [
        RecordedFrame(
            Frame(0.05 * i, np.zeros(3), None, (points, points), (covs, covs), None, truth[i]),
            FrameLabels(i % 11, i // 100, float(deflection[i]), float(noise[i])),
        )
        for i in range(n)
    ]
    results = {}
    for name in ("tip-position", "ukf"):
        delta = truth + 0.02 * rng.standard_normal(n)
        estimates = tuple(Estimate(0.05 * i, delta[i], 0.02, 0.0, nis=1.0) for i in range(n))
        results[name] = MethodResult(name, estimates, truth)
    return Replay(
        "labelled.mcap", "markers", scene, frames, [], results, np.full(n, 0.02), np.ones(n),
        ReadReport("labelled.mcap"), {},
    )  # fmt: skip


def bench_tables() -> None:
    rng = np.random.default_rng(0)
    for n in (5_000, 50_000):
        replay = _labelled_replay(n, rng)
        seconds = []
        for _ in range(5):
            t0 = time.perf_counter()
            tables = replay_tables(replay)
            seconds.append(time.perf_counter() - t0)
        groups = len({r["group"] for r in tables["deflection"]})
        print(
            f"tables of {n} frames with continuous labels ({groups} deflection groups):"
            f" median {1e3 * statistics.median(seconds):.1f} ms"
            f" ({1e6 * statistics.median(seconds) / n:.2f} us/frame)"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller recordings")
    parser.add_argument("--tables", action="store_true", help="only the tables benchmark")
    parser.add_argument("--markers", action="store_true", help="only the markers-only replay")
    parser.add_argument(
        "--load", type=int, default=0, metavar="N",
        help="time the markers-only replay again with N busy processes",
    )  # fmt: skip
    args = parser.parse_args()
    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    with tempfile.TemporaryDirectory() as tmp, single_blas_thread():
        if not args.markers:
            bench_tables()
        if args.tables:
            return
        directory = Path(tmp)
        bench_markers(directory, 22 if args.quick else 94, args.load)
        if args.markers:
            return
        bench_images(directory, 4 if args.quick else 11)


if __name__ == "__main__":
    main()
