"""The online tracking loop (docs/design.md section 6): the replay pipeline fed live.

    source -> (segmentation, for images) -> Reconstructor -> estimator -> sinks

The same :class:`~tracker.reconstruction.Reconstructor` and estimators as replay; only the
source (cameras, UDP markers, a paced simulation or recording) and the sinks (UDP estimates,
OpenIGTLink, rerun, recordings, CSV) differ. Joints: a :class:`~tracker.io.udp.JointReceiver`.

Real time (docs/live.md, "Real time"): the loop's own thread does only what the controller
waits for: segmentation (in a region around the catheter predicted for this frame once the
last estimate was sent), joint values at the image time, reconstruction, the estimator and
the sinks given to it (the estimate datagram); every other output runs behind a
:class:`~tracker.live.sinks.QueuedSink` in its own thread. A live source (cameras) is
captured in its own thread and the loop always takes the newest frame (``NewestOnly``): the
older ones are dropped and counted, never processed late. Python's garbage collection runs
between frames; a frame's step and the wait for it, at a real-time priority where permitted.

Faults (docs/live.md, "How the loop handles faults", the table), each counted in the
:class:`LiveSummary`: frames of implausible or out-of-order times are dropped (a run of
consistent ones is a new time base); frames without joints at their time are flagged and
predict only (never stale joints with fresh markers); a frame that cannot be segmented or
reconstructed is dropped, an estimator error gives an invalid estimate, a sink that raises
is disabled, each reported once; Ctrl-C or SIGTERM ends the loop after the current frame
with every sink closed, and :meth:`LiveTracker.run` returns the summary.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from inspect import signature

import cv2
import numpy as np

from tracker.io.datagrams import SegmentedMarkers
from tracker.io.joints import JointStatus
from tracker.io.udp import JointReceiver
from tracker.live.affinity import LoopAffinity
from tracker.live.collection import FrameCollection
from tracker.live.pacing import FramePace, PrimeTiming
from tracker.live.priority import FramePriority
from tracker.live.signals import StopRequest
from tracker.live.sinks import INVALID, PREDICT_ONLY, LiveResult, LiveStatus, QueuedSink, Sink
from tracker.live.sources import NewestOnly, arrivals
from tracker.live.summary import LatencyRecorder, LiveSummary
from tracker.live.wake import WakeLatency
from tracker.reconstruction import Reconstructor
from tracker.types import Estimate, Flag, Frame, Observation

Array = np.ndarray

MAX_HOLD_S = 0.02
"""How far past the newest joint sample an image may be and still use its values, s."""
MAX_TIME_JUMP_S = 5.0
"""How far a frame time may run ahead of the stream (beyond the time passed here), s."""
MAX_FUTURE_S = 1.0
"""How far ahead of this machine's clock a frame stamped with it may be, s."""
REBASE_AFTER = 5
"""Consistent frames rejected for their time in a row that make a new time base."""
STAGES = ("segmentation", "joints and reconstruction", "estimator")
"""The stages of a frame up to its estimate, timed in the summary (``stage_ms``)."""
ROI_POINTS = 12
"""Points along the predicted catheter that outline the segmentation's region of interest."""
ROI_TIME_TOLERANCE = 0.5
"""A region predicted for the next frame serves a frame this far from the predicted time, in
frame periods (further: the segmenter searches around the last frame's catheter)."""
PRIME_LEAD_S = 0.001
"""How long before a frame is due its priming ends, s (:meth:`LiveTracker.prime`; docs/live.md)."""
PRIME_WAIT_S = 0.003
"""How long past its due time a primed loop waits for its frame with the sinks paused, s."""


def _report_stderr(message: str) -> None:
    print(f"cathtrack track: {message}", file=sys.stderr, flush=True)


@dataclass
class _SinkEntry:
    sink: Sink
    name: str
    enabled: bool = True


_JOINT_STATUS = {
    JointStatus.OK: LiveStatus.NONE,
    JointStatus.HELD: LiveStatus.NONE,  # up to the loop's hold; past it, extrapolated
    JointStatus.CLAMPED: LiveStatus.JOINTS_CLAMPED,
    JointStatus.STALE: LiveStatus.STALE_JOINTS,
    JointStatus.NONE: LiveStatus.NO_JOINTS,
}


