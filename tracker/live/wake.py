"""Processors kept out of their deep sleep states while the live loop runs (Linux).

Between two frames the loop waits some 45 ms. An idle processor enters a sleep state, and
the deep ones (C6 and beyond on x86, a halted virtual processor under a hypervisor, which
hands the physical core to other work) lose the contents of the core's caches: the frame
that wakes it then starts with none of the segmentation's, the reconstruction's or the
estimator's code and data at hand. On the 2-core development machine the reconstruction
of one frame takes 0.09 ms right after another and 0.5-0.8 ms after 45 ms of sleep
(docs/live.md, *Where the time goes*).

Linux's PM QoS interface takes a bound on the wake-up latency of every processor from any
process that holds ``/dev/cpu_dma_latency`` open with the bound written into it; the bound
lasts until the file is closed (also when the process ends, however it ends). A bound of
0 us leaves the processors only their polling idle state: they stay awake, and use more
power, while the loop runs. Writing the file needs root (or a udev rule granting the
tracking user write access): without it the loop runs as before, and says so once.
"""

from __future__ import annotations

import os
import struct
import sys
from collections.abc import Callable
from pathlib import Path

QOS_PATH = Path("/dev/cpu_dma_latency")


class WakeLatency:
    """A bound on the processors' wake-up latency, held from :meth:`hold` to :meth:`release`.

    Parameters
    ----------
    max_us : int
        The bound, microseconds (0: no sleep state beyond polling).
    path : Path
        The PM QoS file (tests pass another).
    report : callable, optional
        Takes the one message when the bound cannot be set.
    """

    def __init__(
        self,
        max_us: int = 0,
        path: Path = QOS_PATH,
        report: Callable[[str], None] | None = None,
    ) -> None:
        if max_us < 0:
            raise ValueError(f"max_us must be >= 0, got {max_us}")
        self.max_us = int(max_us)
        self.path = Path(path)
        self.report = report
        self._fd: int | None = None
        self.problem: str | None = None  # why the last hold did not take effect

    @property
    def held(self) -> bool:
        """Whether the bound is in force (between a successful :meth:`hold` and
        :meth:`release`)."""
        return self._fd is not None

    def hold(self) -> bool:
        """Put the bound in force; False when it cannot be (reported on Linux, where
        access to the file is what is missing)."""
        if self._fd is not None:
            return True
        if not sys.platform.startswith("linux"):
            self.problem = "keeping the processors awake needs Linux's PM QoS"
            return False  # nothing a user could change: not reported
        try:
            fd = os.open(self.path, os.O_WRONLY)
        except OSError as exc:
            self._failed(exc)
            return False
        try:
            os.write(fd, struct.pack("=i", self.max_us))
        except OSError as exc:
            os.close(fd)
            self._failed(exc)
            return False
        self._fd = fd
        self.problem = None
        return True

    def _failed(self, exc: OSError) -> None:
        self.problem = (
            f"the processors may sleep deeply between frames ({self.path}: {exc.strerror});"
            " frames then start with cold caches. Run as root or grant write access to"
            f" {self.path}, or pass --no-keep-awake to silence this"
        )
        if self.report is not None:
            self.report(self.problem)

    def release(self) -> None:
        """Lift the bound (closing the file is what lifts it)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)
