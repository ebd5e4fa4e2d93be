"""Timing of the catheter model's hot paths (prints only; no asserts).

Run from the repository root: ``python benchmarks/bench_models.py``.

- Batched direct kinematics: ``Catheter.tip`` for 100,000 configurations in one call
  (the sensitivity studies and the simulator). Target: >= 1,000,000 configurations/s.
- Per-frame cost: ``Catheter.shape_vectors(q, q_dot)`` for one configuration (what the
  tracker calls once per frame). Target: <= 20 us median.
"""

from __future__ import annotations

import platform
import time

import numpy as np
from _common import verdict  # noqa: E402,F401  (puts the repository on sys.path)
from threadpoolctl import threadpool_info

from models.catheter import default_catheter  # noqa: E402

N_BATCH = 100_000
BATCH_REPEATS = 15
TARGET_BATCH_PER_S = 1_000_000.0
SINGLE_REPEATS = 20_000
TARGET_SINGLE_US = 20.0


def blas_threads() -> str:
    """Threads used by numpy's BLAS."""
    pools = [p for p in threadpool_info() if p.get("user_api") == "blas"]
    if not pools:
        return "no BLAS pool found"
    return ", ".join(f"{p['internal_api']}: {p['num_threads']}" for p in pools)


def bench_batched_tip(rng: np.random.Generator) -> None:
    catheter = default_catheter()
    q = np.column_stack(
        [
            rng.uniform(-np.pi, np.pi, N_BATCH),
            rng.uniform(-1.0, 1.0, N_BATCH),
            rng.uniform(-1.0, 1.0, N_BATCH),
        ]
    )
    delta_L = rng.uniform(-np.pi, np.pi, N_BATCH)
    catheter.tip(q, delta_L)  # warm-up: builds the quadrature plan
    seconds = np.empty(BATCH_REPEATS)
    for i in range(BATCH_REPEATS):
        start = time.perf_counter()
        catheter.tip(q, delta_L)
        seconds[i] = time.perf_counter() - start
    median, p99 = np.median(seconds), np.percentile(seconds, 99)
    rate = N_BATCH / median
    print(f"Catheter.tip, {N_BATCH:,} configurations per call, {BATCH_REPEATS} calls")
    print(f"  median {median:.4f} s   p99 {p99:.4f} s")
    print(
        f"  {rate:,.0f} configurations/s   target >= {TARGET_BATCH_PER_S:,.0f}/s"
        f"   {verdict(rate >= TARGET_BATCH_PER_S)}"
    )


def bench_single(label: str, call) -> float:
    call()  # warm-up
    ns = np.empty(SINGLE_REPEATS, dtype=np.int64)
    for i in range(SINGLE_REPEATS):
        start = time.perf_counter_ns()
        call()
        ns[i] = time.perf_counter_ns() - start
    median_us, p99_us = np.median(ns) / 1e3, np.percentile(ns, 99) / 1e3
    print(f"{label}, one configuration, {SINGLE_REPEATS:,} calls")
    print(
        f"  median {median_us:.1f} us   p99 {p99_us:.1f} us   target <= {TARGET_SINGLE_US:.0f} us"
        f"   {verdict(median_us <= TARGET_SINGLE_US)}"
    )
    return median_us


def main() -> None:
    print(f"Python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    print(f"BLAS threads: {blas_threads()}")
    print()
    rng = np.random.default_rng(0)
    bench_batched_tip(rng)
    print()
    catheter = default_catheter()
    q = np.array([0.3, 0.6, -0.4])
    q_dot = np.array([0.5, 0.2, -0.1])
    bench_single("Catheter.shape_vectors(q, q_dot)", lambda: catheter.shape_vectors(q, q_dot))
    print()
    print("For context (no targets):")
    for label, call in (
        ("Catheter.shape_vectors(q)", lambda: catheter.shape_vectors(q)),
        ("Catheter.tip(q, delta_L)", lambda: catheter.tip(q, 0.2)),
        ("Catheter.tip_twist(q, q_dot, delta_L)", lambda: catheter.tip_twist(q, q_dot, 0.2)),
    ):
        call()
        ns = np.empty(2_000, dtype=np.int64)
        for i in range(ns.size):
            start = time.perf_counter_ns()
            call()
            ns[i] = time.perf_counter_ns() - start
        print(f"  {label}: median {np.median(ns) / 1e3:.1f} us")


if __name__ == "__main__":
    main()
