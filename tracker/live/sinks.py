"""Where the live loop's results go: the sink protocol, and the sinks that keep or write them.

Every sink has one method per frame,

    handle(frame, observation, estimate, latency_s, status)

with the frame as the loop built it (joint values interpolated to the image time), its
observation in {B}, the estimate, the latency from the image time stamp (or arrival) to the
estimate, s, and the :class:`LiveStatus` of the frame; and ``close()``, called once when the
loop ends. ``status`` defaults to :attr:`LiveStatus.NONE` so that a sink can also be fed by
hand. A sink may have a ``name`` for the loop's reports.

Sinks here: :class:`MemorySink` (tests, notebooks), :class:`CsvSink`, :class:`RecordingSink`
(MCAP). Elsewhere: :class:`tracker.io.udp.EstimateSender` (datagrams to the controller),
:class:`tracker.io.igtl.IgtlSink` (3D Slicer), :class:`tracker.viewer.sink.LiveViewerSink`
(rerun).

The loop calls its sinks on its own thread, in order. Only the estimate datagram belongs
there (the controller waits for it); every other sink goes behind a :class:`QueuedSink`, which
hands the frame to the sink's own thread through a bounded queue.
"""

from __future__ import annotations

import collections
import csv
import enum
import functools
import math
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from tracker.io.recording import RecordingWriter
from tracker.io.udp import JointReceiver
from tracker.types import Estimate, Frame, Observation

Array = np.ndarray


class LiveStatus(enum.IntFlag):
    """What the live loop noticed about a frame (bits 16.. of the estimate datagram flags)."""

    NONE = 0
    STALE_JOINTS = 1  # the joint stream had stopped: predict only
    NO_JOINTS = 2  # no joint value received yet: predict only
    JOINTS_CLAMPED = 4  # image time before the oldest joint sample kept: predict only
    ESTIMATOR_ERROR = 8  # the estimator raised: invalid estimate
    JOINTS_EXTRAPOLATED = 16  # image time past the newest joint sample by more than a hold


PREDICT_ONLY = (
    LiveStatus.STALE_JOINTS
    | LiveStatus.NO_JOINTS
    | LiveStatus.JOINTS_CLAMPED
    | LiveStatus.JOINTS_EXTRAPOLATED
)
"""Frames without joint values at their time: the estimator only predicted, and the estimate
sent is not valid (NaN, valid bit clear)."""

INVALID = PREDICT_ONLY | LiveStatus.ESTIMATOR_ERROR
"""Frames whose estimate is not valid whatever the estimator returned."""


class Sink(Protocol):
    """Where results go (see the module docstring)."""

    def handle(
        self,
        frame: Frame,
        observation: Observation,
        estimate: Estimate,
        latency_s: float,
        status: LiveStatus = LiveStatus.NONE,
    ) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class LiveResult:
    """One processed frame."""

    frame: Frame
    observation: Observation
    estimate: Estimate
    latency_s: float
    status: LiveStatus = LiveStatus.NONE


class MemorySink:
    """Keeps every result (tests, notebooks)."""

    name = "memory"

    def __init__(self) -> None:
        self.results: list[LiveResult] = []
        self.closed = False

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE) -> None:
        self.results.append(LiveResult(frame, observation, estimate, latency_s, status))

    def close(self) -> None:
        self.closed = True


CSV_COLUMNS = (
    "time_s",
    "delta_L_rad",
    "std_rad",
    "delta_1_rad",
    "q_r_rad",
    "q_p_mm",
    "q_d_mm",
    "estimator_flags",
    "live_status",
    "latency_s",
    "delta_L_true_rad",
)


class CsvSink:
    """One CSV row per frame (columns :data:`CSV_COLUMNS`; radians, seconds, mm)."""

    name = "csv"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file = self.path.open("w", newline="")
        self._writer = csv.writer(self._file)
        self._writer.writerow(CSV_COLUMNS)
        self.rows = 0

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE) -> None:
        q = np.asarray(frame.q, dtype=float)
        truth = frame.delta_L_true_rad
        self._writer.writerow(
            [
                repr(float(estimate.time_s)),
                repr(float(estimate.delta_L_rad)),
                repr(float(estimate.std_rad)),
                repr(float(estimate.delta_1_rad)),
                repr(float(estimate.q_r_rad)),
                repr(float(q[1])),
                repr(float(q[2])),
                int(estimate.flags.value),
                int(status),
                f"{latency_s:.6f}",
                "" if truth is None else repr(float(truth)),
            ]
        )
        self.rows += 1

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()


