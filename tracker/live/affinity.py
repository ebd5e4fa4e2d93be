"""A processor of its own for the live loop's thread (Linux; elsewhere nothing is changed).

While the loop waits for a frame, whatever runs on its processor takes the caches that the
frame's segmentation and estimate need next: on the 2-core development machine a pair
segmented right after another costs 2.5 ms, and 7 ms after 45 ms of other work on the same
processor (docs/live.md, *Where the time goes*). During :meth:`LiveTracker.run
<tracker.live.loop.LiveTracker.run>` the loop's thread therefore runs on one processor, the
last one it may use, and the process's other threads (the capture, the queued sinks,
rerun's) and its child processes (the demo's cameras and controller) on the others. Threads
started later by the loop's thread (a queued sink starts its thread with its first job)
inherit its processor; :meth:`LoopAffinity.sweep` moves them off, and the loop calls it
while it waits. With a single processor allowed, nothing is pinned.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from pathlib import Path

_TASKS = Path("/proc/self/task")


def _supported() -> bool:
    return hasattr(os, "sched_setaffinity") and _TASKS.is_dir()


class LoopAffinity:
    """The loop's thread on one processor, the rest of the process and its children off it.

    Parameters
    ----------
    allowed : set of int, optional
        The processors to share out (default: those this process may use).
    """

    def __init__(self, allowed: set[int] | None = None) -> None:
        self.loop_cpu: int | None = None
        self.others: frozenset[int] = frozenset()
        self._saved: dict[int, set[int]] = {}  # thread or process id -> its processors before
        self._loop_tid: int | None = None
        self._original: set[int] = set()  # the loop thread's processors before
        if not _supported():
            return
        allowed = set(os.sched_getaffinity(0) if allowed is None else allowed)
        if len(allowed) >= 2:
            self.loop_cpu = max(allowed)
            self.others = frozenset(allowed - {self.loop_cpu})

    @property
    def active(self) -> bool:
        """Whether the loop's thread is pinned (between :meth:`apply` and :meth:`restore`)."""
        return self._loop_tid is not None

    def _move(self, task_id: int, cpus: frozenset[int] | set[int]) -> None:
        try:
            before = os.sched_getaffinity(task_id)
            if before != cpus:
                os.sched_setaffinity(task_id, cpus)
                # A thread the loop's thread started while pinned gets the loop's own back.
                inherited = before == {self.loop_cpu} and task_id != self._loop_tid
                self._saved.setdefault(task_id, self._original if inherited else before)
        except OSError:  # ended meanwhile, or not ours to move
            pass

    def apply(self) -> bool:
        """Pin the calling thread (the loop's) and move everything else off its processor;
        False when there is nothing to share out."""
        if self.loop_cpu is None or self.active:
            return False
        self._loop_tid = threading.get_native_id()
        self._original = os.sched_getaffinity(0)
        self.sweep()
        for child in multiprocessing.active_children():
            if child.pid is not None:
                self._move(child.pid, self.others)
        self._move(self._loop_tid, {self.loop_cpu})
        return True

    def sweep(self) -> None:
        """Move the process's threads other than the loop's off its processor (those started
        since :meth:`apply` included)."""
        if not self.active:
            return
        try:
            tasks = [int(name) for name in os.listdir(_TASKS)]
        except OSError:
            return
        for task_id in tasks:
            if task_id != self._loop_tid:
                self._move(task_id, self.others)

    def restore(self) -> None:
        """Give every thread and process moved its processors back."""
        saved, self._saved = self._saved, {}
        self._loop_tid = None
        for task_id, cpus in saved.items():
            try:
                os.sched_setaffinity(task_id, cpus)
            except OSError:
                pass
