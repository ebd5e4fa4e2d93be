"""Timing of the segmentation of rendered 640 x 480 frames (prints only; no asserts).

Run from the repository root: ``python benchmarks/bench_segmentation.py [--frames 500]
[--load N]``.

Frames of a catheter moving smoothly through random bent configurations (a sequence as a
camera delivers it at 20 fps), segmented as synchronised pairs by
:class:`tracker.vision.pair.PairSegmenter` (both views, the epipolar check and the tip placed
from both views: everything between the cameras and a pipeline Frame) in four set-ups, each
with its own segmenter, timed in turn on every frame of the same run:

- plain: no photometric normalisation, a frozen background, the whole image searched (the
  photometry of the segmentation before issue 15, with today's detection);
- normalised: each frame's tone curve fitted to its background, the background model
  updated (a stripe of rows every other frame per camera), the whole image searched: the
  defaults without the region of interest;
- ROI, last frame: the defaults: the search starts around the last frame's catheter;
- ROI, predicted: the search starts around predicted points (here the true points of the
  frame, as the last estimate reprojected would give them).

Single thread (OpenCV and BLAS), median and 99th percentile of the wall clock and of the
thread's CPU time, and the ratio of the CPU medians to the plain path. Target: a pair in at
most 3 ms median with normalisation and the background update on (the cameras run at 20
frames per second: ten times faster, with room to spare). The 99th percentile counts as
much: the live loop's budget (issue 12) is image -> estimate within 5 ms at the 99th
percentile, so no step may put a burst of work on one frame in a cycle (the background
model's upkeep is spread over its stripes). ``--load N`` starts N busy processes for the
duration of the timing, to see the cost on a loaded machine.

Also the time the compiled kernels (:mod:`tracker.vision.kernels`) take to be ready before
the first frame: loaded from numba's cache, or compiled on a first run (a few seconds; the
segmenters do it when they are made, never on a frame).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import multiprocessing  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402
from _common import verdict  # noqa: E402  (puts the repository on sys.path)

from models.catheter import default_catheter  # noqa: E402
from replay.simulation.render import Renderer, default_render_rig  # noqa: E402
from tracker.vision import kernels  # noqa: E402
from tracker.vision.pair import PairSegmenter  # noqa: E402
from tracker.vision.settings import DEFAULT_SETTINGS  # noqa: E402

TARGET_PAIR_MS = 3.0
DISTINCT_FRAMES = 60
BASE_W = np.array([0.0, 0.0, -15.0])

SETUPS = {
    "plain": dataclasses.replace(
        DEFAULT_SETTINGS, normalise=False, freeze_background=True, roi_pad_px=0.0
    ),
    "normalised": dataclasses.replace(DEFAULT_SETTINGS, roi_pad_px=0.0),
    "ROI, last frame": DEFAULT_SETTINGS,
    "ROI, predicted": DEFAULT_SETTINGS,
}


def percentiles_ms(times_s: list[float]) -> tuple[float, float]:
    t = np.asarray(times_s) * 1e3
    return float(np.median(t)), float(np.percentile(t, 99))


def timed(function, *args) -> tuple[float, float]:
    """Wall-clock and this thread's CPU time of one call, s (CPU time leaves out the time
    the thread waited for a core, which matters on a loaded machine)."""
    w0, c0 = time.perf_counter(), time.thread_time()
    function(*args)
    return time.perf_counter() - w0, time.thread_time() - c0


def _busy(stop) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


def smooth_sequence(renderer: Renderer, n: int, seed: int, waypoints: int = 5) -> list:
    """Rendered pairs of a catheter moving smoothly through random bent configurations (the
    benchmark's frames before: uniform q_r, q_p, q_d and delta_L), looping back to the first."""
    rng = np.random.default_rng(seed)
    q = np.column_stack([rng.uniform(-np.pi, np.pi, waypoints), rng.uniform(-1, 1, waypoints),
                         rng.uniform(-1, 1, waypoints)])
    delta_L = rng.uniform(-np.pi, np.pi, waypoints)
    per = n // waypoints
    pairs = []
    for k in range(waypoints):
        j = (k + 1) % waypoints
        for a in 0.5 - 0.5 * np.cos(np.pi * np.arange(per) / per):
            pairs.append(renderer.render(q[k] + a * (q[j] - q[k]),
                                         delta_L[k] + a * (delta_L[j] - delta_L[k]), rng))
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500, help="timed pairs per set-up (500)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--load", type=int, default=0, metavar="N", help="busy processes during the timing (0)"
    )
    args = parser.parse_args()
    cv2.setNumThreads(1)
    start = time.perf_counter()
    kernels.warm_up()
    warm_up_ms = 1e3 * (time.perf_counter() - start)
    catheter = default_catheter()
    rig = default_render_rig()
    renderer = Renderer(catheter, rig, np.eye(3), BASE_W, seed=args.seed)
    pairs = smooth_sequence(renderer, DISTINCT_FRAMES, args.seed)
    stop = multiprocessing.Event()
    hogs = [multiprocessing.Process(target=_busy, args=(stop,), daemon=True)
            for _ in range(args.load)]
    for hog in hogs:
        hog.start()
    try:
        segmenters = {
            name: PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds, settings)
            for name, settings in SETUPS.items()
        }
        times = {name: [] for name in SETUPS}
        # Round robin over the set-ups, frame by frame: a change of the machine's load
        # touches them all alike.
        for k in range(-10, args.frames):  # 10 frames of warm-up
            pair = pairs[k % len(pairs)]
            for name, segmenter in segmenters.items():
                predicted = pair.points_px if name == "ROI, predicted" else None
                t = timed(segmenter.segment, pair.images, predicted)
                if k >= 0:
                    times[name].append(t)
        view = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds).cameras[0]
        single = [timed(view.segment, pairs[k % len(pairs)].images[0])
                  for k in range(args.frames)]
    finally:
        stop.set()
        for hog in hogs:
            hog.join()
    print(f"python {platform.python_version()}, numpy {np.__version__}, opencv {cv2.__version__},"
          f" cv2 threads {cv2.getNumThreads()}, {platform.machine()}, load average"
          f" {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs, {args.load} busy processes")
    print(f"compiled kernels ready in {warm_up_ms:.0f} ms before the first frame (numba"
          f" {numba.__version__}; loaded from its cache, or compiled on a first run)")
    print(f"{args.frames} pairs per set-up ({len(pairs)} distinct, a smooth motion) of 640x480"
          " at the default rendering rig (f = 2500 px at 400 mm); wall clock / thread CPU time")
    wall, cpu = percentiles_ms([t[0] for t in single]), percentiles_ms([t[1] for t in single])
    print(f"  one view (defaults)   : median {wall[0]:.2f} / {cpu[0]:.2f} ms,"
          f" p99 {wall[1]:.2f} / {cpu[1]:.2f} ms")
    plain_cpu = percentiles_ms([t[1] for t in times["plain"]])[0]
    for name, values in times.items():
        wall = percentiles_ms([t[0] for t in values])
        cpu = percentiles_ms([t[1] for t in values])
        line = (f"  pair, {name:<15}: median {wall[0]:.2f} / {cpu[0]:.2f} ms,"
                f" p99 {wall[1]:.2f} / {cpu[1]:.2f} ms, {cpu[0] / plain_cpu:.2f} x plain")
        if name == "normalised":
            line += (f"  (target CPU median <= {TARGET_PAIR_MS:.0f} ms on one core:"
                     f" {verdict(cpu[0] <= TARGET_PAIR_MS)})")
        print(line)
    # The region of interest saves the search of the whole image; the catheter's own pixels,
    # the photometric fit and the cross-view steps cost the same in both.
    whole = percentiles_ms([t[1] for t in times["normalised"]])[0]
    last, predicted = (whole - percentiles_ms([t[1] for t in times[name]])[0]
                       for name in ("ROI, last frame", "ROI, predicted"))
    print(f"  region of interest saves, over the whole image (normalised): {last:.2f} ms per"
          f" pair around the last frame's catheter, {predicted:.2f} ms around predicted points")


if __name__ == "__main__":
    main()
