"""Physical limits of the inputs: what a value must be within to be data rather than damage.

One place for the ranges that the datagram decoders (:mod:`tracker.io.datagrams`), the joint
receiver (:mod:`tracker.io.udp`) and the recording reader (:mod:`tracker.io.recording`) check:
a joint value of 1e300 or a time stamp of 2^64 - 1 ns is refused there (counted by reason),
never handed to the estimators. The limits are generous: they catch corruption and unit
mix-ups, not unusual but real motions.
"""

from __future__ import annotations

import numpy as np

Array = np.ndarray

MAX_ANGLE_RAD = 100.0
"""|q_r|, and a true or estimated angle: 16 turns."""
JOINT_VALUE_LIMITS = np.array([MAX_ANGLE_RAD, 100.0, 100.0])
"""|q_r| rad, |q_p| and |q_d| mm (a tendon's whole stroke; the model's calibrated range is
about 1 mm)."""
JOINT_RATE_LIMITS = np.array([1e4, 1e5, 1e5])
"""|q_r_dot| rad/s, |q_p_dot| and |q_d_dot| mm/s: far beyond any motor, but a simulated or
commanded step differentiated over a millisecond stays within (a quarter turn: 1.6e3 rad/s)."""
MAX_IMAGE_COORDINATE = 1e5
"""|u|, |v| of an image point, px or mm (a 65,536 px image is 6.6e4 px wide)."""
MAX_POINT_SIGMA = 1e3
"""Standard deviation of an image point, px or mm (the covariance's variances: its square)."""
MAX_DATAGRAM_TIME_S = 1e10
"""|time_s| of a datagram: seconds since the sender's boot or since the epoch (1.7e9 in 2024)."""
JOINT_TIME_WINDOW_S = 1.0
"""A joint datagram may be stamped at most this much later than the newest kept sample plus
the time that passed on the receiver's clock between their arrivals (network delay, a burst
after a stall); later is a damaged or foreign time stamp."""
SESSION_TIME_RANGE_S = (-86_400.0, 3.2e9)
"""Session time (log time minus the recording's start) of a message: a day before the start
(clock adjustments) to a century after it (live sessions count from the machine's boot)."""
MAX_START_TIME_NS = 4 * 10**18
"""Latest start time of a recording, ns since the epoch (the year 2096): with the session
range this keeps every log time within a signed 64-bit integer."""


def joints_in_range(q: Array, q_dot: Array | None = None) -> Array:
    """Which samples hold joint values (and measured rates) within the robot's ranges.

    Parameters
    ----------
    q : array, shape (..., 3)
        Joint values; NaN fails.
    q_dot : array, shape (..., 3), optional
        Rates; NaN passes (not measured).

    Returns
    -------
    ok : bool array, shape (...)
    """
    q = np.asarray(q, dtype=float)
    ok = np.all(np.abs(q) <= JOINT_VALUE_LIMITS, axis=-1)
    if q_dot is not None:
        q_dot = np.asarray(q_dot, dtype=float)
        ok &= ~np.any(np.abs(q_dot) > JOINT_RATE_LIMITS, axis=-1)
    return ok


_VALUE_LIMITS = tuple(JOINT_VALUE_LIMITS.tolist())
_RATE_LIMITS = tuple(JOINT_RATE_LIMITS.tolist())


def joint_sample_in_range(q, q_dot=None) -> bool:
    """:func:`joints_in_range` of one sample, in plain floats.

    The same rule (NaN values fail, NaN rates pass) for the joint datagram decoder, which
    checks one sample per datagram at 1 kHz: three comparisons per vector cost far less than
    numpy's call overhead on three values.

    Parameters
    ----------
    q : sequence of 3 floats
    q_dot : sequence of 3 floats, optional
    """
    (q_r, q_p, q_d), (max_r, max_p, max_d) = q, _VALUE_LIMITS
    if not (abs(q_r) <= max_r and abs(q_p) <= max_p and abs(q_d) <= max_d):
        return False
    if q_dot is None:
        return True
    (r_r, r_p, r_d), (max_r, max_p, max_d) = q_dot, _RATE_LIMITS
    return not (abs(r_r) > max_r or abs(r_p) > max_p or abs(r_d) > max_d)


def points_in_range(uv: Array, cov: Array) -> Array:
    """Which image points (finite ones) and covariances are within the cameras' ranges: the
    coordinates within :data:`MAX_IMAGE_COORDINATE`, the covariance symmetric positive
    semi-definite with variances up to :data:`MAX_POINT_SIGMA` squared.

    Parameters
    ----------
    uv : array, shape (..., 2)
    cov : array, shape (..., 2, 2)

    Returns
    -------
    ok : bool array, shape (...)
        False also for NaN rows (the caller tells missing points from bad ones).
    """
    uv = np.asarray(uv, dtype=float)
    cov = np.asarray(cov, dtype=float)
    with np.errstate(invalid="ignore", over="ignore"):  # 1e300 entries fail the checks below
        a, b, c, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 0], cov[..., 1, 1]
        scale = np.maximum(np.maximum(np.abs(a), np.abs(d)), 1e-300)
        ok = np.all(np.abs(uv) <= MAX_IMAGE_COORDINATE, axis=-1)
        ok &= (a >= 0) & (d >= 0) & (np.maximum(a, d) <= MAX_POINT_SIGMA**2)
        ok &= np.abs(b - c) <= 1e-9 * scale
        ok &= a * d - b * c >= -1e-12 * scale * scale
    return ok