def _report_stderr(message: str) -> None:
    print(f"cathtrack: {message}", file=sys.stderr, flush=True)


class _Unpaused(threading.local):
    active = False  # in this thread: inside QueuedSink.submit, never pause


_unpaused = _Unpaused()


class QueuedSink:
    """A sink run in its own thread behind a bounded queue, off the loop's critical path.

    The loop hands each frame over in microseconds and goes on; the sink's thread does the
    work. When the sink falls behind and its queue is full:

    - ``keep_all=False`` (viewer, OpenIGTLink): the oldest queued frame makes room and is
      counted in ``dropped``;
    - ``keep_all=True`` (recordings): nothing is lost; the loop waits for room, each wait
      counted in ``stalls`` and the first reported loudly.

    A sink that must read something on the loop's thread (the joint receiver, which the loop
    keeps filling) has ``prepare(frame, observation, estimate, latency_s, status)``: it runs
    on the loop's thread and returns the callable to run in the sink's thread. Otherwise the
    sink's ``handle`` runs there. :meth:`submit` queues other work for the same thread, after
    what is queued (e.g. a second estimator's series logged to the same rerun stream).

    An exception of the sink is reported once and disables it (``failure``); it is still
    closed. :meth:`close` lets the queue run out, then closes the sink in its own thread.

    Parameters
    ----------
    sink : Sink
    capacity : int
        Frames (and submitted jobs) the queue holds.
    keep_all : bool
        Never drop: wait for room instead (see above).
    report : callable
        Receives one line per problem.

    Attributes
    ----------
    idle : threading.Event or None
        Set by the loop while it waits for a frame (:class:`tracker.live.loop.LiveTracker`
        attaches its own): a job starts only then, and pauses at its next Python call when
        a frame comes in (each wait at most ``idle_wait_s``), so that the sink's Python code
        does not compete with the loop's for the interpreter.
    """

    def __init__(
        self,
        sink: Sink,
        capacity: int = 64,
        *,
        keep_all: bool = False,
        report: Callable[[str], None] = _report_stderr,
        idle_wait_s: float = 0.1,
    ) -> None:
        if int(capacity) < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self.sink = sink
        self.name = str(getattr(sink, "name", type(sink).__name__))
        self.capacity = int(capacity)
        self.keep_all = keep_all
        self.report = report
        self.idle: threading.Event | None = None
        self.idle_wait_s = float(idle_wait_s)
        self.handled = 0
        self.dropped = 0
        self.stalls = 0
        self.failure: str | None = None
        self._jobs: collections.deque[Callable[[], None]] = collections.deque()
        self._cond = threading.Condition()
        self._closing = False
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._work, name=f"sink-{self.name}", daemon=True)

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE) -> None:
        prepare = getattr(self.sink, "prepare", None)
        if prepare is not None:
            job = prepare(frame, observation, estimate, latency_s, status)
        else:
            job = functools.partial(
                self.sink.handle, frame, observation, estimate, latency_s, status
            )
        self.submit(job)

    def submit(self, job: Callable[[], None]) -> None:
        """Run ``job()`` in this sink's thread after what is queued (same queue rules)."""
        # Another sink's job may call this: it must not pause holding the queue's lock.
        _unpaused.active = True
        try:
            with self._cond:
                if self._closing:
                    return
                if not self._thread.is_alive():
                    self._thread.start()
                while len(self._jobs) >= self.capacity:
                    if not self.keep_all:
                        self._jobs.popleft()
                        self.dropped += 1
                        break
                    self._wait_for_room()
                self._jobs.append(job)
                self._cond.notify_all()
        finally:
            _unpaused.active = False

    def _wait_for_room(self) -> None:
        """The loop waits for this sink (``keep_all``): counted, the first time loudly."""
        self.stalls += 1
        if self.stalls == 1:
            self.report(
                f"WARNING: sink {self.name} cannot keep up: its queue of {self.capacity} is"
                " full and the loop waits for it (nothing is lost; every wait is counted)"
            )
        idle = self.idle
        busy = idle is not None and not idle.is_set()
        if busy:
            idle.set()  # waiting, the loop leaves the interpreter to the sinks
        try:
            self._cond.wait()
        finally:
            if busy:
                idle.clear()

    @property
    def pending(self) -> int:
        """Jobs queued and not yet started."""
        return len(self._jobs)

    def _work(self) -> None:
        while True:
            with self._cond:
                while not self._jobs and not self._closing:
                    self._cond.wait()
                if not self._jobs:
                    break
                job = self._jobs.popleft()
                self._cond.notify_all()  # room for a loop that waits (keep_all)
            idle = self.idle
            if idle is not None and not self._closing:
                idle.wait(self.idle_wait_s)
            if self.failure is not None:
                continue
            try:
                if idle is not None and not self._closing:
                    sys.setprofile(self._yield_to_loop)
                job()
                self.handled += 1
            except Exception as exc:  # any failure: report once, disable, go on draining
                self.failure = f"{type(exc).__name__}: {exc}"
                self.report(f"sink {self.name} failed and is disabled ({self.failure})")
            finally:
                sys.setprofile(None)
        try:
            self.sink.close()
        except Exception as exc:
            self.failure = self.failure or f"close failed: {type(exc).__name__}: {exc}"
            self.report(f"sink {self.name} failed to close ({exc})")
        finally:
            self._closed.set()

    def _yield_to_loop(self, frame, event, arg) -> None:
        """At every Python call of a job: wait while the loop processes a frame.

        The interpreter runs one thread at a time; a job that holds it while the loop works
        on a frame delays the loop (by up to the switch interval each time the loop lets
        go of it for a system or numpy call). Pausing here hands the loop its frame's time.
        """
        if event == "call" and not self.idle.is_set() and not _unpaused.active:
            self.idle.wait(self.idle_wait_s)

    def close(self, timeout_s: float | None = None) -> bool:
        """Finish the queued jobs, close the sink; False if that took over ``timeout_s``."""
        with self._cond:
            self._closing = True
            started = self._thread.is_alive() or self._closed.is_set()
            self._cond.notify_all()
        if not started:  # nothing was ever queued
            self._thread.start()
        return self._closed.wait(timeout_s)


