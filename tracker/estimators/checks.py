"""Input checks of every estimator: a bad observation is a flagged, skipped step.

What reaches an estimator through :func:`tracker.estimators.make_estimator` is checked here,
once for all of them, before the estimator sees it:

- time: finite; for the filters (which carry a state over time) also later than the last
  accepted observation and at most :data:`MAX_TIME_STEP_S` after it. An observation that
  fails is skipped; when :data:`CLOCK_RESTART_FRAMES` skipped observations in a row agree
  among themselves (increasing, plausible steps), the clock has restarted: the estimator is
  reset and goes on from them.
- joint values and rates: finite and within the robot's ranges (:mod:`tracker.io.limits`).
- points: the tip, the markers (of the catheter's count), the velocity and single-view points:
  finite where present (NaN rows mean "not found") and within physical ranges.
- covariances of the points present: symmetric, positive definite, every variance between
  :data:`MIN_VARIANCE_MM2` and :data:`MAX_VARIANCE_MM2` (image points: the cameras' limits).

A skipped step of a filter returns the last estimate held, flagged ``INVALID_INPUT | HELD |
NO_MEASUREMENT`` (NaN before the first estimate; a per-frame estimator gives NaN): the
estimator's state is untouched, so the steps after it are those it would have made had the
bad observation never come. Covariance
``tip_cov_b = 1e-30 I`` (a collapsed filter), ``1e300`` values, an observation stamped a
billion seconds ahead: all are such skipped steps. Estimators built directly (e.g.
``BendingPlaneUKF(...)``) are not wrapped and raise on what they cannot use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tracker.io.limits import (
    JOINT_RATE_LIMITS,
    JOINT_VALUE_LIMITS,
    MAX_IMAGE_COORDINATE,
    MAX_POINT_SIGMA,
)
from tracker.types import Estimate, Flag, Observation

Array = np.ndarray

MAX_POINT_MM = 1e3
"""|coordinate| of a reconstructed point in {B}, mm: the catheter is a few centimetres long."""
MAX_SPEED_MM_S = 1e5
"""|tip velocity|, mm/s."""
MIN_VARIANCE_MM2 = 1e-16
"""Smallest variance of a reconstructed point, mm^2 (a std of 10 nm): below it the filter would
take the point as exact and collapse."""
MAX_VARIANCE_MM2 = 1e6
"""Largest variance of a reconstructed point or velocity component, mm^2 (a std of 1 m)."""
MAX_TIME_STEP_S = 3600.0
"""Longest plausible interval between two observations, s."""
CLOCK_RESTART_FRAMES = 5
"""Skipped observations in a row, consistent among themselves, that make a restarted clock."""
SKIPPED = Flag.INVALID_INPUT | Flag.HELD | Flag.NO_MEASUREMENT
_JOINT_VALUE_LIMITS = tuple(float(x) for x in JOINT_VALUE_LIMITS)
_JOINT_RATE_LIMITS = tuple(float(x) for x in JOINT_RATE_LIMITS)


def _symmetric_in_range(cov: Array, low: float, high: float) -> bool:
    """Symmetric, ``cov - low I`` positive definite (Sylvester's criterion for 2x2 and 3x3, in
    plain floats: this runs on every step) and every variance at most ``high``."""
    if cov is None:
        return False
    try:
        c = np.asarray(cov, dtype=float)
    except (TypeError, ValueError):
        return False
    if c.shape == (3, 3):
        return _symmetric_in_range_3(c.tolist(), low, high)
    if c.shape == (2, 2):
        return _symmetric_in_range_2(c.tolist(), low, high)
    return False


def _symmetric_in_range_3(rows: list, low: float, high: float) -> bool:
    """:func:`_symmetric_in_range` of a 3x3 matrix given as nested Python floats."""
    (a, b, c, d, e, f, g, h, i) = rows[0] + rows[1] + rows[2]
    if not math.isfinite(a + b + c + d + e + f + g + h + i):  # a NaN or an infinity
        return False
    tol = 1e-9 * max(abs(a), abs(e), abs(i), 1e-300)
    if abs(b - d) > tol or abs(c - g) > tol or abs(f - h) > tol or max(a, e, i) > high:
        return False
    a, e, i = a - low, e - low, i - low
    minor = a * e - b * b
    return a > 0.0 and minor > 0.0 and a * (e * i - f * f) - b * (b * i - f * c) + c * (
        b * f - e * c
    ) > 0.0


def _symmetric_in_range_2(rows: list, low: float, high: float) -> bool:
    """:func:`_symmetric_in_range` of a 2x2 matrix given as nested Python floats."""
    (a, b), (d, e) = rows
    if not math.isfinite(a + b + d + e):
        return False
    tol = 1e-9 * max(abs(a), abs(e), 1e-300)
    if abs(b - d) > tol or max(a, e) > high:
        return False
    return a - low > 0.0 and (a - low) * (e - low) - b * b > 0.0


def _positive_definite(a: Array) -> bool:
    if not np.all(np.isfinite(a)) or not np.allclose(a, a.T, rtol=1e-9, atol=0.0):
        return False
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        return False
    return True


def _points(points: Array | None, shape: tuple[int, ...], limit: float) -> list[bool] | None:
    """Which rows of points are present (finite), or None when the array is unusable: wrong
    shape, a row partly NaN, an infinity, or a coordinate beyond ``limit``. Plain floats: this
    runs on every step."""
    points = np.asarray(points, dtype=float)
    if points.shape != shape:
        return None
    rows = points.tolist()
    present = []
    for row in rows if points.ndim == 2 else (rows,):
        if math.isfinite(sum(row)):
            if max(map(abs, row)) > limit:
                return None
            present.append(True)
        elif all(map(math.isnan, row)):
            present.append(False)
        else:  # partly missing, or an infinity
            return None
    return present


def _within(values, limits) -> bool:
    """Finite values, each within its limit."""
    for x, limit in zip(values, limits, strict=True):
        if not (math.isfinite(x) and abs(x) <= limit):
            return False
    return True


def observation_problem(observation: Observation, n_markers: int) -> str | None:
    """Why ``observation`` cannot be used (one phrase), or None when it can (times aside)."""
    o = observation
    q = np.asarray(o.q, dtype=float)
    if q.shape != (3,) or not _within(q.tolist(), _JOINT_VALUE_LIMITS):
        return "joint values missing, not finite or beyond the robot's ranges"
    if o.q_dot is not None:
        q_dot = np.asarray(o.q_dot, dtype=float)
        if q_dot.shape != (3,) or not _within(q_dot.tolist(), _JOINT_RATE_LIMITS):
            return "joint rates not finite or beyond the robot's ranges"
    if o.tip_b_mm is not None:
        present = _points(o.tip_b_mm, (3,), MAX_POINT_MM)
        if present is None:
            return "tip not finite or beyond the catheter's reach"
        if present[0] and not _symmetric_in_range(
            o.tip_cov_b,
            MIN_VARIANCE_MM2,
            MAX_VARIANCE_MM2,
        ):
            return "tip covariance not positive definite or out of range"
    if o.markers_b_mm is not None:
        present = _points(o.markers_b_mm, (n_markers, 3), MAX_POINT_MM)
        if present is None:
            return f"markers not {n_markers} finite points within the catheter's reach"
        if any(present):
            cov = np.asarray(o.markers_cov_b if o.markers_cov_b is not None else np.nan, float)
            if cov.shape == (n_markers, 3, 3):
                ok = all(
                    _symmetric_in_range_3(block, MIN_VARIANCE_MM2, MAX_VARIANCE_MM2)
                    for block, found in zip(cov.tolist(), present, strict=True)
                    if found
                )
            elif cov.shape == (3 * n_markers, 3 * n_markers):
                rows = np.repeat(present, 3)
                joint = cov[np.ix_(rows, rows)]
                if joint.shape[-1] == 3:  # one marker: its block
                    ok = _symmetric_in_range_3(joint.tolist(), MIN_VARIANCE_MM2, MAX_VARIANCE_MM2)
                else:  # the joint covariance of several markers
                    ok = np.all(np.diag(joint) <= MAX_VARIANCE_MM2) and _positive_definite(
                        joint - MIN_VARIANCE_MM2 * np.eye(joint.shape[-1])
                    )
            else:
                return f"marker covariance of shape {cov.shape}"
            if not ok:
                return "marker covariance not positive definite or out of range"
    if o.velocity_b_mm_s is not None:
        present = _points(o.velocity_b_mm_s, (3,), MAX_SPEED_MM_S)
        if present is None or (
            present[0]
            and not _symmetric_in_range(
                o.velocity_cov_b,
                MIN_VARIANCE_MM2,
                MAX_VARIANCE_MM2,
            )
        ):
            return "velocity or its covariance unusable"
        cross = o.velocity_tip_cov_b
        if cross is not None and not all(map(math.isfinite, np.asarray(cross).ravel().tolist())):
            return "velocity-tip cross-covariance not finite"
    for view in o.views:
        uv = np.asarray(view.uv, dtype=float)
        cov = np.asarray(view.cov, dtype=float)
        if (
            uv.ndim != 2
            or uv.shape[-1] != 2
            or cov.shape != uv.shape[:1] + (2, 2)
            or not np.all(np.isfinite(uv))
            or np.any(np.abs(uv) > MAX_IMAGE_COORDINATE)
            or not all(
                _symmetric_in_range_2(c, MIN_VARIANCE_MM2, MAX_POINT_SIGMA**2)
                for c in cov.tolist()
            )
        ):
            return "single-view points or covariances unusable"
    return None


@dataclass
class CheckedEstimator:
    """An estimator behind the input checks (what :func:`make_estimator` returns).

    Attributes other than ``step``, ``reset`` and ``skipped`` are the wrapped estimator's
    (``name``, ``settings``, ...); ``inner`` is the estimator itself.
    """

    inner: object
    n_markers: int
    check_time: bool = True

    def __post_init__(self) -> None:
        self.skipped: dict[str, int] = {}
        self._reset_state()

    def _reset_state(self) -> None:
        self._last_time_s: float | None = None
        self._last: Estimate | None = None
        self._rejected_times: list[float] = []

    def __getattr__(self, name: str):
        return getattr(self.inner, name)

    def reset(self) -> None:
        self.inner.reset()
        self._reset_state()

    def _skip(self, observation: Observation, reason: str) -> Estimate:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        last = self._last
        t = float(observation.time_s) if math.isfinite(observation.time_s) else math.nan
        q_r = np.asarray(observation.q, dtype=float).reshape(-1)[:1]
        q_r = float(q_r[0]) if q_r.size and math.isfinite(q_r[0]) and abs(q_r[0]) < 1e3 else None
        if last is None:
            return Estimate(t, math.nan, math.nan, math.nan if q_r is None else q_r, SKIPPED)
        return Estimate(
            time_s=t if math.isfinite(t) else last.time_s,
            delta_L_rad=last.delta_L_rad,
            std_rad=last.std_rad,
            q_r_rad=last.q_r_rad if q_r is None else q_r,
            flags=SKIPPED | (last.flags & Flag.NOT_INITIALISED),
            informative_radius_mm=last.informative_radius_mm,
        )

    def _time_ok(self, t: float) -> bool:
        """Whether ``t`` follows the last accepted time; a run of rejected times that agree
        among themselves is a restarted clock: the estimator starts again from them."""
        last = self._last_time_s
        if last is None or 0.0 < t - last <= MAX_TIME_STEP_S:
            self._rejected_times = []
            return True
        run = self._rejected_times
        if run and not 0.0 < t - run[-1] <= MAX_TIME_STEP_S:
            run.clear()
        run.append(t)
        if len(run) < CLOCK_RESTART_FRAMES:
            return False
        self.inner.reset()
        self._reset_state()
        self.skipped["clock restarted"] = self.skipped.get("clock restarted", 0) + 1
        return True

    def step(self, observation: Observation) -> Estimate:
        """The wrapped estimator's step, or a flagged, skipped step for a bad observation."""
        t = float(observation.time_s)
        if not math.isfinite(t):
            return self._skip(observation, "time not finite")
        problem = observation_problem(observation, self.n_markers)
        if problem is not None:
            return self._skip(observation, problem)
        if not self.check_time:  # a per-frame estimator: nothing carried from step to step
            return self.inner.step(observation)
        if not self._time_ok(t):
            return self._skip(observation, "time not after the last frame or too far ahead")
        estimate = self.inner.step(observation)
        self._last_time_s = t
        if math.isfinite(estimate.delta_L_rad) and math.isfinite(estimate.std_rad):
            self._last = estimate
        return estimate
