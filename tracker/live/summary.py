"""What a live run did: :class:`LiveSummary` (counts, latencies, failures) and the ring of
latencies it reports from (:class:`LatencyRecorder`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tracker.io.udp import StreamCounts

Array = np.ndarray


class LatencyRecorder:
    """The last ``capacity`` latencies (a ring), and their percentiles."""

    def __init__(self, capacity: int = 100_000) -> None:
        self._values = np.empty(int(capacity))
        self._count = 0

    def add(self, latency_s: float) -> None:
        self._values[self._count % self._values.size] = latency_s
        self._count += 1

    def values(self) -> Array:
        """The kept latencies, oldest first, s."""
        size = self._values.size
        if self._count <= size:
            return self._values[: self._count].copy()
        return np.roll(self._values, -(self._count % size))  # the ring unrolled

    def thirds_ms(self) -> tuple[float, float, float]:
        """The median of each third of the kept latencies in the order they came, ms: a
        loop that falls behind its source shows it as a rise (NaN with fewer than three)."""
        v = self.values()
        if v.size < 3:
            return (math.nan, math.nan, math.nan)
        return tuple(1e3 * float(np.median(part)) for part in np.array_split(v, 3))

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

    frames_received: int = 0  # taken from the source by the loop
    frames_processed: int = 0
    frames_superseded: int = 0  # live source: replaced by a newer frame before the loop was free
    frames_out_of_order: int = 0
    frames_duplicate: int = 0
    frames_bad_time: dict[str, int] = field(default_factory=dict)  # by reason
    time_rebases: int = 0
    frames_rejected: int = 0  # could not be segmented or reconstructed
    frames_stale_joints: int = 0
    frames_no_joints: int = 0
    frames_clamped_joints: int = 0
    frames_extrapolated_joints: int = 0
    frames_valid: int = 0  # with a finite estimate
    estimator_errors: int = 0
    joints: StreamCounts | None = None
    markers: StreamCounts | None = None
    sink_failures: dict[str, str] = field(default_factory=dict)
    sink_dropped: dict[str, int] = field(default_factory=dict)  # queued sinks behind
    sink_stalls: dict[str, int] = field(default_factory=dict)
    age_ms: dict[str, float] = field(default_factory=dict)  # image time -> processing starts
    latency_ms: dict[str, float] = field(default_factory=dict)  # image time -> estimate sent
    # The latency's median in each third of the run (of its last 100 000 frames), ms: flat
    # unless the loop falls behind.
    latency_thirds_ms: tuple[float, ...] = ()
    cycle_ms: dict[str, float] = field(default_factory=dict)  # image time -> loop done with it
    # The loop's time per stage up to the estimate (segmentation, joints and reconstruction,
    # estimator), p50 / p99 / max each, ms: where the latency goes.
    stage_ms: dict[str, dict[str, float]] = field(default_factory=dict)
    # Whether the processors were kept out of their deep sleep states during the run
    # (tracker.live.wake; None: not asked).
    kept_awake: bool | None = None
    # Whether each frame's step ran at a real-time priority (tracker.live.priority; None:
    # not asked).
    realtime: bool | None = None
    # Whether the views after the first were segmented in a worker process, at the same time
    # ("yes", or "no (why)"; tracker.vision.parallel); None: no images segmented in parallel.
    segmentation_worker: str | None = None
    # The garbage collections run between frames (FrameCollection.describe()).
    garbage_collection: str | None = None
    duration_s: float = 0.0
    stop_reason: str = ""

    @property
    def frames_dropped(self) -> int:
        """Frames never processed: superseded, out of order, duplicate, bad time, unusable."""
        return (
            self.frames_superseded
            + self.frames_out_of_order
            + self.frames_duplicate
            + sum(self.frames_bad_time.values())
            + self.frames_rejected
        )

    @property
    def frames_without_joints(self) -> int:
        """Frames processed predict-only for lack of joint values at their time."""
        return (
            self.frames_stale_joints
            + self.frames_no_joints
            + self.frames_clamped_joints
            + self.frames_extrapolated_joints
        )

    @property
    def interrupted(self) -> bool:
        return self.stop_reason == "interrupted"

    def lines(self) -> list[str]:
        """The summary as a few human-readable lines."""
        bad_time = "".join(f", {n} {reason}" for reason, n in sorted(self.frames_bad_time.items()))
        out = [
            f"live loop ended ({self.stop_reason}) after {self.duration_s:.1f} s:"
            f" {self.frames_processed} of {self.frames_received} frames processed,"
            f" {self.frames_valid} with an estimate",
            f"  dropped: {self.frames_superseded} replaced by a newer frame while the loop was"
            f" busy, {self.frames_out_of_order} out of order, {self.frames_duplicate}"
            f" duplicate{bad_time}, {self.frames_rejected} unusable",
            f"  without joints (predict only, not valid): {self.frames_without_joints} frames"
            f" ({self.frames_stale_joints} stale, {self.frames_no_joints} before the first"
            f" sample, {self.frames_clamped_joints} before the history,"
            f" {self.frames_extrapolated_joints} past the newest sample)",
        ]
        if self.time_rebases:
            out.append(f"  new time base: {self.time_rebases} (the estimator started again)")
        for label, counts in (("joint", self.joints), ("marker", self.markers)):
            if counts is not None:
                bad = ", ".join(f"{k} {v}" for k, v in sorted(counts.malformed.items())) or "none"
                out.append(
                    f"  {label} datagrams: {counts.received} received, {counts.accepted} used,"
                    f" {counts.stale} stale, {counts.duplicate} duplicate, dropped by reason: {bad}"
                    + (f", {counts.restarts} sender restarts" if counts.restarts else "")
                )
        if self.estimator_errors:
            out.append(f"  estimator errors: {self.estimator_errors}")
        lat, cyc, age = self.latency_ms, self.cycle_ms, self.age_ms
        if lat:
            out.append(
                f"  latency image -> estimate: p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms,"
                f" max {lat['max']:.2f} ms; -> loop done: p50 {cyc['p50']:.2f} ms,"
                f" p99 {cyc['p99']:.2f} ms; age of a frame when taken: p50 {age['p50']:.2f} ms,"
                f" max {age['max']:.2f} ms"
            )
        if self.latency_thirds_ms and all(map(math.isfinite, self.latency_thirds_ms)):
            out.append(
                "  latency image -> estimate, p50 in each third of the run: "
                + " / ".join(f"{ms:.2f}" for ms in self.latency_thirds_ms)
                + " ms"
            )
        if self.stage_ms:
            out.append(
                "  time per stage, p50 / p99: "
                + ", ".join(
                    f"{name} {ms['p50']:.2f} / {ms['p99']:.2f} ms"
                    for name, ms in self.stage_ms.items()
                )
            )
        if self.kept_awake is not None:
            out.append(
                "  processors kept awake between frames: "
                + ("yes" if self.kept_awake else "no (frames may start cold)")
            )
        if self.realtime is not None:
            out.append(
                "  frames at a real-time priority: "
                + ("yes" if self.realtime else "no (other work can hold them up)")
            )
        if self.segmentation_worker is not None:
            out.append(f"  views segmented side by side: {self.segmentation_worker}")
        if self.garbage_collection is not None:
            out.append(f"  garbage collected between frames: {self.garbage_collection}")
        for name in sorted(set(self.sink_dropped) | set(self.sink_stalls)):
            dropped, stalls = self.sink_dropped.get(name, 0), self.sink_stalls.get(name, 0)
            if dropped or stalls:
                out.append(
                    f"  sink {name} fell behind: {dropped} frames dropped, {stalls} waits"
                )
        for name, failure in self.sink_failures.items():
            out.append(f"  sink {name} disabled: {failure}")
        return out

    def __str__(self) -> str:
        return "\n".join(self.lines())
