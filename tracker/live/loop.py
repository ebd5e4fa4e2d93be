"""The online tracking loop (docs/design.md section 6): the replay pipeline fed live.

    source -> (segmentation, for images) -> Reconstructor -> estimator -> sinks

The same :class:`~tracker.reconstruction.Reconstructor` and estimators as replay; only the source
(cameras, UDP markers, a paced simulation or recording) and the sinks (UDP estimates,
OpenIGTLink, rerun, recordings, CSV) differ. Joint values come from a
:class:`~tracker.io.udp.JointReceiver`, interpolated to each image time stamp.

Faults, each counted in the :class:`LiveSummary`:

- frames whose time does not increase (duplicates, out of order) are dropped;
- frames whose joint values are stale (the joint stream stopped) or missing are flagged
  (:class:`LiveStatus`) and the estimator gets a predict-only observation (no measurement),
  never stale joints with fresh markers;
- a frame that cannot be segmented or reconstructed is dropped and reported once per cause;
- an estimator error gives an invalid estimate (NaN) for that frame, reported once;
- a sink (:mod:`tracker.live.sinks`) that raises is reported once and disabled; the loop
  goes on;
- Ctrl-C (SIGINT) or SIGTERM ends the loop after the current frame; a second Ctrl-C
  interrupts at once. Every sink is closed (recordings finalised) and sockets released in
  all cases, and :meth:`LiveTracker.run` returns the summary.
"""

from __future__ import annotations

import dataclasses
import math
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from tracker.io.datagrams import SegmentedMarkers
from tracker.io.joints import JointStatus
from tracker.io.udp import JointReceiver, StreamCounts
from tracker.live.sinks import PREDICT_ONLY, LiveResult, LiveStatus, Sink
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Flag, Frame, Observation

Array = np.ndarray


# ---------------------------------------------------------------------------- bookkeeping
class LatencyRecorder:
    """The last ``capacity`` latencies (a ring), and their percentiles."""

    def __init__(self, capacity: int = 100_000) -> None:
        self._values = np.empty(int(capacity))
        self._count = 0

    def add(self, latency_s: float) -> None:
        self._values[self._count % self._values.size] = latency_s
        self._count += 1

    def values(self) -> Array:
        return self._values[: min(self._count, self._values.size)].copy()

    def percentiles_ms(self) -> dict[str, float]:
        """p50, p99 and max in ms (NaN when empty)."""
        v = self.values()
        if v.size == 0:
            return {"p50": math.nan, "p99": math.nan, "max": math.nan}
        p50, p99 = np.percentile(v, [50, 99])
        return {"p50": 1e3 * p50, "p99": 1e3 * p99, "max": 1e3 * float(v.max())}


@dataclass
class LiveSummary:
    """What a run did (counts of frames and datagrams, latencies, failures)."""

    frames_received: int = 0
    frames_processed: int = 0
    frames_out_of_order: int = 0
    frames_duplicate: int = 0
    frames_rejected: int = 0  # could not be segmented or reconstructed
    frames_stale_joints: int = 0
    frames_no_joints: int = 0
    frames_clamped_joints: int = 0
    frames_valid: int = 0  # with a finite estimate
    estimator_errors: int = 0
    joints: StreamCounts | None = None
    markers: StreamCounts | None = None
    sink_failures: dict[str, str] = field(default_factory=dict)
    latency_ms: dict[str, float] = field(default_factory=dict)  # image time -> estimate ready
    cycle_ms: dict[str, float] = field(default_factory=dict)  # image time -> all sinks done
    duration_s: float = 0.0
    stop_reason: str = ""

    @property
    def frames_dropped(self) -> int:
        return self.frames_out_of_order + self.frames_duplicate + self.frames_rejected

    @property
    def interrupted(self) -> bool:
        return self.stop_reason == "interrupted"

    def lines(self) -> list[str]:
        """The summary as a few human-readable lines."""
        out = [
            f"live loop ended ({self.stop_reason}) after {self.duration_s:.1f} s:"
            f" {self.frames_processed} of {self.frames_received} frames processed,"
            f" {self.frames_valid} with an estimate",
            f"  dropped: {self.frames_out_of_order} out of order, {self.frames_duplicate}"
            f" duplicate, {self.frames_rejected} unusable",
            f"  joints: {self.frames_stale_joints} frames with stale joints,"
            f" {self.frames_no_joints} without joints, {self.frames_clamped_joints} clamped",
        ]
        for label, counts in (("joint", self.joints), ("marker", self.markers)):
            if counts is not None:
                bad = ", ".join(f"{k} {v}" for k, v in sorted(counts.malformed.items())) or "none"
                out.append(
                    f"  {label} datagrams: {counts.received} received, {counts.accepted} used,"
                    f" {counts.stale} stale, {counts.duplicate} duplicate, malformed: {bad}"
                    + (f", {counts.restarts} sender restarts" if counts.restarts else "")
                )
        if self.estimator_errors:
            out.append(f"  estimator errors: {self.estimator_errors}")
        lat, cyc = self.latency_ms, self.cycle_ms
        if lat:
            out.append(
                f"  latency image -> estimate: p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms,"
                f" max {lat['max']:.2f} ms; -> all sinks done: p50 {cyc['p50']:.2f} ms,"
                f" p99 {cyc['p99']:.2f} ms"
            )
        for name, failure in self.sink_failures.items():
            out.append(f"  sink {name} disabled: {failure}")
        return out

    def __str__(self) -> str:
        return "\n".join(self.lines())


