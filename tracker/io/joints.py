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

:meth:`JointHistory.interpolate` takes many times at once (recordings);
:func:`sample_joints` takes the one time of an image (the live loop, twice a frame) with a
binary search and the two bracketing rows, in Python floats, and gives bit for bit what
:meth:`JointHistory.interpolate` gives for that time.
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
        ``CLAMPED``) up to ``stale_after_s``, ``STALE`` beyond. Values and rates are those of
        :meth:`interpolate`, bit for bit (:func:`sample_joints`).
        """
        t = np.asarray(self.time_s, dtype=float)
        return sample_joints(time_s, t, self.q, self.q_dot, stale_after_s, rate_window_s)


def sample_joints(
    time_s: float,
    times_s: Array,
    q: Array,
    q_dot: Array | None,
    stale_after_s: float,
    rate_window_s: float = RATE_WINDOW_S,
    offset_s: float | None = None,
) -> JointSample:
    """The joint values at one time: :meth:`JointHistory.sample` of samples held as rows.

    One binary search and the two bracketing rows, in Python floats: the same operations in
    the same order as :meth:`JointHistory.interpolate` does on arrays, hence the same values
    bit for bit (NaN where it has NaN), without its two dozen array operations.

    Parameters
    ----------
    time_s : float
        Time on the clock of the samples, s.
    times_s : array, shape (n,)
        Sample times, s, non-decreasing (a strided view will do): on the clock of ``time_s``
        once ``offset_s`` is added.
    q : array, shape (n, 3)
        q_r [rad], q_p [mm], q_d [mm].
    q_dot : array, shape (n, 3) or None
        Measured rates (rad/s, mm/s, mm/s); NaN rows (or None) where not measured.
    stale_after_s : float
        How far outside the samples a time is still ``HELD`` or ``CLAMPED``, s.
    rate_window_s : float
        Window of the slope that stands in for rates that were not measured, s.
    offset_s : float, optional
        Added to every sample time (a receiver's aligned clock), s: the sample times are
        ``times_s + offset_s`` but that array is only made if rates must be taken as a slope.
        Must be finite.

    Returns
    -------
    JointSample
        ``age_s`` is ``time_s`` less the newest sample time (inf without samples), s.
    """
    time_s = float(time_s)
    n = len(times_s)
    if n == 0:
        nan = np.full(3, np.nan)
        return JointSample(time_s, nan, nan.copy(), JointStatus.NONE, math.inf)
    q = np.asarray(q, dtype=float)
    if offset_s is None:
        first, last = float(times_s[0]), float(times_s[-1])
        hi = int(times_s.searchsorted(time_s))  # first sample >= time
    else:
        first, last = float(times_s[0]) + offset_s, float(times_s[-1]) + offset_s
        hi = _search_shifted(times_s, offset_s, time_s)
    hi = min(hi, n - 1)
    t_hi = float(times_s[hi]) if offset_s is None else float(times_s[hi]) + offset_s
    if t_hi == time_s:
        lo, t_lo = hi, t_hi
    else:
        lo = max(hi - 1, 0)
        t_lo = float(times_s[lo]) if offset_s is None else float(times_s[lo]) + offset_s
    spacing = t_hi - t_lo
    w = (time_s - t_lo) / spacing if spacing > 0 else 0.0
    w = _minimum(_maximum(w, 0.0), 1.0)
    nearest = None  # at a sample (and outside the history) its row as it is
    if w == 0.0 or w == 1.0:
        nearest = hi if w == 1.0 else lo
    q_at = _row_at(q, lo, hi, w, nearest)
    if q_dot is None:
        q_dot_at = [math.nan] * 3
    else:
        q_dot_at = _row_at(np.asarray(q_dot, dtype=float), lo, hi, w, nearest)
    if not all(map(math.isfinite, q_dot_at)):
        times = np.asarray(times_s, dtype=float)
        if offset_s is not None:
            times = times + offset_s
        q_dot_at = _slope_at(time_s, times, q, rate_window_s)
    age = time_s - last
    if age > 0:
        status = JointStatus.HELD if age <= stale_after_s else JointStatus.STALE
    elif time_s < first:
        early = first - time_s
        status = JointStatus.CLAMPED if early <= stale_after_s else JointStatus.STALE
    else:
        status = JointStatus.OK
    return JointSample(time_s, np.array(q_at), np.array(q_dot_at), status, age)


def _maximum(a: float, b: float) -> float:
    """``np.maximum`` of two floats: NaN if either is, ``b`` on a tie (signed zeros)."""
    return a if a > b or a != a else b


def _minimum(a: float, b: float) -> float:
    """``np.minimum`` of two floats: NaN if either is, ``b`` on a tie (signed zeros)."""
    return a if a < b or a != a else b


def _search_shifted(times_s: Array, offset_s: float, time_s: float) -> int:
    """``np.searchsorted(times_s + offset_s, time_s)`` without making the shifted array.

    The search for ``time_s - offset_s`` lands within rounding of the answer; the shifted
    times are non-decreasing (rounding is monotonic), so a short walk finds it exactly.
    """
    k, n = int(times_s.searchsorted(time_s - offset_s)), len(times_s)
    while k > 0 and float(times_s[k - 1]) + offset_s >= time_s:
        k -= 1
    while k < n and float(times_s[k]) + offset_s < time_s:
        k += 1
    return k


def _row_at(values: Array, lo: int, hi: int, w: float, nearest: int | None) -> list[float]:
    """One row of :meth:`JointHistory.interpolate`'s ``between``, in Python floats."""
    if nearest is not None:
        return values[nearest].tolist()
    v = 1.0 - w
    return [v * a + w * b for a, b in zip(values[lo].tolist(), values[hi].tolist(), strict=True)]


def _slope_at(time_s: float, times_s: Array, q: Array, window_s: float) -> list[float]:
    """:meth:`JointHistory._slope` at one time (the same ``np.interp`` calls)."""
    first, last = float(times_s[0]), float(times_s[-1])
    lo = _maximum(first, _minimum(time_s - window_s / 2, last - window_s))
    hi = _minimum(last, lo + window_s)
    span = hi - lo
    if not span > 0:
        return [0.0, 0.0, 0.0]  # a single sample (or no window): no slope
    slope = []
    for k in range(3):
        at_ends = np.interp((hi, lo), times_s, q[:, k])
        slope.append((float(at_ends[0]) - float(at_ends[1])) / span)
    return slope
