"""Timing of the full-size sensitivity studies, and the least-squares baseline's agreement.

Run from the repository root: ``python benchmarks/bench_studies.py`` (prints only; no asserts).

- The three studies at full size (500 trials per point, both delta_2, every method: the
  per-frame closed forms, the UKF on the first ``--ukf-trials`` trials of every point (default
  all 500), and the bounds) on a local process pool. Target: <= 60 s on a 2-core machine, pool
  start-up included.
- The cost of one UKF step on one study task: ``run_ukf_batch`` (all trials
  of the task at once) against ``BendingPlaneUKF.step`` trial by trial on the same observations,
  and the largest difference of their final estimates.
- The paper's least-squares baseline (scipy ``least_squares`` from delta_L = 0) on a subsample
  of the same frames (the first ``--lsq-trials-per-point`` trials of every study point), and how
  often it agrees with the closed form (wrapped difference below 1e-3 rad).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
from _common import verdict  # noqa: E402,F401  (puts the repository on sys.path)

from replay.parallel import single_blas_thread  # noqa: E402
from replay.studies import (  # noqa: E402
    SensitivitySettings,
    Task,
    baseline_agreement,
    findings,
    make_tasks,
    run_sensitivity,
    simulate_task,
    study_points,
    ukf_errors,
)
from tracker.estimators.ukf import BendingPlaneUKF

TARGET_S = 60.0
AGREEMENT_TOLERANCE_RAD = 1e-3


def ukf_step_costs(settings: SensitivitySettings, looped_trials: int, repeats: int = 5) -> None:
    """us per filter step: batched over a task's trials against stepping BendingPlaneUKF."""
    point = next(p for p in study_points(settings) if p.study == "a" and p.noise_mm == 1.0)
    data = simulate_task(settings, Task(point, 0, 0, settings.trials))
    n, frames = data.points_b.shape[:2]
    with single_blas_thread():
        ukf_errors(data, "ukf", n)  # warm-up (imports, caches)
        started = time.perf_counter()
        for _ in range(repeats):
            batched = ukf_errors(data, "ukf", n)
        batched_us = (time.perf_counter() - started) / (repeats * n * frames) * 1e6
        observations = [data.observations(i) for i in range(looped_trials)]
        ukf = BendingPlaneUKF(data.catheter)
        looped = np.full(looped_trials, np.nan)
        started = time.perf_counter()
        for i, trial in enumerate(observations):
            ukf.reset()
            for observation in trial:
                estimate = ukf.step(observation)
            looped[i] = estimate.delta_L_rad
        looped_us = (time.perf_counter() - started) / (looped_trials * frames) * 1e6
    truth = data.delta_L_rad[:looped_trials]
    difference = np.abs((looped - truth - batched[:looped_trials] + np.pi) % (2 * np.pi) - np.pi)
    print(
        f"UKF step cost on one task (study a, 1 mm, delta_2 = {point.delta_2_deg:g} deg,"
        f" {frames} frames, one process, one BLAS thread):"
    )
    print(
        f"  run_ukf_batch over {n} trials       {batched_us:7.1f} us per step"
        f" ({batched_us * n * frames / 1e3:.1f} ms per task)"
    )
    print(
        f"  BendingPlaneUKF.step, {looped_trials} trials    {looped_us:7.1f} us per step"
        f" (observations built beforehand)   x {looped_us / batched_us:.0f}"
    )
    print(f"  largest |difference| of the final delta_L: {np.nanmax(difference):.1e} rad")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--ukf-trials", type=int, default=SensitivitySettings.ukf_trials)
    parser.add_argument("--lsq-trials-per-point", type=int, default=2)
    parser.add_argument(
        "--looped-ukf-trials",
        type=int,
        default=50,
        help="trials stepped through BendingPlaneUKF for the per-step comparison",
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    settings = SensitivitySettings(seed=args.seed, ukf_trials=args.ukf_trials)
    points = study_points(settings)
    tasks = make_tasks(settings, points)
    print(f"Python {platform.python_version()}, numpy {np.__version__}, {platform.machine()},")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"{os.cpu_count()} CPUs, {args.workers} workers, load average {load:.2f} before the run")
    print()
    print(
        f"Sensitivity studies a, b, c: {len(points)} study points, {len(tasks)} tasks,"
        f" {settings.trials} trials per point for the per-frame closed forms and the bound,"
        f" {settings.effective_ukf_trials} for the UKF ({settings.frames_per_trial} frames each),"
        f" seed {settings.seed}"
    )
    started = time.perf_counter()
    result = run_sensitivity(settings, workers=args.workers, progress=True)
    total = time.perf_counter() - started
    print(f"  total {total:.1f} s   target <= {TARGET_S:.0f} s   {verdict(total <= TARGET_S)}")
    held = [f for f in findings(result.rows) if f.holds is not None]
    print(f"  the paper's findings hold: {sum(f.holds for f in held)} of {len(held)}")
    for f in held:
        if not f.holds:
            print(f"    does not hold: {f.claim}")

    per_frame = SensitivitySettings(seed=args.seed, ukf_trials=0)
    started = time.perf_counter()
    run_sensitivity(per_frame, workers=args.workers, progress=False)
    print(
        f"  for context: the same without the UKF (closed forms and bounds only)"
        f" {time.perf_counter() - started:.1f} s"
    )
    print()

    ukf_step_costs(settings, args.looped_ukf_trials)
    print()

    n = args.lsq_trials_per_point
    print(
        f"Least-squares baseline vs closed form: first {n} trials of every study point,"
        f" {len(points) * n * 3} solves (3 estimators)"
    )
    started = time.perf_counter()
    rates = baseline_agreement(
        settings, trials_per_point=n, tolerance_rad=AGREEMENT_TOLERANCE_RAD, workers=args.workers
    )
    elapsed = time.perf_counter() - started
    for name in ("tip-position", "body-positions", "tip-velocity"):
        print(f"  {name:15s} agrees in {100 * rates[name]:.1f}% of trials")
    print(
        f"  all             agrees in {100 * rates['all']:.1f}% of {int(rates['trials'])} solves"
        f" (|wrapped difference| < {AGREEMENT_TOLERANCE_RAD:g} rad), {elapsed:.1f} s"
    )
    print(
        f"  away from the straight configuration (where every angle minimises the cost):"
        f" {100 * rates['bent']:.1f}%"
    )


if __name__ == "__main__":
    main()
