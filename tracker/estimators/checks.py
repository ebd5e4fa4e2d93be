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
  :data:`MIN_VARIANCE_MM2` and :data:`MAX_VARIANCE_MM2` (image points: the cameras' limits);
  with a tip, the velocity's covariance given the tip (what the filters fuse,
  ``Sv - C S^-1 C^T`` with the cross-covariance C) positive definite too.

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
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tracker.estimators import check_kernels as kernels
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
# The limits as the compiled checks take them (read-only: a type of their own).
_JOINT_VALUE_LIMITS = np.array(JOINT_VALUE_LIMITS, dtype=float)
_JOINT_RATE_LIMITS = np.array(JOINT_RATE_LIMITS, dtype=float)
for _limits in (_JOINT_VALUE_LIMITS, _JOINT_RATE_LIMITS):
    _limits.flags.writeable = False


def _symmetric_in_range_2(rows: list, low: float, high: float) -> bool:
    """A 2x2 matrix given as nested Python floats: symmetric, ``A - low I`` positive definite
    and every variance at most ``high``."""
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


def _matrix(value) -> Array | None:
    """A 3x3 covariance as floats, or None (not given, not numbers, another shape)."""
    if value is None:
        return None
    try:
        matrix = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return None
    return matrix if matrix.shape == (3, 3) else None


_PROBLEMS = {
    kernels.BAD_JOINTS: "joint values missing, not finite or beyond the robot's ranges",
    kernels.BAD_RATES: "joint rates not finite or beyond the robot's ranges",
    kernels.BAD_TIP: "tip not finite or beyond the catheter's reach",
    kernels.BAD_TIP_COV: "tip covariance not positive definite or out of range",
    kernels.BAD_MARKERS: "markers not {n} finite points within the catheter's reach",
    kernels.BAD_MARKERS_COV: "marker covariance not positive definite or out of range",
    kernels.BAD_VELOCITY: "velocity or its covariance unusable",
    kernels.BAD_CROSS: "velocity-tip cross-covariance not finite",
    kernels.BAD_DECORRELATED: "velocity-tip cross-covariance too large: the velocity's"
    " covariance given the tip is not positive definite",
}


def _fill(o: Observation, n_markers: int, v: Array) -> tuple[int, int, str | None, Array | None]:
    """Copy the 3-D data of ``o`` into the kernel's buffer ``v``.

    Returns the mask of the parts given, the first problem found on the way (a wrong shape;
    nothing after it is copied: the kernel checks what comes before it), its message when
    it has its own, and a joint marker covariance left to the caller.
    """
    n = n_markers
    has = 0
    q = np.asarray(o.q, dtype=float)
    if q.shape != (3,):
        return has, kernels.BAD_JOINTS, None, None
    v[0:3] = q
    if o.q_dot is not None:
        q_dot = np.asarray(o.q_dot, dtype=float)
        if q_dot.shape != (3,):
            return has, kernels.BAD_RATES, None, None
        v[3:6] = q_dot
        has |= kernels.HAS_Q_DOT
    if o.tip_b_mm is not None:
        tip = np.asarray(o.tip_b_mm, dtype=float)
        if tip.shape != (3,):
            return has, kernels.BAD_TIP, None, None
        v[6:9] = tip
        has |= kernels.HAS_TIP
        cov = _matrix(o.tip_cov_b)
        if cov is not None:
            v[9:18] = cov.ravel()
            has |= kernels.HAS_TIP_COV
    markers, covs, velocity = 18, 18 + 3 * n, 18 + 12 * n
    joint = None
    if o.markers_b_mm is not None:
        points = np.asarray(o.markers_b_mm, dtype=float)
        if points.shape != (n, 3):
            return has, kernels.BAD_MARKERS, None, None
        v[markers:covs] = points.ravel()
        has |= kernels.HAS_MARKERS
        cov = np.asarray(o.markers_cov_b if o.markers_cov_b is not None else np.nan, float)
        if cov.shape == (n, 3, 3):
            v[covs:velocity] = cov.ravel()  # the blocks of the markers found are checked
            has |= kernels.HAS_MARKERS_COV
        elif (found := np.isfinite(points).all(axis=1)).any():
            if cov.shape == (3 * n, 3 * n):
                rows = np.repeat(found, 3)
                joint = cov[np.ix_(rows, rows)]
                if joint.shape[-1] == 3:  # one marker found: its block, checked as one
                    k = covs + 9 * int(np.flatnonzero(found)[0])
                    v[k : k + 9] = joint.ravel()
                    has |= kernels.HAS_MARKERS_COV
                    joint = None
                else:
                    has |= kernels.JOINT_MARKERS_COV
            else:
                return has, kernels.BAD_MARKERS_COV, f"marker covariance of shape {cov.shape}", None
    if o.velocity_b_mm_s is not None:
        speed = np.asarray(o.velocity_b_mm_s, dtype=float)
        if speed.shape != (3,):
            return has, kernels.BAD_VELOCITY, None, joint
        v[velocity : velocity + 3] = speed
        has |= kernels.HAS_VELOCITY
        cov = _matrix(o.velocity_cov_b)
        if cov is not None:
            v[velocity + 3 : velocity + 12] = cov.ravel()
            has |= kernels.HAS_VELOCITY_COV
        cross = o.velocity_tip_cov_b
        if cross is not None:
            cross = np.asarray(cross, dtype=float)
            if cross.shape == (3, 3):
                v[velocity + 12 : velocity + 21] = cross.ravel()
                has |= kernels.HAS_CROSS
            elif not np.isfinite(cross).all():
                return has, kernels.BAD_CROSS, None, joint
    return has, kernels.OK, None, joint