# ------------------------------------------------------------------------------------ loop
class LiveTracker:
    """One frame in, one estimate out to every sink.

    Parameters
    ----------
    reconstructor : Reconstructor
        Frames -> observations in {B} (the registered base and the rig).
    estimator : Estimator
        From :func:`tracker.estimators.make_estimator` (``"ukf"`` for live tracking); one
        with ``prepare(q)`` is prepared for each frame's joints while the loop primes, and
        again with the frame's while the segmenter waits (``meanwhile``, below).
    sinks : sequence of Sink
        Called in order on the loop's thread (:mod:`tracker.live.sinks`): put the estimate
        sender first (the latency is until it has sent; its datagram carries the latency up
        to the send), and every slow output behind a :class:`~tracker.live.sinks.QueuedSink`.
    joints : JointReceiver, optional
        Joint values for every frame, interpolated to its time; frames that carry their own
        joint values (simulation, recordings) keep them when no receiver is given.
    segmenter : optional
        Anything with ``segment(images, predicted_px=None)`` (one image per view) returning
        an object with ``uv`` and ``cov`` (one array per view; :class:`PairSegmenter`);
        needed when the source yields images. ``predicted_px`` (one array of points per
        view, px) is where the last estimate puts the catheter at this frame's time: the
        segmenter searches around it first. It is predicted off the critical path, once the
        last frame's estimate was sent and again when the frame is due (:meth:`prime`).
        A segmenter with ``settle()`` is called ``segment(images, predicted_px,
        settle=False)`` and settled once the estimate has left: the update of its
        background models is off the critical path. One whose ``segment`` takes
        ``meanwhile`` reads the joints then, while it waits for a view segmented elsewhere
        (their time is then part of the segmentation stage's).
    report : callable
        Receives one line per new problem (default: stderr).
    monotonic : callable
        Local clock for the latencies.
    max_hold_s : float
        An image this much past the newest joint sample still uses its values, moved on at
        their rates; later, the frame is flagged ``JOINTS_EXTRAPOLATED`` (s).
    max_time_jump_s : float
        A frame time further ahead of the stream than this plus the time passed here since
        its last frame is implausible (sources not stamped with this machine's clock; a
        source played back at ``speed`` times real time: that times the time passed; at no
        pace, ``speed=None``, the check is off), s.
    switch_interval_s : float or None
        The interpreter's thread switch interval during :meth:`run` (None: unchanged): how
        long the loop may wait for the interpreter held by another thread (a sink).
    cv_threads : int or None
        OpenCV's threads during :meth:`run` (None: unchanged). One: a pair's image
        operations are too short to gain from a split, which waits for busy cores.
    prime_lead_s : float or None
        Prime the loop this long before a frame is due (None: never), s; see :meth:`prime`.
    rehearse : bool
        Whether priming also runs the last frame again, its result dropped and nothing
        changed (:meth:`prime`): its images' segmentation, its reconstruction and its
        estimator step (each of these with a ``rehearse`` method; the others never are).
    pin : bool
        During :meth:`run`, the loop's thread on a processor of its own, the process's other
        threads and children off it (:class:`~tracker.live.affinity.LoopAffinity`).
    realtime : bool
        Each frame's step at a real-time priority where permitted and the loop is pinned
        (:class:`~tracker.live.priority.FramePriority`).
    keep_awake : bool
        During :meth:`run`, the processors kept out of their deep sleep states, which lose
        the caches (:class:`~tracker.live.wake.WakeLatency`; needs ``/dev/cpu_dma_latency``).
    collect_between_frames : bool
        During :meth:`run`, collect garbage between frames only (:mod:`tracker.live.collection`).
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
        max_hold_s: float = MAX_HOLD_S,
        max_time_jump_s: float = MAX_TIME_JUMP_S,
        switch_interval_s: float | None = 0.0005,
        cv_threads: int | None = 1,
        prime_lead_s: float | None = PRIME_LEAD_S,
        rehearse: bool = True,
        pin: bool = True,
        keep_awake: bool = False,
        realtime: bool = True,
        collect_between_frames: bool = True,
    ) -> None:
        self.reconstructor = reconstructor
        self.estimator = estimator
        self.joints = joints
        self.segmenter = segmenter
        self.report = report
        self.monotonic = monotonic
        self.max_hold_s = float(max_hold_s)
        self.max_time_jump_s = float(max_time_jump_s)
        self.switch_interval_s = switch_interval_s
        self.cv_threads = cv_threads
        self.prime_lead_s = prime_lead_s
        self.rehearse = rehearse and callable(getattr(segmenter, "rehearse", None))
        self.rehearse_steps = rehearse  # the reconstruction and the estimator's (prime)
        self._settles = callable(getattr(segmenter, "settle", None))
        # One that can read the joints while it waits for a view segmented elsewhere.
        self._overlaps = self._settles and "meanwhile" in signature(segmenter.segment).parameters
        self.affinity = LoopAffinity() if pin else None
        self.wake = WakeLatency(report=report) if keep_awake else None
        self.realtime = realtime
        self._priority = FramePriority(enabled=False, report=report)  # on during run
        self.collection = FrameCollection(enabled=collect_between_frames)
        self._rehearsal_s = 0.0  # how long a rehearsal takes (a running mean), s
        self.priming = PrimeTiming()  # how long priming takes, the rehearsal included
        self._last_images = None  # the last frame's images, for the rehearsal
        self._last_steps: tuple[Frame, Observation] | None = None  # and its other steps
        self.idle = threading.Event()  # set while the loop waits for a frame
        self.idle.set()
        self._sinks: list[_SinkEntry] = []
        for sink in sinks:
            self.add_sink(sink)
        self.summary = LiveSummary(joints=None if joints is None else joints.counts)
        self.age, self.latency, self.cycle = (LatencyRecorder() for _ in range(3))
        self.stages = {name: LatencyRecorder() for name in STAGES}  # summary's stage_ms
        self._last_time_s = self._last_arrival_s = None  # float | None
        self._odd_times: list[float] = []  # consecutive frames rejected for their time
        self._last_delta_L_rad: float | None = None  # of the last valid estimate (ROI)
        self.pace = FramePace()  # when the next frame is due
        self._primed = False  # for the frame due
        self._images = False  # the last frame was images (segmented here)
        self._roi: tuple[float, tuple[Array, ...]] | None = None  # (for time, px per view)
        L = reconstructor.catheter.length_mm
        self._roi_arclengths = tuple(np.linspace(0.0, L, ROI_POINTS).tolist())  # outline's
        self._capture: NewestOnly | None = None
        self._speed: float | None = 1.0  # of the source's stream time (None: no pace)
        self._reported: set[str] = set()
        self._closed = False
        self.time_is_monotonic = False

    @property
    def sinks(self) -> list[Sink]:
        """The sinks still enabled."""
        return [e.sink for e in self._sinks if e.enabled]

    def add_sink(self, sink: Sink, before: Sink | None = None) -> None:
        """Call ``sink`` after the others, or just before ``before`` (before the run starts).

        Sinks are closed in the same order: a sink that hands work to a queued sink's thread
        (:meth:`QueuedSink.submit`) goes before it.
        """
        if isinstance(sink, QueuedSink):
            sink.idle = self.idle
        entry = _SinkEntry(sink, str(getattr(sink, "name", type(sink).__name__)))
        at = [k for k, e in enumerate(self._sinks) if e.sink is before]  # (no sink is None)
        self._sinks.insert(at[0] if at else len(self._sinks), entry)

    def _report_once(self, key: str, message: str) -> None:
        if key not in self._reported:
            self._reported.add(key)
            self.report(message)

    # ------------------------------------------------------------------ time stamps
    def _admit(self, time_s: float, now: float) -> bool:
        """Whether a frame's time is plausible and after the last frame's (else counted)."""
        s = self.summary
        reason = None
        if not math.isfinite(time_s):
            reason = "without a finite time"
        elif self.time_is_monotonic and time_s > now + MAX_FUTURE_S:
            reason = "stamped in the future"
        if reason is not None:
            s.frames_bad_time[reason] = s.frames_bad_time.get(reason, 0) + 1
            self._report_once(f"time:{reason}", f"frames {reason} are dropped ({time_s} s)")
            return False
        last = self._last_time_s
        if last is None:
            return self._accept_time(time_s, now)
        if time_s == last:
            s.frames_duplicate += 1
            return False
        behind = time_s < last
        if not behind and (self.time_is_monotonic or self._speed is None):
            return self._accept_time(time_s, now)
        allowed_s = self.max_time_jump_s + (now - self._last_arrival_s) * self._speed
        if not behind and time_s - last <= allowed_s:
            return self._accept_time(time_s, now)
        # A run of consistent rejected times is a sender that restarted its clock.
        odd = self._odd_times
        if odd and not 0 < time_s - odd[-1] <= self.max_time_jump_s:
            odd.clear()
        odd.append(time_s)
        if len(odd) < REBASE_AFTER:
            if behind:
                s.frames_out_of_order += 1
            else:
                reason = "too far ahead of the stream"
                s.frames_bad_time[reason] = s.frames_bad_time.get(reason, 0) + 1
                self._report_once(
                    f"time:{reason}", f"a frame {reason} was dropped ({time_s} s after {last} s)"
                )
            return False
        s.time_rebases += 1
        self.report(
            f"the frame times moved from {last} s to {time_s} s and stayed there: a new time"
            " base, the estimator starts again"
        )
        self.estimator.reset()
        self.reconstructor.reset()
        self._last_delta_L_rad = None
        self._roi = None
        self.pace.reset()
        return self._accept_time(time_s, now)

    def _accept_time(self, time_s: float, now: float) -> bool:
        self._last_time_s, self._last_arrival_s = time_s, now
        self._odd_times.clear()
        return True

    # ------------------------------------------------------------------ one frame
    def _joints_at(
        self, time_s: float, frame: Frame | None
    ) -> tuple[Array, Array | None, LiveStatus]:
        if self.joints is None:
            if frame is not None:
                return np.asarray(frame.q, float), frame.q_dot, LiveStatus.NONE
            return np.zeros(3), None, LiveStatus.NO_JOINTS
        self.joints.poll()
        sample = self.joints.sample(time_s)
        status = _JOINT_STATUS[sample.status]
        q = sample.q if np.all(np.isfinite(sample.q)) else np.zeros(3)
        if sample.status is JointStatus.HELD:
            if sample.age_s > self.max_hold_s:
                status = LiveStatus.JOINTS_EXTRAPOLATED
            else:  # newer datagrams late: the newest values moved on at their rates
                q = self._moved_on(q, sample.q_dot, sample.age_s)
        return q, sample.q_dot, status

    def _prepare(self, q: Array) -> None:
        """The estimator's model at the frame's joints ``q``, if it has ``prepare(q)``."""
        if callable(prepare := getattr(self.estimator, "prepare", None)):
            with contextlib.suppress(ValueError):  # joints out of range: the step says so
                prepare(q)

    def _read_joints(self, time_s: float, frame: Frame | None, into: list) -> None:
        """The frame's joints (into ``into``) and the model at them, read meanwhile."""
        q, q_dot, status = self._joints_at(time_s, frame)
        into.append((q, q_dot, status))
        if not status & PREDICT_ONLY:
            self._prepare(q)

    def _predict_region(self, time_s: float, q: Array) -> None:
        """Where the catheter will be in the views at ``time_s`` with the joints ``q``: the
        model at the last valid estimate, px per view, for the segmentation of the frame at
        ``time_s`` (None without a valid estimate: the segmenter then searches around the
        last frame's catheter, or the whole image)."""
        self._roi = None
        if self._last_delta_L_rad is None or not np.all(np.isfinite(q)):
            return
        r = self.reconstructor
        try:
            points_b = r.catheter.outline(q, self._last_delta_L_rad, self._roi_arclengths)
        except ValueError:
            return
        points_w = r.pose.world_from_base(points_b)
        self._roi = (time_s, tuple(view.project(points_w) for view in r.rig.views))

    def _region_for(self, time_s: float) -> tuple[Array, ...] | None:
        """The region predicted for a frame at ``time_s``, if it was predicted for about then."""
        roi, period_s = self._roi, self.pace.period_s
        if roi is None or period_s is None or abs(time_s - roi[0]) > ROI_TIME_TOLERANCE * period_s:
            return None
        return roi[1]

    @staticmethod
    def _moved_on(q: Array, q_dot: Array | None, dt_s: float) -> Array:
        """Joint values ``dt_s`` later at their rates (as they are without finite rates)."""
        if q_dot is None or not np.all(np.isfinite(q_dot)):
            return q
        return q + q_dot * dt_s

    def prime(self, now: float | None = None) -> bool:
        """Get ready for the frame due: called while the loop waits; True if it primed.

        Once per frame, :data:`PRIME_LEAD_S` before the frame is due
        (:class:`~tracker.live.pacing.FramePace`): the joints are sampled at the frame's
        expected time, the catheter's region in its images is predicted from them and an
        estimator with ``prepare(q)`` computes its model at them: work the frame needs, and
        the loop's code and data back in the caches (docs/live.md). With ``rehearse``, the
        last frame is run again, its result dropped and nothing changed: its reconstruction
        and estimator step at the frame's time, and its images' segmentation, earlier by the
        time that takes; a frame that comes meanwhile stops it (a live source's). The joints
        are drained again at the end unless the frame has come. Until it comes (at most
        :data:`PRIME_WAIT_S` past its due time), the queued sinks pause (they neither take
        those caches again nor hold the interpreter) and the loop's and capture threads wait
        at the frame's priority."""
        now = self.monotonic() if now is None else now
        due_s = self.pace.due_s(self._speed)
        if self._primed:
            if now > due_s + PRIME_WAIT_S:
                self.idle.set()  # the frame is late: let the sinks work meanwhile
                self._priority.release()
            return False
        if self.prime_lead_s is None or self.joints is None:
            return False
        if now < self.priming.start_s(due_s, self.prime_lead_s):
            return False
        self._primed = True
        self.idle.clear()
        self._priority.hold((0, None if self._capture is None else self._capture.thread_id))
        time_s = self.pace.next_time_s
        self.joints.poll()
        sample = self.joints.sample(time_s)
        if sample.status in (JointStatus.OK, JointStatus.HELD):
            # Held: the newest values, moved on to the frame's time (a few ms).
            q = self._moved_on(sample.q, sample.q_dot, max(sample.age_s, 0.0))
            self._prepare(q)
            if self._images:
                self._predict_region(time_s, q)
        self._rehearse_steps(time_s)
        if finished := self._rehearse(time_s):  # else stopped by its frame, which goes first
            self.joints.poll()  # what came meanwhile: not left to the frame's critical path
        took_s, mean_s = self.monotonic() - now, self.priming.mean_s  # stopped: a lead short
        self.priming.add(took_s if finished else max(took_s, mean_s) + self.prime_lead_s)
        return True

    def wait_s(self, now: float, poll_s: float) -> float:
        """How long the loop may wait for a frame before it has something to do: drain the
        joints (every ``poll_s``) or start priming, s."""
        if self._primed or self.prime_lead_s is None or self.joints is None:
            return poll_s
        start_s = self.priming.start_s(self.pace.due_s(self._speed), self.prime_lead_s)
        return min(poll_s, max(start_s - now, 0.0))

    def _rehearse(self, time_s: float) -> bool:
        """Segment the last frame's images again, where the next frame's region is (see
        :meth:`prime`); skipped when it would take more than a fifth of the frame period
        (a machine too busy to spare it). False if a live source's frame stopped it."""
        period_s = self.pace.period_s
        if not (self.rehearse and self._images and self._last_images is not None):
            return True
        if period_s is not None and self._rehearsal_s > 0.2 * period_s:
            self._rehearsal_s *= 0.9  # try again later, when the machine may be quieter
            return True
        started, region, capture = self.monotonic(), self._region_for(time_s), self._capture
        stop = () if capture is None else (lambda: capture.waiting,)
        try:
            if self.segmenter.rehearse(self._last_images, region, *stop) is False:
                return False  # the frame came: it goes first
        except Exception as exc:  # a rehearsal must never stop the loop
            self.rehearse = False
            self.report(f"the segmentation's rehearsal failed and is off ({exc})")
            return True
        took = self.monotonic() - started
        self._rehearsal_s = took if self._rehearsal_s == 0.0 else (
            0.8 * self._rehearsal_s + 0.2 * took
        )
        return True

    def _rehearse_steps(self, time_s: float) -> None:
        """The last frame's reconstruction and estimator step again at ``time_s`` (after the
        estimator's time), changing nothing (see :meth:`prime`)."""
        if not (self.rehearse_steps and self._last_steps):
            return
        frame, observation = self._last_steps
        try:
            for owner, item in ((self.reconstructor, frame), (self.estimator, observation)):
                if callable(rehearse := getattr(owner, "rehearse", None)):
                    rehearse(dataclasses.replace(item, time_s=time_s))
        except Exception as exc:  # a rehearsal must never stop the loop
            self.rehearse_steps = False
            self.report(f"the estimator's rehearsal failed and is off ({exc})")

    def _segment(self, time_s: float, images, frame) -> tuple[SegmentedMarkers, list]:
        """The markers, and the joints if read while the segmenter waited (else [])."""
        self._last_images = images
        predicted = self._region_for(time_s)
        joints, options = [], {"settle": False} if self._settles else {}
        if self._overlaps:
            options["meanwhile"] = lambda: self._read_joints(time_s, frame, joints)
        if predicted is None and not options:
            seg = self.segmenter.segment(images)
        else:
            seg = self.segmenter.segment(images, predicted, **options)
        return SegmentedMarkers(time_s, tuple(seg.uv), tuple(seg.cov)), joints

    def step(self, item, received_s: float | None = None) -> LiveResult | None:
        """Process one source item; None when it was dropped (counted in ``summary``).

        Parameters
        ----------
        item : ImageSet, SegmentedMarkers or Frame
        received_s : float, optional
            Monotonic time the item left the source (latency reference unless the source's
            times are monotonic stamps); now if not given."""
        self.idle.clear()
        try:
            with self._priority:  # this thread stays raised from its wait (prime) on
                self._priority.release()  # the capture thread's: the wait is over
                return self._step(item, received_s)
        finally:
            self.idle.set()

    def _step(self, item, received_s: float | None) -> LiveResult | None:
        s = self.summary
        now = self.monotonic()
        received_s = now if received_s is None else received_s
        s.frames_received += 1
        is_images = isinstance(item, tuple)  # ImageSet or a plain (time, images)
        if is_images and self.segmenter is None:
            raise ValueError("the source yields images but the live loop has no segmenter")
        time_s = float(item[0] if is_images else item.time_s)
        if not self._admit(time_s, now):
            return None
        self.pace.add(time_s, received_s)
        self._primed = False
        reference = time_s if self.time_is_monotonic else received_s
        self.age.add(now - reference)

        frame = item if isinstance(item, Frame) else None
        try:
            # Segmentation first: it needs no joint values (its region was predicted after
            # the last frame), and the joints received meanwhile are drained with the rest.
            markers, joints = self._segment(time_s, item[1], frame) if is_images else (item, [])
            segmented_s = self.monotonic()
            if is_images:
                self.stages["segmentation"].add(segmented_s - now)
            q, q_dot, status = joints[0] if joints else self._joints_at(time_s, frame)
            if frame is None:
                frame = markers.frame(q, q_dot, item[1] if is_images else None)
            elif self.joints is not None:
                frame = dataclasses.replace(frame, q=q, q_dot=q_dot)
            if status & PREDICT_ONLY:
                # Predict only: markers with joints not of their time would pull it wrong.
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

        observed_s = self.monotonic()
        self.stages["joints and reconstruction"].add(observed_s - segmented_s)
        try:
            estimate = self.estimator.step(observation)
        except (ValueError, np.linalg.LinAlgError) as exc:
            status |= LiveStatus.ESTIMATOR_ERROR
            s.estimator_errors += 1
            self._report_once(f"estimator:{type(exc).__name__}", f"estimator error: {exc}")
            estimate = Estimate(time_s=time_s, delta_L_rad=math.nan, std_rad=math.nan,
                                q_r_rad=float(q[0]), flags=Flag.NO_MEASUREMENT)  # fmt: skip
        if status & INVALID and estimate.valid:
            # Held, but not of this frame's joints: not for the controller (valid bit clear).
            estimate = dataclasses.replace(estimate, delta_L_rad=math.nan, std_rad=math.nan,
                                           flags=estimate.flags | Flag.NO_MEASUREMENT)  # fmt: skip
        elif estimate.valid and not status:
            self._last_delta_L_rad = float(estimate.delta_L_rad)
        self._last_steps = None if status & PREDICT_ONLY else (frame, observation)

        self.stages["estimator"].add(self.monotonic() - observed_s)
        s.frames_processed += 1
        s.frames_valid += int(estimate.valid)
        if status:  # (a flag's test costs a microsecond: not for the usual frame)
            s.frames_stale_joints += int(bool(status & LiveStatus.STALE_JOINTS))
            s.frames_no_joints += int(bool(status & LiveStatus.NO_JOINTS))
            s.frames_clamped_joints += int(bool(status & LiveStatus.JOINTS_CLAMPED))
            s.frames_extrapolated_joints += int(bool(status & LiveStatus.JOINTS_EXTRAPOLATED))
        # The first sink's datagram carries the latency so far; the latency is until it is sent.
        sinks, result = self._sinks, (frame, observation, estimate)
        self._dispatch(sinks[:1], *result, self.monotonic() - reference, status)
        latency_s = self.monotonic() - reference
        self.latency.add(latency_s)
        self._dispatch(sinks[1:], *result, latency_s, status)
        self._images = is_images
        if is_images:
            # For the next frame, now that the controller has its estimate (again, primed).
            self._roi = None
            next_time_s = self.pace.next_time_s
            if next_time_s is not None and not status & PREDICT_ONLY:
                self._predict_region(next_time_s, self._moved_on(q, q_dot, next_time_s - time_s))
            if self._settles:
                try:
                    self.segmenter.settle()
                except Exception as exc:  # the frame's estimate has left: report, go on
                    self._report_once("settle", f"a background update failed ({exc})")
        self.cycle.add(self.monotonic() - reference)
        return LiveResult(frame, observation, estimate, latency_s, status)

    def _dispatch(self, sinks, frame, observation, estimate, latency_s, status) -> None:
        for entry in sinks:
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
    def _superseded(self) -> None:
        """Bring the count of frames a newer one replaced up to date; report the first."""
        capture = self._capture
        if capture is None or capture.dropped == self.summary.frames_superseded:
            return
        self.summary.frames_superseded = capture.dropped
        cycle = self.cycle.percentiles_ms()["p50"]
        self._report_once(
            "superseded",
            f"frames come faster than the loop takes them (it needs {cycle:.1f} ms per frame):"
            " only the newest is processed, the others are dropped and counted",
        )

    def run(
        self,
        source: Iterable,
        *,
        idle_timeout_s: float | None = None,
        max_frames: int | None = None,
        handle_signals: bool = True,
        on_start: Callable[[], None] | None = None,
    ) -> LiveSummary:
        """Process the source until it ends, idles, reaches ``max_frames`` or is interrupted.

        A ``live`` source (:mod:`tracker.live.sources`) is captured in its own thread and
        the loop takes its newest item each time (:class:`NewestOnly`). Closes every sink,
        the joint receiver and the source (if it has ``close()``) on the way out, whatever
        ended the run, and returns the summary. Exceptions other than Ctrl-C (e.g. a source
        that yields images to a loop without segmenter) propagate after that clean-up.

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
        on_start : callable, optional
            Called once Ctrl-C stops the run cleanly, before the first item (to tell the
            user what runs).
        """
        if getattr(source, "live", False) and not isinstance(source, NewestOnly):
            source = NewestOnly(source, monotonic=self.monotonic)
        self._capture = source if isinstance(source, NewestOnly) else None
        self.time_is_monotonic = bool(getattr(source, "time_is_monotonic", False))
        self._speed = getattr(source, "speed", 1.0)  # a played-back stream's pace
        self.pace.nominal_period_s = getattr(getattr(source, "source", source), "period_s", None)
        if self.summary.markers is None and getattr(source, "counts", None) is not None:
            self.summary.markers = source.counts
        stop = StopRequest()
        if handle_signals:
            stop.install()
        switch_interval_s, cv_threads = sys.getswitchinterval(), cv2.getNumThreads()
        if self.switch_interval_s is not None:
            sys.setswitchinterval(self.switch_interval_s)
        if self.cv_threads is not None:
            cv2.setNumThreads(self.cv_threads)
        started = self.monotonic()
        last_item_s = swept_s = started
        reason = "source exhausted"
        try:
            if on_start is not None:
                on_start()
            if self._capture is not None:
                self._capture.start()
            if self.affinity is not None:
                capture = self._capture
                self.affinity.apply(() if capture is None else (capture.thread_id,))
            if self.wake is not None:
                self.summary.kept_awake = self.wake.hold()
            pinned = self.affinity is not None and self.affinity.active
            self.summary.realtime = self._priority.start() if self.realtime and pinned else None
            self.collection.hold()
            if self._capture is not None:
                poll_s = self._capture.poll_s
                entries = self._capture.items(lambda: self.wait_s(self.monotonic(), poll_s))
            else:
                entries = arrivals(source, self.monotonic)
            while True:
                if stop.requested:
                    reason = "interrupted"
                    break
                if max_frames is not None and self.summary.frames_processed >= max_frames:
                    reason = "max frames"
                    break
                try:
                    entry = next(entries)
                except StopIteration:
                    reason = getattr(source, "stop_reason", None) or "source exhausted"
                    break
                now = self.monotonic()
                if entry is None:
                    if not self.prime(now) and self.joints is not None:
                        self.joints.poll()
                    if not self._primed:
                        self.collection.collect()  # none due in most waits
                    if self.affinity is not None and now - swept_s > 1.0 and not self._primed:
                        swept_s = now
                        self.affinity.sweep()  # threads the loop's thread started
                    if idle_timeout_s is not None and now - last_item_s > idle_timeout_s:
                        reason = f"no frame for {idle_timeout_s:g} s"
                        break
                    continue
                last_item_s = now
                if stop.requested:
                    reason = "interrupted"
                    break
                self._superseded()
                self.step(*entry)
                self.collection.collect()  # the estimate has left: the time to spare
        except KeyboardInterrupt:
            reason = "interrupted"
        finally:
            stop.closing = True
            self.idle.set()  # primed for a frame that never came: the sinks must not wait
            self._priority.release()
            sys.setswitchinterval(switch_interval_s)
            cv2.setNumThreads(cv_threads)
            if self.affinity is not None:
                self.affinity.restore()
            if self.wake is not None:
                self.wake.release()
            self._priority.stop()
            self.collection.release()
            self.summary.garbage_collection = self.collection.describe()
            self.summary.stop_reason = reason
            self.summary.duration_s = self.monotonic() - started
            try:
                self.close(source)
            finally:
                stop.restore()
        return self.summary

    def close(self, source: object | None = None) -> None:
        """Close every sink (even disabled ones; queued sinks finish their queue first), the
        joint receiver and the source."""
        if self._closed:
            return
        self._closed = True
        s = self.summary
        for entry in self._sinks:
            try:
                entry.sink.close()
            except Exception as exc:  # one failing close must not keep the others open
                failure = f"close failed: {type(exc).__name__}: {exc}"
                s.sink_failures.setdefault(entry.name, failure)
                self.report(f"sink {entry.name} failed to close ({exc})")
            if isinstance(entry.sink, QueuedSink):
                queued = entry.sink
                s.sink_dropped[entry.name] = queued.dropped
                s.sink_stalls[entry.name] = queued.stalls
                if queued.failure is not None:
                    s.sink_failures.setdefault(entry.name, queued.failure)
        closers = [getattr(source, "close", None)]
        if self.joints is not None:
            closers.append(self.joints.close)
        for closer in closers:
            if closer is not None:
                try:
                    closer()
                except OSError as exc:
                    self.report(f"closing failed: {exc}")
        self._superseded()
        s.age_ms = self.age.percentiles_ms()
        s.latency_ms = self.latency.percentiles_ms()
        s.latency_thirds_ms = self.latency.thirds_ms()
        s.cycle_ms = self.cycle.percentiles_ms()
        s.stage_ms = {n: r.percentiles_ms() for n, r in self.stages.items() if r.values().size}


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
    monotonic: Callable[[], float] = time.monotonic,
) -> LiveSummary:
    """Build a :class:`LiveTracker` and run it over ``source``; returns the summary."""
    tracker = LiveTracker(
        reconstructor, estimator, sinks, joints=joints, segmenter=segmenter, report=report,
        monotonic=monotonic,
    )  # fmt: skip
    return tracker.run(
        source, idle_timeout_s=idle_timeout_s, max_frames=max_frames, handle_signals=handle_signals
    )


__all__ = ["LatencyRecorder", "LiveSummary", "LiveTracker", "run_live"]
