"""A processor of its own for the live loop's thread (Linux; elsewhere nothing is changed).

While the loop waits for a frame, whatever runs on its processor takes the caches that the
frame's segmentation and estimate need next: on the 2-core development machine a pair
segmented right after another costs 2.5 ms, and 7 ms after 45 ms of other work on the same
processor (docs/live.md, *Where the time goes*). During :meth:`LiveTracker.run
<tracker.live.loop.LiveTracker.run>` the loop's thread therefore runs on one processor, the
last one it may use, together with the capture thread that hands it each frame. The
process's other threads (the queued sinks, rerun's) and every thread of its child processes
(the demo's cameras and controller) run on the others: the controller's 1 kHz joint stream
alone used to preempt the loop about seven times a frame. Threads started later by the
loop's thread (a queued sink starts its thread with its first job) inherit its processor;
:meth:`LoopAffinity.sweep` moves them off, and the loop calls it while it waits. With a
single processor allowed, nothing is pinned.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import threading
from collections.abc import Iterable
from pathlib import Path

_TASKS = Path("/proc/self/task")
_active: list[LoopAffinity] = []  # the one pinned loop of the process, if any
_lock = threading.Lock()


def usable_processors() -> int:
    """The processors this process may run on (its affinity, where the system has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _supported() -> bool:
    return hasattr(os, "sched_setaffinity") and _TASKS.is_dir()


def _threads(tasks: Path) -> list[int]:
    """The thread ids of a process (its ``/proc/<pid>/task``); none if it has ended."""
    try:
        return [int(name) for name in os.listdir(tasks)]
    except OSError:
        return []


class LoopAffinity:
    """The loop's thread on one processor, the rest of the process and its children off it.

    One loop of a process is pinned at a time: another one's :meth:`apply` does nothing
    until the first is restored.

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
        self._with_loop: set[int] = set()  # the threads on the loop's processor
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
        with contextlib.suppress(OSError):  # ended meanwhile, or not ours to move
            before = os.sched_getaffinity(task_id)
            if before != cpus:
                os.sched_setaffinity(task_id, cpus)
                # A thread the loop's thread started while pinned gets the loop's own back.
                inherited = before == {self.loop_cpu} and task_id not in self._with_loop
                self._saved.setdefault(task_id, self._original if inherited else before)

    def apply(self, with_loop: Iterable[int | None] = ()) -> bool:
        """Pin the calling thread (the loop's) and move everything else off its processor;
        False when there is nothing to share out.

        ``with_loop``: the native ids of threads that share the loop's processor (the
        capture thread, which hands the loop each frame the moment it comes, when the loop
        waits for it: elsewhere it would queue behind the outputs for its turn).
        """
        with _lock:
            if self.loop_cpu is None or _active:  # one pinned loop per process
                return False
            _active.append(self)
        self._loop_tid = threading.get_native_id()
        self._with_loop = {self._loop_tid} | {tid for tid in with_loop if tid is not None}
        self._original = os.sched_getaffinity(0)
        self.sweep()
        for task_id in self._with_loop:
            self._move(task_id, {self.loop_cpu})
        return True

    def sweep(self) -> None:
        """Move the threads of the process other than the loop's, and every thread of its
        child processes, off the loop's processor (those started since :meth:`apply`
        included)."""
        if not self.active:
            return
        tasks = _threads(_TASKS)
        for child in multiprocessing.active_children():
            if child.pid is not None:
                tasks += _threads(Path(f"/proc/{child.pid}/task"))
        for task_id in tasks:
            if task_id not in self._with_loop:
                self._move(task_id, self.others)

    def restore(self) -> None:
        """Give every thread and process moved its processors back."""
        saved, self._saved = self._saved, {}
        with _lock:
            if self in _active:
                _active.remove(self)
        self._loop_tid = None
        self._with_loop = set()
        for task_id, cpus in saved.items():
            with contextlib.suppress(OSError):  # a thread or process that has ended
                os.sched_setaffinity(task_id, cpus)