def _report_stderr(message: str) -> None:
    print(f"cathtrack track: {message}", file=sys.stderr, flush=True)


@dataclass
class _SinkEntry:
    sink: Sink
    name: str
    enabled: bool = True


def _sink_name(sink: object) -> str:
    return str(getattr(sink, "name", type(sink).__name__))


class _StopRequest:
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


# ------------------------------------------------------------------------------------ loop
class LiveTracker:
    """One frame in, one estimate out to every sink.

    Parameters
    ----------
    reconstructor : Reconstructor
        Frames -> observations in {B} (the registered base and the rig).
    estimator : Estimator
        From :func:`tracker.estimators.make_estimator` (``"ukf"`` for live tracking).
    sinks : sequence of Sink
        Called in order (:mod:`tracker.live.sinks`); put the estimate sender first, it is the
        one the latency is for.
    joints : JointReceiver, optional
        Joint values for every frame, interpolated to its time; frames that carry their own
        joint values (simulation, recordings) keep them when no receiver is given.
    segmenter : optional
        Anything with ``segment(images)`` (one image per view) returning an object with
        ``uv`` and ``cov`` (one array per view; :class:`PairSegmenter`); needed when the
        source yields images.
    report : callable
        Receives one line per new problem (default: stderr).
    monotonic : callable
        Local clock for the latencies.
    """

    def __init__(
        self,
        reconstructor: Reconstructor,
        estimator,
        sinks: Sequence[Sink] = (),
        *,
        joints: JointReceiver | None = None,
        segmenter=None,
        report: Callable[[str], None] = _report_stderr,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.reconstructor = reconstructor
        self.estimator = estimator
        self.joints = joints
        self.segmenter = segmenter
        self.report = report
        self.monotonic = monotonic
        self._sinks = [_SinkEntry(s, _sink_name(s)) for s in sinks]
        self.summary = LiveSummary(joints=None if joints is None else joints.counts)
        self.latency = LatencyRecorder()
        self.cycle = LatencyRecorder()
        self._last_time_s: float | None = None
        self._reported: set[str] = set()
        self._closed = False
        self.time_is_monotonic = False

    @property
    def sinks(self) -> list[Sink]:
        """The sinks still enabled."""
        return [e.sink for e in self._sinks if e.enabled]

    def add_sink(self, sink: Sink) -> None:
        """Call ``sink`` after the others (before the run starts)."""
        self._sinks.append(_SinkEntry(sink, _sink_name(sink)))

    def _report_once(self, key: str, message: str) -> None:
        if key not in self._reported:
            self._reported.add(key)
            self.report(message)

    # ------------------------------------------------------------------ one frame
    def _markers(self, item) -> tuple[SegmentedMarkers, tuple[Array, ...] | None]:
        if isinstance(item, SegmentedMarkers):
            return item, None
        time_s, images = item
        seg = self.segmenter.segment(images)
        return SegmentedMarkers(time_s, tuple(seg.uv), tuple(seg.cov)), tuple(images)

    def _joints_at(
        self, time_s: float, frame: Frame | None
    ) -> tuple[Array, Array | None, LiveStatus]:
        if self.joints is None:
            if frame is not None:
                return np.asarray(frame.q, float), frame.q_dot, LiveStatus.NONE
            return np.zeros(3), None, LiveStatus.NO_JOINTS
        self.joints.poll()
        sample = self.joints.sample(time_s)
        status = {
            JointStatus.OK: LiveStatus.NONE,
            JointStatus.HELD: LiveStatus.NONE,
            JointStatus.CLAMPED: LiveStatus.JOINTS_CLAMPED,
            JointStatus.STALE: LiveStatus.STALE_JOINTS,
            JointStatus.NONE: LiveStatus.NO_JOINTS,
        }[sample.status]
        q = sample.q if np.all(np.isfinite(sample.q)) else np.zeros(3)
        return q, sample.q_dot, status

    def step(self, item, received_s: float | None = None) -> LiveResult | None:
        """Process one source item; None when it was dropped (counted in ``summary``).

        Parameters
        ----------
        item : ImageSet, SegmentedMarkers or Frame
        received_s : float, optional
            Monotonic time the item left the source (latency reference unless the source's
            times are monotonic stamps); now if not given.
        """
        s = self.summary
        received_s = self.monotonic() if received_s is None else received_s
        s.frames_received += 1
        is_images = isinstance(item, tuple)  # ImageSet or a plain (time, images)
        if is_images and self.segmenter is None:
            raise ValueError("the source yields images but the live loop has no segmenter")
        time_s = float(item[0] if is_images else item.time_s)
        if not math.isfinite(time_s):
            s.frames_rejected += 1
            self._report_once("time", "a frame without a finite time stamp was dropped")
            return None
        last = self._last_time_s
        if last is not None and time_s <= last:
            if time_s == last:
                s.frames_duplicate += 1
            else:
                s.frames_out_of_order += 1
            return None
        self._last_time_s = time_s

        frame = item if isinstance(item, Frame) else None
        try:
            if frame is None:
                markers, images = self._markers(item)
            q, q_dot, status = self._joints_at(time_s, frame)
            if frame is None:
                frame = markers.frame(q, q_dot)
                if images is not None:
                    frame = dataclasses.replace(frame, images=images)
            elif self.joints is not None:
                frame = dataclasses.replace(frame, q=q, q_dot=q_dot)
            if status & PREDICT_ONLY:
                # Predict only: markers with stale joints would pull the estimate wrong.
                self.reconstructor.reset()
                observation = Observation(time_s=time_s, q=q)
            else:
                observation = self.reconstructor.observe(frame)
        except ValueError as exc:
            s.frames_rejected += 1
            # One report per cause: the same message up to its numbers.
            cause = re.sub(r"[-+.\d]+", "#", str(exc))
            self._report_once(f"frame:{cause}", f"frame at {time_s:.3f} s dropped: {exc}")
            return None

        try:
            estimate = self.estimator.step(observation)
        except (ValueError, np.linalg.LinAlgError) as exc:
            status |= LiveStatus.ESTIMATOR_ERROR
            s.estimator_errors += 1
            self._report_once(f"estimator:{type(exc).__name__}", f"estimator error: {exc}")
            estimate = Estimate(
                time_s=time_s,
                delta_L_rad=math.nan,
                std_rad=math.nan,
                q_r_rad=float(q[0]),
                flags=Flag.NO_MEASUREMENT,
            )

        s.frames_processed += 1
        s.frames_valid += int(estimate.valid)
        s.frames_stale_joints += int(bool(status & LiveStatus.STALE_JOINTS))
        s.frames_no_joints += int(bool(status & LiveStatus.NO_JOINTS))
        s.frames_clamped_joints += int(bool(status & LiveStatus.JOINTS_CLAMPED))
        reference = time_s if self.time_is_monotonic else received_s
        latency_s = self.monotonic() - reference
        self.latency.add(latency_s)
        self._dispatch(frame, observation, estimate, latency_s, status)
        self.cycle.add(self.monotonic() - reference)
        return LiveResult(frame, observation, estimate, latency_s, status)

    def _dispatch(self, frame, observation, estimate, latency_s, status) -> None:
        for entry in self._sinks:
            if not entry.enabled:
                continue
            try:
                entry.sink.handle(frame, observation, estimate, latency_s, status)
            except Exception as exc:  # any sink failure: report, disable, go on
                entry.enabled = False
                failure = f"{type(exc).__name__}: {exc}"
                self.summary.sink_failures[entry.name] = failure
                self.report(f"sink {entry.name} failed and is disabled ({failure})")

    # ------------------------------------------------------------------ the run
    def run(
        self,
        source: Iterable,
        *,
        idle_timeout_s: float | None = None,
        max_frames: int | None = None,
        handle_signals: bool = True,
    ) -> LiveSummary:
        """Process the source until it ends, idles, reaches ``max_frames`` or is interrupted.

        Closes every sink, the joint receiver and the source (if it has ``close()``) on the
        way out, whatever ended the run, and returns the summary. Exceptions other than
        Ctrl-C (e.g. a source that yields images to a loop without segmenter) propagate
        after that clean-up.

        Parameters
        ----------
        source : iterable
            Items as described in :mod:`tracker.live.sources`.
        idle_timeout_s : float, optional
            End when no item came for this long (sources yield ``None`` while idle).
        max_frames : int, optional
            End after this many processed frames.
        handle_signals : bool
            Turn SIGINT / SIGTERM into a clean stop (main thread only).
        """
        self.time_is_monotonic = bool(getattr(source, "time_is_monotonic", False))
        if self.summary.markers is None and hasattr(source, "counts"):
            self.summary.markers = source.counts
        stop = _StopRequest()
        if handle_signals:
            stop.install()
        started = self.monotonic()
        last_item_s = started
        reason = "source exhausted"
        try:
            iterator = iter(source)
            while True:
                if stop.requested:
                    reason = "interrupted"
                    break
                if max_frames is not None and self.summary.frames_processed >= max_frames:
                    reason = "max frames"
                    break
                try:
                    item = next(iterator)
                except StopIteration:
                    reason = getattr(source, "stop_reason", None) or "source exhausted"
                    break
                now = self.monotonic()
                if item is None:
                    if self.joints is not None:
                        self.joints.poll()
                    if idle_timeout_s is not None and now - last_item_s > idle_timeout_s:
                        reason = f"no frame for {idle_timeout_s:g} s"
                        break
                    continue
                last_item_s = now
                if stop.requested:
                    reason = "interrupted"
                    break
                self.step(item, now)
        except KeyboardInterrupt:
            reason = "interrupted"
        finally:
            stop.closing = True
            self.summary.stop_reason = reason
            self.summary.duration_s = self.monotonic() - started
            try:
                self.close(source)
            finally:
                stop.restore()
        return self.summary

    def close(self, source: object | None = None) -> None:
        """Close every sink (even disabled ones), the joint receiver and the source."""
        if self._closed:
            return
        self._closed = True
        for entry in self._sinks:
            try:
                entry.sink.close()
            except Exception as exc:  # one failing close must not keep the others open
                self.summary.sink_failures.setdefault(
                    entry.name, f"close failed: {type(exc).__name__}: {exc}"
                )
                self.report(f"sink {entry.name} failed to close ({exc})")
        closers = [getattr(source, "close", None)]
        if self.joints is not None:
            closers.append(self.joints.close)
        for closer in closers:
            if closer is not None:
                try:
                    closer()
                except OSError as exc:
                    self.report(f"closing failed: {exc}")
        self.summary.latency_ms = self.latency.percentiles_ms()
        self.summary.cycle_ms = self.cycle.percentiles_ms()


def run_live(
    source: Iterable,
    reconstructor: Reconstructor,
    estimator,
    sinks: Sequence[Sink] = (),
    *,
    joints: JointReceiver | None = None,
    segmenter=None,
    idle_timeout_s: float | None = None,
    max_frames: int | None = None,
    report: Callable[[str], None] = _report_stderr,
    handle_signals: bool = True,
) -> LiveSummary:
    """Build a :class:`LiveTracker` and run it over ``source``; returns the summary."""
    tracker = LiveTracker(
        reconstructor, estimator, sinks, joints=joints, segmenter=segmenter, report=report
    )
    return tracker.run(
        source, idle_timeout_s=idle_timeout_s, max_frames=max_frames, handle_signals=handle_signals
    )


__all__ = [
    "LatencyRecorder",
    "LiveSummary",
    "LiveTracker",
    "run_live",
]
