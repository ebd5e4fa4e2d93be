"""When the live loop's next frame is due: the period of a stream of frames.

Cameras deliver at a fixed period, so the loop knows, within the delivery's jitter, when the
next frame will come. :class:`FramePace` keeps that period (the median of the last intervals
between admitted frames, so that a dropped frame does not double it) and the time the next
frame is due on this machine's clock. The loop uses it to prime itself just before a frame
(:meth:`tracker.live.loop.LiveTracker.prime`): after tens of milliseconds of waiting, while
other threads and processes ran, the loop's code and data are no longer in the processor's
caches, and the first stage to run pays for it (about 2 ms a frame on a 2-core machine).
:class:`PrimeTiming` keeps how long priming takes, so that it ends before the frame comes.
"""

from __future__ import annotations

import collections
import math


class FramePace:
    """The period of a stream of frames and when the next one is due.

    Parameters
    ----------
    window : int
        Intervals kept; the period is their median.
    nominal_period_s : float, optional
        The period the source says it keeps (its ``period_s``, e.g. the simulated cameras'),
        taken until a first interval has been seen: the loop can then prime for the second
        frame too. None: no period before two frames.
    """

    def __init__(self, window: int = 5, nominal_period_s: float | None = None) -> None:
        self._intervals_s: collections.deque[float] = collections.deque(maxlen=int(window))
        self._last_time_s: float | None = None
        self._last_received_s: float | None = None
        self.nominal_period_s = nominal_period_s

    def add(self, time_s: float, received_s: float) -> None:
        """A frame admitted: its stream time and when it left the source (local clock), s."""
        if self._last_time_s is not None and time_s > self._last_time_s:
            self._intervals_s.append(time_s - self._last_time_s)
        self._last_time_s, self._last_received_s = float(time_s), float(received_s)

    def reset(self) -> None:
        """Forget the stream (a new time base)."""
        self._intervals_s.clear()
        self._last_time_s = self._last_received_s = None

    @property
    def period_s(self) -> float | None:
        """Median of the last intervals between frames (stream time), s; before two frames,
        the nominal period if one was given (a positive, finite one), else None."""
        if not self._intervals_s:
            nominal = self.nominal_period_s
            ok = nominal is not None and 0.0 < nominal < math.inf
            return float(nominal) if ok else None
        ordered = sorted(self._intervals_s)
        return ordered[len(ordered) // 2]

    @property
    def next_time_s(self) -> float | None:
        """Stream time of the next frame if the stream keeps its period, s."""
        period_s = self.period_s
        if period_s is None or self._last_time_s is None:
            return None
        return self._last_time_s + period_s

    def due_s(self, speed: float | None = 1.0) -> float:
        """When the next frame should leave the source on the local clock, s (inf: unknown).

        ``speed`` is the source's stream time per local second (None: no pace, never due).
        """
        period_s = self.period_s
        if period_s is None or self._last_received_s is None or not speed:
            return math.inf
        return self._last_received_s + period_s / speed


PRIME_SPREADS = 3.0
"""Priming starts this many of its running mean deviations earlier than its running mean
duration alone would have it (a priming that runs long must not hold up the frame)."""


PRIME_FIRST_S = 0.01
"""How long the first priming is taken to last before one has been timed, s: the first
runs cold (its rehearsal the first of a session's code and data), 5-8 ms on a slow 2-core
machine, against a median of 4; started as if it took none, it held up the frame it
primed for by 5.6 ms."""


class PrimeTiming:
    """How long the loop's priming takes (running mean and mean deviation), and so when to
    start it for a frame: early enough that it ends the lead before the frame is due (the
    first as if it took :data:`PRIME_FIRST_S`)."""

    def __init__(self) -> None:
        self.mean_s = 0.0
        self.spread_s = 0.0

    def add(self, took_s: float) -> None:
        """One priming's duration, s."""
        if self.mean_s == 0.0:
            self.mean_s = took_s
        else:
            self.spread_s = 0.8 * self.spread_s + 0.2 * abs(took_s - self.mean_s)
            self.mean_s = 0.8 * self.mean_s + 0.2 * took_s

    def start_s(self, due_s: float, lead_s: float) -> float:
        """When to start priming for a frame due at ``due_s`` to end ``lead_s`` before it."""
        took_s = self.mean_s if self.mean_s else PRIME_FIRST_S
        return due_s - lead_s - took_s - PRIME_SPREADS * self.spread_s
