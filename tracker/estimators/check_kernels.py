"""The input checks of an observation's 3-D data, compiled (numba).

:func:`tracker.estimators.checks.observation_problem` runs before every step of every
estimator. Written with Python floats it cost a frame 10 to 45 us (the latter when the
filter's own work has just left the caches cold); here the joint values, the tip, the
markers, the velocity and their covariances are copied into one float buffer and checked in
one compiled call. The rules are those of the module :mod:`tracker.estimators.checks`
documents; the buffer makes every input, whatever its layout or dtype, the same argument type,
so that nothing compiles while a loop runs.

The buffer holds, in order: q (3), q_dot (3), the tip (3), its covariance (9), the markers
(3 n), their covariances (9 n), the velocity (3), its covariance (9), the cross-covariance
(9). Which parts are given is a bit mask (:data:`HAS_Q_DOT` ...).
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

# Which parts of the buffer hold data.
HAS_Q_DOT, HAS_TIP, HAS_TIP_COV, HAS_MARKERS, HAS_MARKERS_COV = 1, 2, 4, 8, 16
HAS_VELOCITY, HAS_VELOCITY_COV, HAS_CROSS = 32, 64, 128
JOINT_MARKERS_COV = 256
"""The markers' covariance is a joint one, checked by the caller (not in the buffer)."""

# What check_buffer finds (0: nothing wrong), in the order the checks run.
OK, BAD_JOINTS, BAD_RATES, BAD_TIP, BAD_TIP_COV, BAD_MARKERS, BAD_MARKERS_COV = range(7)
BAD_VELOCITY, BAD_CROSS, BAD_DECORRELATED = 7, 8, 9


def buffer_size(n_markers: int) -> int:
    """Length of the buffer of a catheter with ``n_markers`` markers."""
    return 3 + 3 + 3 + 9 + 12 * n_markers + 3 + 9 + 9


@numba.njit(cache=True, nogil=True)
def _within(v, start, limits):
    """v[start : start + 3] finite and each within its limit."""
    for i in range(3):
        x = v[start + i]
        if not (math.isfinite(x) and abs(x) <= limits[i]):
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _point(v, start, limit):
    """1: a finite point within ``limit``; 0: all NaN (not found); -1: unusable (partly NaN,
    an infinity, or beyond the limit)."""
    a, b, c = v[start], v[start + 1], v[start + 2]
    if math.isfinite(0.0 + a + b + c):
        if max(abs(a), abs(b), abs(c)) > limit:
            return -1
        return 1
    if math.isnan(a) and math.isnan(b) and math.isnan(c):
        return 0
    return -1


@numba.njit(cache=True, nogil=True)
def symmetric_in_range_3(v, start, low, high):
    """The 3x3 matrix v[start : start + 9] (rows in order) symmetric, ``A - low I`` positive
    definite (Sylvester's criterion) and every variance at most ``high``."""
    a, b, c = v[start], v[start + 1], v[start + 2]
    d, e, f = v[start + 3], v[start + 4], v[start + 5]
    g, h, i = v[start + 6], v[start + 7], v[start + 8]
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


@numba.njit(cache=True, nogil=True)
def check_buffer(v, n_markers, has, value_limits, rate_limits, max_point, max_speed, low, high):
    """The first rule the buffer's data break (:data:`OK` when none)."""
    if not _within(v, 0, value_limits):
        return BAD_JOINTS
    if has & HAS_Q_DOT and not _within(v, 3, rate_limits):
        return BAD_RATES
    if has & HAS_TIP:
        found = _point(v, 6, max_point)
        if found < 0:
            return BAD_TIP
        if found == 1 and not (has & HAS_TIP_COV and symmetric_in_range_3(v, 9, low, high)):
            return BAD_TIP_COV
    markers, covs = 18, 18 + 3 * n_markers
    if has & HAS_MARKERS:
        any_found = False
        for k in range(n_markers):
            found = _point(v, markers + 3 * k, max_point)
            if found < 0:
                return BAD_MARKERS
            any_found = any_found or found == 1
        if any_found and not has & JOINT_MARKERS_COV:
            if not has & HAS_MARKERS_COV:
                return BAD_MARKERS_COV
            for k in range(n_markers):
                if _point(v, markers + 3 * k, max_point) == 1 and not symmetric_in_range_3(
                    v, covs + 9 * k, low, high
                ):
                    return BAD_MARKERS_COV
    velocity = covs + 9 * n_markers
    if has & HAS_VELOCITY:
        found = _point(v, velocity, max_speed)
        if found < 0 or (
            found == 1
            and not (has & HAS_VELOCITY_COV and symmetric_in_range_3(v, velocity + 3, low, high))
        ):
            return BAD_VELOCITY
        if has & HAS_CROSS:
            for j in range(velocity + 12, velocity + 21):
                if not math.isfinite(v[j]):
                    return BAD_CROSS
            # With the tip, the filters fuse the velocity decorrelated from it: its
            # covariance given the tip must be a covariance too.
            if found == 1 and has & HAS_TIP and _point(v, 6, max_point) == 1:
                if not decorrelated_in_range(v, 9, velocity + 3, velocity + 12, low):
                    return BAD_DECORRELATED
    return OK


@numba.njit(cache=True, nogil=True)
def decorrelated_in_range(v, tip_cov, velocity_cov, cross, low):
    """Whether ``Sv - C S^-1 C^T`` (S the tip's covariance, Sv the velocity's, C their
    cross-covariance: 3x3 matrices at those offsets of v, rows in order), the velocity's
    covariance given the tip, is positive definite above ``low`` (S is one already)."""
    S = v[tip_cov : tip_cov + 9].reshape(3, 3)
    C = v[cross : cross + 9].reshape(3, 3)
    # S^-1 by its adjugate (S is symmetric positive definite).
    a, b, c, e, f, i = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    A = np.empty((3, 3))
    A[0, 0], A[0, 1], A[0, 2] = e * i - f * f, c * f - b * i, b * f - c * e
    A[1, 1], A[1, 2], A[2, 2] = a * i - c * c, b * c - a * f, a * e - b * b
    A[1, 0], A[2, 0], A[2, 1] = A[0, 1], A[0, 2], A[1, 2]
    det = a * A[0, 0] + b * A[1, 0] + c * A[2, 0]
    given = np.empty(9)
    for r in range(3):
        for k in range(3):
            t = 0.0
            for m in range(3):
                for n in range(3):
                    t += C[r, m] * A[m, n] * C[k, n]
            given[3 * r + k] = v[velocity_cov + 3 * r + k] - t / det
    for r in range(3):
        for k in range(r + 1, 3):
            given[3 * r + k] = given[3 * k + r] = 0.5 * (given[3 * r + k] + given[3 * k + r])
    return symmetric_in_range_3(given, 0, low, math.inf)


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) the kernel once per process, with the types the checks
    pass (the limits are read-only arrays)."""
    limits = np.ones(3)
    limits.flags.writeable = False
    check_buffer(np.zeros(buffer_size(1)), 1, 511, limits, limits, 1.0, 1.0, 0.1, 2.0)


__all__ = ["buffer_size", "check_buffer", "symmetric_in_range_3", "warm_up"]
