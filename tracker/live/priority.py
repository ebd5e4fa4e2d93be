"""A real-time priority for the work of a frame (Linux; elsewhere nothing is changed).

Between its frames the loop waits and every other thread and process has the processors. When
a frame comes, any of them that is running keeps its processor until its time slice is used
up, and a kernel thread or a process that has slept a while gets the processor back at
once: on the 2-core development machine a kernel thread (the memory monitor ``kdamond``)
runs twice a second for 0.7-1.4 ms, and the demo's controller and the outputs' threads share
the segmentation worker's processor. A frame's work that such a thread holds up is late by
as long.

:class:`FramePriority` raises the calling thread to ``SCHED_FIFO`` at priority 1 (above every
ordinary thread, below the kernel's own real-time ones) for a frame's work only: the live
loop from a frame's arrival to the end of its step, the segmentation worker from a request
to its answer. A few milliseconds in fifty, so the others lose no more than that; the
kernel's real-time throttling (by default 95% of each second) would still leave them their
share if the work of a frame never ended. Threads and processes started meanwhile do not
inherit it (``SCHED_RESET_ON_FORK``). A thread that already has a real-time policy (the
whole tracker started with ``chrt``) keeps its own.

The wait for a frame is raised too (:meth:`FramePriority.hold`): from the start of the loop's
priming for a frame (:meth:`~tracker.live.loop.LiveTracker.prime`) until the frame is taken,
or one priming lead past its due time, the loop's thread and its capture thread
(:class:`~tracker.live.sources.NewestOnly`) run at the same priority. Both are blocked for
most of it; a frame that arrives then wakes them at once instead of after whatever ordinary
thread holds their processor (``kdamond`` for up to 4 ms on a slower host). A capture thread
that never blocks gets no more than that window: it is put back when the frame is taken.

The live loop raises its step only when its thread has a processor of its own
(:class:`~tracker.live.affinity.LoopAffinity`): polling at a real-time priority for the
worker's answer on the processor the worker shares would keep the worker off it.

Raising a thread's policy needs ``CAP_SYS_NICE`` or an ``rtprio`` resource limit (e.g.
``@realtime - rtprio 10`` in ``/etc/security/limits.conf``): without it the first frame
reports once that the work runs at the ordinary priority, and nothing else changes.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterable

PRIORITY = 1  # the lowest real-time priority


def _supported() -> bool:
    return all(hasattr(os, name) for name in ("sched_setscheduler", "SCHED_FIFO"))


# Policies a thread may already have from its user (``chrt``): left as they are.
_REAL_TIME = tuple(getattr(os, name) for name in ("SCHED_FIFO", "SCHED_RR") if hasattr(os, name))
_RESET_ON_FORK = getattr(os, "SCHED_RESET_ON_FORK", 0)


class FramePriority:
    """A context manager: the calling thread at ``SCHED_FIFO`` inside, as it was outside.

    Parameters
    ----------
    enabled : bool
        Off: entering changes nothing (also where the system has no such policy).
    report : callable, optional
        Told once when the system refuses the policy (it is then off).

    Attributes
    ----------
    refused : str or None
        Why the system refused, if it did.
    """

    def __init__(self, enabled: bool = True, report: Callable[[str], None] | None = None) -> None:
        self.enabled = bool(enabled) and _supported()
        self.report = report
        self.refused: str | None = None
        self._saved: tuple[int, os.sched_param] | None = None
        self._held: dict[int, tuple[int, os.sched_param]] = {}

    def start(self) -> bool:
        """Turn it on; whether the system allows it (tried once now: raised and put back,
        and reported if refused)."""
        self.enabled = _supported()
        self._restore(self._raise())
        return self.enabled

    def stop(self) -> None:
        """Turn it off."""
        self.enabled = False

    def hold(self, thread_ids: Iterable[int | None]) -> None:
        """Raise these threads (native ids; 0 is the calling thread; None is skipped) until
        :meth:`release`; a thread already raised or real-time stays as it is."""
        for thread_id in thread_ids:
            if thread_id is None or thread_id in self._held:
                continue
            saved = self._raise(thread_id)
            if saved is not None:
                self._held[thread_id] = saved

    def release(self) -> None:
        """Put the threads raised by :meth:`hold` back (nothing when none are held; the
        calling thread not once it has entered the context, which then puts it back)."""
        if self._held:
            held, self._held = self._held, {}
            for thread_id, saved in held.items():
                self._restore(saved, thread_id)

    @property
    def held(self) -> tuple[int, ...]:
        """The threads :meth:`hold` raised and that are not released yet."""
        return tuple(self._held)

    def __enter__(self) -> FramePriority:
        # A calling thread that :meth:`hold` raised goes on at the priority, never put back
        # in between: even for the moment between two calls, an ordinary thread that is
        # ready (a tokio worker at niceness -10 was seen) takes its processor for ms.
        held = self._held.pop(0, None)
        self._saved = self._raise() if held is None else held
        return self

    def __exit__(self, *exc) -> None:
        saved, self._saved = self._saved, None
        self._restore(saved)

    def _raise(self, thread_id: int = 0) -> tuple[int, os.sched_param] | None:
        """Raise a thread (0: the calling one); what to put back (None: nothing was changed, because
        it is off, refused, or the thread already has a real-time policy of its own, e.g.
        from ``chrt``, which it keeps)."""
        if not self.enabled:
            return None
        try:
            saved = os.sched_getscheduler(thread_id), os.sched_getparam(thread_id)
            if (saved[0] & ~_RESET_ON_FORK) in _REAL_TIME:
                return None
            os.sched_setscheduler(
                thread_id, os.SCHED_FIFO | _RESET_ON_FORK, os.sched_param(PRIORITY)
            )
        except ProcessLookupError:  # that thread has ended
            return None
        except OSError as exc:  # not permitted (no CAP_SYS_NICE, no rtprio limit)
            self.enabled = False
            self.refused = str(exc)
            if self.report is not None:
                self.report(
                    f"a frame's work runs at the ordinary priority ({exc}): other work on its"
                    " processor can hold it up; CAP_SYS_NICE or an rtprio limit allows"
                    " SCHED_FIFO (docs/live.md)"
                )
            return None
        return saved

    @staticmethod
    def _restore(saved: tuple[int, os.sched_param] | None, thread_id: int = 0) -> None:
        if saved is not None:
            # Back to what it was: always permitted (an ended thread: nothing to do).
            with contextlib.suppress(OSError):
                os.sched_setscheduler(thread_id, *saved)