def observation_problem(
    observation: Observation, n_markers: int, buffer: Array | None = None
) -> str | None:
    """Why ``observation`` cannot be used (one phrase), or None when it can (times aside).

    The 3-D data are checked by one compiled call (:mod:`tracker.estimators.check_kernels`),
    a joint marker covariance and single-view points here. ``buffer``: the kernel's buffer
    (``check_kernels.buffer_size(n_markers)`` floats) to reuse, if the caller keeps one.
    """
    o = observation
    if buffer is None:
        buffer = np.empty(kernels.buffer_size(n_markers))
    has, stop, message, joint = _fill(o, n_markers, buffer)
    code = kernels.check_buffer(
        buffer, n_markers, has, _JOINT_VALUE_LIMITS, _JOINT_RATE_LIMITS, MAX_POINT_MM,
        MAX_SPEED_MM_S, MIN_VARIANCE_MM2, MAX_VARIANCE_MM2,
    )  # fmt: skip
    if code == kernels.OK or code > kernels.BAD_MARKERS_COV:
        # The joint covariance of several markers comes in the order of the markers' checks.
        if joint is not None and not (
            np.all(np.diag(joint) <= MAX_VARIANCE_MM2)
            and _positive_definite(joint - MIN_VARIANCE_MM2 * np.eye(joint.shape[-1]))
        ):
            code = kernels.BAD_MARKERS_COV
    if stop != kernels.OK and (code == kernels.OK or code >= stop):
        # What the kernel found at or after the part that stopped the copy is that part's.
        if message is not None:
            return message
        code = stop
    if code != kernels.OK:
        return _PROBLEMS[code].format(n=n_markers)
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
        kernels.warm_up()
        self._buffer = np.empty(kernels.buffer_size(self.n_markers))
        self.skipped: dict[str, int] = {}
        self._reset_state()

    def _reset_state(self) -> None:
        self._last_time_s: float | None = None
        self._last: Estimate | None = None
        self._rejected_times: list[float] = []

    def __getattr__(self, name: str):
        if name == "inner":  # not set yet (an instance being copied or unpickled)
            raise AttributeError(name)
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

    def _follows(self, t: float) -> bool:
        """Whether ``t`` follows the last accepted time, by at most ``MAX_TIME_STEP_S``."""
        last = self._last_time_s
        return last is None or 0.0 < t - last <= MAX_TIME_STEP_S

    def _time_ok(self, t: float) -> bool:
        """Whether ``t`` follows the last accepted time; a run of rejected times that agree
        among themselves is a restarted clock: the estimator starts again from them."""
        if self._follows(t):
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

    def _problem(self, observation: Observation) -> str | None:
        """Why the wrapped estimator must not see ``observation`` (None: it may), the time
        taken as the last accepted one when it may. A restarted clock resets the estimator
        here (:meth:`_time_ok`)."""
        t = float(observation.time_s)
        if not math.isfinite(t):
            return "time not finite"
        problem = observation_problem(observation, self.n_markers, self._buffer)
        if problem is not None or not self.check_time:  # a per-frame estimator: no order
            return problem
        if not self._time_ok(t):
            return "time not after the last frame or too far ahead"
        self._last_time_s = t
        return None

    def _accepted(self, estimate: Estimate) -> Estimate:
        """Keep a filter's valid estimate: a skipped step holds it."""
        if self.check_time and math.isfinite(estimate.delta_L_rad + estimate.std_rad):
            self._last = estimate
        return estimate

    def run(self, observations: Sequence[Observation]) -> list[Estimate]:
        """The steps of frames in order, as :meth:`step` on each in turn gives them: the
        checks frame by frame, the accepted frames through the wrapped estimator's ``run``
        (in one call between skipped frames, which need the estimate held before them)."""
        observations = list(observations)
        estimates: list[Estimate | None] = [None] * len(observations)
        accepted: list[int] = []

        def flush() -> None:
            if not accepted:
                return
            frames = [observations[i] for i in accepted]
            for i, estimate in zip(accepted, self.inner.run(frames), strict=True):
                estimates[i] = self._accepted(estimate)
            accepted.clear()

        for i, observation in enumerate(observations):
            if self._rejected_times:  # a clock restart resets the estimator: after these
                flush()
            problem = self._problem(observation)
            if problem is None:
                accepted.append(i)
            else:
                flush()
                estimates[i] = self._skip(observation, problem)
        flush()
        return estimates

    def rehearse(self, observation: Observation) -> None:
        """The wrapped estimator's ``rehearse`` (a step that changes nothing), if it has
        one, for an observation it would be given after the last accepted one; nothing
        here changes either."""
        rehearse = getattr(self.inner, "rehearse", None)
        t = float(observation.time_s)
        if not (callable(rehearse) and math.isfinite(t) and self._follows(t)):
            return
        if observation_problem(observation, self.n_markers, self._buffer) is None:
            rehearse(observation)

    def step(self, observation: Observation) -> Estimate:
        """The wrapped estimator's step, or a flagged, skipped step for a bad observation."""
        problem = self._problem(observation)
        if problem is not None:
            return self._skip(observation, problem)
        return self._accepted(self.inner.step(observation))
