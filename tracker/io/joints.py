"""Joint values at an image time: one interpolation for the live loop and for recordings.

The robot controller samples the joints (up to 1 kHz) on its own schedule; the cameras take
images on theirs. Both the live receiver (:class:`tracker.io.udp.JointReceiver`) and the
recording reader (:mod:`tracker.io.recording`) hand the estimator the joint values at the
image time stamp, and both do it here, with :class:`JointHistory`:

- values (and measured rates) linearly between the two samples that bracket the time, the
  nearest end sample outside the history;
- where the rates were not measured, the slope of the values over :data:`RATE_WINDOW_S`
  around the time, the window moved inside the history at either end (the difference of
  two interpolated values, which smooths the 1 kHz quantisation of the encoders).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

Array = np.ndarray

RATE_WINDOW_S = 0.02
"""Width of the window over which unmeasured joint rates are taken as a slope, s."""


class JointStatus(enum.Enum):
    """How the joint values at an image time were obtained."""

    OK = "ok"  # interpolated between two samples
    HELD = "held"  # after the newest sample by less than the timeout: newest value held
    CLAMPED = "clamped"  # before the oldest kept sample by less than the timeout
    STALE = "stale"  # the stream has stopped (or the history does not reach back): clamped
    NONE = "none"  # no sample received yet


@dataclass(frozen=True)
class JointSample:
    """Joint values and rates at one time, and how they were obtained."""

    time_s: float
    q: Array
    q_dot: Array
    status: JointStatus
    age_s: float  # time since the newest sample (negative when it is newer), s

    @property
    def usable(self) -> bool:
        return self.status in (JointStatus.OK, JointStatus.HELD, JointStatus.CLAMPED)


@dataclass(frozen=True)
class JointHistory:
    """Joint samples in time order.

    Parameters
    ----------
    time_s : array, shape (n,)
        Sample times, non-decreasing, s.
    q : array, shape (n, 3)
        q_r [rad], q_p [mm], q_d [mm].
    q_dot : array, shape (n, 3), optional
        Measured rates (rad/s, mm/s, mm/s); NaN rows (or None) where not measured.
    """

    time_s: Array
    q: Array
    q_dot: Array | None = None

    def interpolate(
        self, time_s, rate_window_s: float = RATE_WINDOW_S
    ) -> tuple[Array, Array, Array]:
        """Joint values and rates at the given times.

        Parameters
        ----------
        time_s : array, shape (m,)
            Times on the clock of the samples, s.
        rate_window_s : float
            Window of the slope that stands in for rates that were not measured, s.

        Returns
        -------
        q, q_dot : arrays, shape (m, 3)
            Interpolated between the bracketing samples (the nearest end sample outside the
            history; NaN without samples). Rates that cannot be taken as a slope (a single
            sample) are 0.
        gap_s : array, shape (m,)
            Spacing of the two bracketing samples (0 at a sample, inf outside the history),
            s: how far the values were interpolated.
        """
        times = np.atleast_1d(np.asarray(time_s, dtype=float))
        t = np.asarray(self.time_s, dtype=float)
        n, m = t.size, times.size
        if n == 0:
            nan = np.full((m, 3), np.nan)
            return nan, nan.copy(), np.full(m, math.inf)
        hi = np.minimum(t.searchsorted(times, side="left"), n - 1)  # first sample >= time
        exact = t[hi] == times
        lo = np.where(exact, hi, np.maximum(hi - 1, 0))
        spacing = t[hi] - t[lo]
        inside = (t[lo] <= times) & (times <= t[hi])
        w = np.zeros(m)
        np.divide(times - t[lo], spacing, out=w, where=spacing > 0)
        w = np.minimum(np.maximum(w, 0.0), 1.0)
        # At a sample (and outside the history) its row as it is: bit-exact, and a rate that
        # was not measured at the other bracketing sample does not leak in.
        at_sample = (w == 0.0) | (w == 1.0)
        nearest = np.where(w == 1.0, hi, lo)[at_sample]

        def between(values: Array) -> Array:
            # Only the bracketing rows are read: the history may hold thousands.
            row = (1.0 - w)[:, None] * values[lo] + w[:, None] * values[hi]
            row[at_sample] = values[nearest]
            return row

        q_all = np.asarray(self.q, float)
        q = between(q_all)
        if self.q_dot is None:
            q_dot = np.full((m, 3), np.nan)
        else:
            q_dot = between(np.asarray(self.q_dot, float))
        missing = ~np.isfinite(q_dot).all(axis=1)
        if missing.any():
            q_dot[missing] = self._slope(times[missing], q_all, rate_window_s)
        return q, q_dot, np.where(inside, spacing, math.inf)

    def _slope(self, times: Array, q: Array, window_s: float) -> Array:
        """Slope of the values over ``window_s`` around each time, kept inside the samples."""
        t = np.asarray(self.time_s, dtype=float)
        lo = np.maximum(t[0], np.minimum(times - window_s / 2, t[-1] - window_s))
        hi = np.minimum(t[-1], lo + window_s)
        span = hi - lo
        slope = np.zeros((times.size, 3))
        usable = span > 0
        ends = np.concatenate([hi, lo])  # one interpolation per joint for both window ends
        for k in range(3):
            at_ends = np.interp(ends, t, q[:, k])
            delta = at_ends[: times.size] - at_ends[times.size :]
            slope[usable, k] = delta[usable] / span[usable]
        return slope

    def sample(
        self, time_s: float, stale_after_s: float, rate_window_s: float = RATE_WINDOW_S
    ) -> JointSample:
        """The joint values at one time and how they were obtained (:class:`JointStatus`).

        A time later than the newest sample is ``HELD`` (earlier than the oldest:
        ``CLAMPED``) up to ``stale_after_s``, ``STALE`` beyond.
        """
        time_s = float(time_s)
        t = np.asarray(self.time_s, dtype=float)
        q, q_dot, _ = self.interpolate(time_s, rate_window_s)
        if t.size == 0:
            return JointSample(time_s, q[0], q_dot[0], JointStatus.NONE, math.inf)
        age = time_s - float(t[-1])
        if age > 0:
            status = JointStatus.HELD if age <= stale_after_s else JointStatus.STALE
        elif time_s < t[0]:
            early = float(t[0]) - time_s
            status = JointStatus.CLAMPED if early <= stale_after_s else JointStatus.STALE
        else:
            status = JointStatus.OK
        return JointSample(time_s, q[0], q_dot[0], status, age)
