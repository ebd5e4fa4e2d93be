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
"""

from __future__ import annotations

import csv
import enum
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from tracker.io.recording import RecordingWriter
from tracker.io.udp import JointReceiver
from tracker.types import Estimate, Frame, Observation


class LiveStatus(enum.IntFlag):
    """What the live loop noticed about a frame (bits 16.. of the estimate datagram flags)."""

    NONE = 0
    STALE_JOINTS = 1  # the joint stream had stopped: predict only
    NO_JOINTS = 2  # no joint value received yet: predict only
    JOINTS_CLAMPED = 4  # image time just outside the joint history: nearest sample used
    ESTIMATOR_ERROR = 8  # the estimator raised: invalid estimate


PREDICT_ONLY = LiveStatus.STALE_JOINTS | LiveStatus.NO_JOINTS
"""Frames without usable joint values: the estimator only predicted."""


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

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE) -> None:
        if self.joints is not None:
            times, q, q_dot = self.joints.samples_after(self._joints_until_s)
            if times.size:
                rates = None if not np.all(np.isfinite(q_dot)) else q_dot
                self.writer.write_joints(times, q, rates)
                self._joints_until_s = float(times[-1])
        elif not status & PREDICT_ONLY:
            self.writer.write_joints(frame.time_s, frame.q, frame.q_dot)
        self.writer.write_frame(frame, images=self.images)
        self.writer.write_estimate(self.method, estimate)

    def close(self) -> None:
        self.writer.close()
