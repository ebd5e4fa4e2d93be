"""Per-frame cost of the estimators (prints only; no asserts).

Run from the repository root: ``python benchmarks/bench_estimators.py``.

- Tip Position, closed form: ``PerFrameEstimator("tip", "closed-form").step``.
- Tip Position, the paper's least-squares baseline ("tip-position-lsq").
- One full UKF step: shape vectors, predict and one fused update of the tip, both markers and
  the tip velocity (with its cross-covariance). A finite-difference velocity is redundant once
  the previous tip has been fused, so the default filter leaves it out
  (``velocity_is_finite_difference``); to time the full fused update this run declares the
  velocity independent, so it is fused in every frame. The default pipeline step (velocity
  left out) is printed for context.

Every step consumes a different frame of a simulated sequence (moving joints, 1 mm noise),
measured in the same run. Targets: UKF step median <= 150 us; baseline / UKF >= 10.
"""

from __future__ import annotations

import platform
import time

import numpy as np
from _common import verdict  # noqa: E402,F401  (puts the repository on sys.path)

from models.catheter import default_catheter  # noqa: E402
from models.rotations import rotate_z  # noqa: E402
from tracker.estimators import make_estimator
from tracker.estimators.ukf import BendingPlaneUKF, UKFSettings
from tracker.types import Observation, velocity_from_positions

N_FRAMES = 20_000
N_BASELINE = 2_000
DT_S = 0.04
TARGET_UKF_US = 150.0
TARGET_RATIO = 10.0


def frames(n: int, rng: np.random.Generator, catheter, independent_velocity: bool):
    """A sequence of frames: tip, markers and velocity in {B}, 1 mm noise (0.7 mm along z)."""
    t = np.arange(n) * DT_S
    q_dot = np.array([0.4, 0.3, -0.2])
    q = np.column_stack(
        [
            0.3 + q_dot[0] * t,
            0.6 + 0.3 * np.sin(q_dot[1] * t),
            -0.4 + 0.3 * np.sin(q_dot[2] * t),
        ]
    )
    q_dots = np.column_stack(
        [
            np.full(n, q_dot[0]),
            0.3 * q_dot[1] * np.cos(q_dot[1] * t),
            0.3 * q_dot[2] * np.cos(q_dot[2] * t),
        ]
    )
    delta_L = 1.0 + 0.05 * np.sin(0.1 * t)
    shape = catheter.shape_vectors(q, q_dots)
    angle = q[:, 0] + delta_L
    cov = np.diag([1.0, 1.0, 0.5])
    n_markers = shape.c_markers_mm.shape[1]
    tips = rotate_z(shape.c_tip_mm, angle) + rng.multivariate_normal(np.zeros(3), cov, n)
    markers = rotate_z(shape.c_markers_mm, angle[:, None]) + rng.multivariate_normal(
        np.zeros(3), cov, (n, n_markers)
    )
    velocities = rotate_z(shape.u_tip_mm_s, angle)
    marker_cov = np.broadcast_to(cov, (n_markers, 3, 3)).copy()
    out = []
    for k in range(n):
        if independent_velocity:
            v = velocities[k] + rng.multivariate_normal(np.zeros(3), cov) / DT_S
            velocity = dict(velocity_b_mm_s=v, velocity_cov_b=cov / DT_S**2)
        else:
            v, v_cov, v_tip = velocity_from_positions(tips[k], cov, tips[k - 1], cov, DT_S)
            velocity = dict(velocity_b_mm_s=v, velocity_cov_b=v_cov, velocity_tip_cov_b=v_tip)
        out.append(
            Observation(
                time_s=k * DT_S,
                q=q[k],
                q_dot=q_dots[k],
                tip_b_mm=tips[k],
                tip_cov_b=cov,
                markers_b_mm=markers[k],
                markers_cov_b=marker_cov,
                **velocity,
            )
        )
    return out


def time_steps(step, observations) -> np.ndarray:
    """Microseconds of each call of ``step`` on consecutive frames."""
    step(observations[0])  # warm-up (plans, caches)
    ns = np.empty(len(observations) - 1, dtype=np.int64)
    for i, observation in enumerate(observations[1:]):
        start = time.perf_counter_ns()
        step(observation)
        ns[i] = time.perf_counter_ns() - start
    return ns / 1e3


def report(label: str, us: np.ndarray) -> float:
    median = float(np.median(us))
    print(f"{label}, {us.size:,} frames")
    print(f"  median {median:.1f} us   p99 {np.percentile(us, 99):.1f} us")
    return median


def main() -> None:
    print(f"Python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    print()
    rng = np.random.default_rng(0)
    catheter = default_catheter()
    sequence = frames(N_FRAMES, rng, catheter, independent_velocity=True)

    closed = make_estimator("tip-position", catheter)
    report("Tip Position, closed form", time_steps(closed.step, sequence))
    baseline = make_estimator("tip-position-lsq", catheter)
    baseline_us = report(
        "Tip Position, least-squares baseline", time_steps(baseline.step, sequence[:N_BASELINE])
    )

    fused = BendingPlaneUKF(catheter, UKFSettings(velocity_is_finite_difference=False))
    ukf_us = time_steps(fused.step, sequence)
    ukf_median = report(
        "UKF step: shape vectors + predict + update of tip, markers, velocity", ukf_us
    )
    shape_us = time_steps(lambda o: catheter.shape_vectors(o.q, o.q_dot), sequence)
    print(f"  of which Catheter.shape_vectors(q, q_dot): median {np.median(shape_us):.1f} us")
    print(f"  target median <= {TARGET_UKF_US:.0f} us   {verdict(ukf_median <= TARGET_UKF_US)}")
    ratio = baseline_us / ukf_median
    print(
        f"Baseline / UKF step (medians, this run): {ratio:.1f}   target >= {TARGET_RATIO:.0f}"
        f"   {verdict(ratio >= TARGET_RATIO)}"
    )
    print()
    print("For context (no target):")
    pipeline = frames(N_FRAMES, np.random.default_rng(1), catheter, independent_velocity=False)
    default = BendingPlaneUKF(catheter)
    us = time_steps(default.step, pipeline)
    print(
        "  UKF step, default settings, finite-difference velocity (left out as redundant):"
        f" median {np.median(us):.1f} us   p99 {np.percentile(us, 99):.1f} us"
    )


if __name__ == "__main__":
    main()
