"""Timing of the segmentation of rendered 640 x 480 frames (prints only; no asserts).

Run from the repository root: ``python benchmarks/bench_segmentation.py [--frames 500]``.

- One frame: ``Segmenter.segment`` of one view against its empty-scene prior.
- A synchronised pair: ``PairSegmenter.segment`` (both views, the epipolar check and the
  tip placed from both views), i.e. everything between the cameras and a pipeline Frame.

Single thread (OpenCV and BLAS), median and 99th percentile over rendered frames of bent
configurations at the default rendering rig. Target: the pair in at most 3 ms median (the
cameras run at 20 frames per second: ten times faster, with room to spare).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from _common import verdict  # noqa: E402,F401  (puts the repository on sys.path)

from models.catheter import default_catheter  # noqa: E402
from replay.simulation.render import Renderer, default_render_rig  # noqa: E402
from tracker.vision.segmentation import PairSegmenter  # noqa: E402

TARGET_PAIR_MS = 3.0
DISTINCT_FRAMES = 50
BASE_W = np.array([0.0, 0.0, -15.0])


def percentiles_ms(times_s: list[float]) -> tuple[float, float]:
    t = np.asarray(times_s) * 1e3
    return float(np.median(t)), float(np.percentile(t, 99))


def timed(function, *args) -> tuple[float, float]:
    """Wall-clock and this thread's CPU time of one call, s (CPU time leaves out the time
    the thread waited for a core, which matters on a loaded machine)."""
    w0, c0 = time.perf_counter(), time.thread_time()
    function(*args)
    return time.perf_counter() - w0, time.thread_time() - c0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500, help="timed frames (default 500)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    catheter = default_catheter()
    rig = default_render_rig()
    renderer = Renderer(catheter, rig, np.eye(3), BASE_W, seed=args.seed)
    segmenter = PairSegmenter(catheter, rig, np.eye(3), BASE_W, renderer.backgrounds)
    rng = np.random.default_rng(args.seed)
    pairs = []
    for _ in range(DISTINCT_FRAMES):
        q = np.array([rng.uniform(-np.pi, np.pi), rng.uniform(-1, 1), rng.uniform(-1, 1)])
        pairs.append(renderer.render(q, rng.uniform(-np.pi, np.pi), rng).images)
    view = segmenter.segmenter
    background, base_px = segmenter.backgrounds[0], segmenter.base_px[0]
    for images in pairs[:10]:  # warm-up
        segmenter.segment(images)
    single = [timed(view.segment, pairs[k % DISTINCT_FRAMES][0], background, base_px)
              for k in range(args.frames)]
    pair = [timed(segmenter.segment, pairs[k % DISTINCT_FRAMES]) for k in range(args.frames)]
    print(f"python {platform.python_version()}, numpy {np.__version__}, opencv {cv2.__version__},"
          f" cv2 threads {cv2.getNumThreads()}, {platform.machine()}, load average"
          f" {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    print(f"{args.frames} frames ({DISTINCT_FRAMES} distinct) of 640x480 at the default"
          " rendering rig (f = 2500 px at 400 mm); wall clock / thread CPU time")
    for label, times in (("one frame", single), ("pair     ", pair)):
        wall_med, wall_p99 = percentiles_ms([t[0] for t in times])
        cpu_med, cpu_p99 = percentiles_ms([t[1] for t in times])
        line = (f"  {label}: median {wall_med:.2f} / {cpu_med:.2f} ms,"
                f" p99 {wall_p99:.2f} / {cpu_p99:.2f} ms")
        if label.startswith("pair"):
            verdict = "PASS" if cpu_med <= TARGET_PAIR_MS else "MISS"
            line += f"  (target CPU median <= {TARGET_PAIR_MS:.0f} ms on one core: {verdict})"
        print(line)


if __name__ == "__main__":
    main()