class RecordingSink:
    """Writes the session to an MCAP recording (:class:`tracker.io.recording.RecordingWriter`).

    Per frame: the joint samples received since the previous frame (or, without a joint
    receiver, the frame's own joint values), the markers (and images), the estimate.
    ``close()`` finishes the file (last chunk and summary).

    Parameters
    ----------
    writer : RecordingWriter
    method : str
        Estimate topic ``/estimates/<method>``.
    joints : JointReceiver, optional
        Record its raw samples (1 kHz) rather than the per-frame interpolated values.
    images : bool
    """

    name = "recording"

    def __init__(
        self,
        writer: RecordingWriter,
        method: str,
        joints: JointReceiver | None = None,
        images: bool = True,
    ) -> None:
        self.writer, self.method, self.joints, self.images = writer, method, joints, images
        self._joints_until_s = -math.inf

    def prepare(
        self, frame, observation, estimate, latency_s, status=LiveStatus.NONE
    ) -> Callable[[], None]:
        """Take the joint samples received since the last frame (on the thread that fills the
        receiver); returns the writing, for any thread (:class:`QueuedSink`)."""
        if self.joints is not None:
            joints = self._new_joint_samples()
        elif not status & PREDICT_ONLY:
            joints = (frame.time_s, frame.q, frame.q_dot)
        else:
            joints = None
        return functools.partial(self._write, frame, estimate, joints)

    def _new_joint_samples(self) -> tuple[Array, Array, Array | None] | None:
        """The receiver's samples after those already taken (rates None if not sent)."""
        times, q, q_dot = self.joints.samples_after(self._joints_until_s)
        if not times.size:
            return None
        self._joints_until_s = float(times[-1])
        return times, q, q_dot if np.all(np.isfinite(q_dot)) else None

    def _write(self, frame, estimate, joints) -> None:
        if joints is not None:
            self.writer.write_joints(*joints)
        self.writer.write_frame(frame, images=self.images)
        self.writer.write_estimate(self.method, estimate)

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE) -> None:
        self.prepare(frame, observation, estimate, latency_s, status)()

    def close(self) -> None:
        """Write the joint samples received after the last frame, then finish the file."""
        joints = None if self.joints is None else self._new_joint_samples()
        if joints is not None:
            self.writer.write_joints(*joints)
        self.writer.close()
