"""Ctrl-C and SIGTERM for the live loop: stop after the current frame, not in the middle of
one (:meth:`tracker.live.loop.LiveTracker.run`), so that every sink is closed and every
recording finalised; a second Ctrl-C interrupts at once."""

from __future__ import annotations

import signal
import threading


class StopRequest:
    """SIGINT / SIGTERM -> stop after the current frame; a second SIGINT interrupts at once."""

    def __init__(self) -> None:
        self.requested = False
        self.closing = False
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # signals only reach the main thread; KeyboardInterrupt still works there
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handler)

    def _handler(self, signum, frame) -> None:
        if self.requested and signum == signal.SIGINT and not self.closing:
            raise KeyboardInterrupt
        self.requested = True

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()
