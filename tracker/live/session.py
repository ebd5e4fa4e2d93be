"""One live session: the loop wired to its joint receiver and to every output (docs/live.md).

``cathtrack track`` and ``cathtrack demo`` both build their loop here from a
:class:`SessionSettings`; they differ only in the frames they feed it (cameras, video files,
UDP markers or a recording; simulated cameras) and, for the demo, a simulated controller at the
other end of the sockets and estimators run alongside for comparison::

    with LiveSession(settings, scene, rerun_args=args, segmenter=segmenter) as session:
        source = VideoSource(0, 1)
        summary = session.run(source)
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from models.pose import Pose
from models.rig_file import rig_toml
from tracker.estimators import make_estimator
from tracker.io.igtl import IgtlSink
from tracker.io.recording import VIEWS, RecordingWriter
from tracker.io.udp import (
    DEFAULT_ESTIMATE_PORT,
    DEFAULT_JOINT_PORT,
    LOOPBACK,
    EstimateSender,
    JointReceiver,
)
from tracker.live.loop import LiveSummary, LiveTracker
from tracker.live.sinks import CsvSink, QueuedSink, RecordingSink, Sink
from tracker.reconstruction import Reconstructor
from tracker.viewer.layout import default_blueprint
from tracker.viewer.output import RerunOutput, open_rerun_output
from tracker.viewer.sink import FILE_FLUSH_EVERY_S, LiveViewerSink, RerunSink
from tracker.vision.pair import PairSegmenter
from tracker.vision.parallel import ParallelPairSegmenter

LONG_FLUSH_TICK_S = 3600.0
"""The rerun stream's own flush period in a live session, s: never, in effect; the viewer
sink flushes once a frame's estimate has left (:class:`LiveViewerSink`), and rerun when
2 MiB have piled up, which happens while the sink logs."""


def _report_stderr(message: str) -> None:
    print(f"cathtrack: {message}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class SessionSettings:
    """What a live session listens on and sends to.

    Parameters
    ----------
    estimator : str
        The loop's estimator (:func:`tracker.estimators.make_estimator`).
    bind : str
        Address of every listener: joints, OpenIGTLink, the rerun gRPC server.
    joints_port : int or None
        UDP port of the joint datagrams (0: one the OS picks); None: no joint receiver, the
        frames bring their own joint values (a recording).
    joint_clock : {"aligned", "sender", "arrival"}
        Time base of the joint samples (:class:`tracker.io.udp.JointReceiver`).
    estimate_to : (host, port) or None
        Where the estimate datagrams go (None: nowhere).
    igtl_port : int or None
        Serve OpenIGTLink transforms for 3D Slicer on this port.
    record_path, csv_path : str or Path, optional
        Record the session (MCAP); write one CSV row per frame.
    live_clock : bool
        Frame times are this machine's ``time.monotonic()`` (cameras, joints over UDP): the
        recording's log times become wall-clock time. False for a recording played back.
    images : bool
        Images in rerun at all...
    image_every : int
        ...of every n-th frame (the markers of every frame).
    jpeg_quality : int or None
        JPEG quality of the images in rerun (None: raw).
    application_id : str
        Of the rerun recording.
    keep_serving : bool
        With ``--serve``, keep the rerun stream open after the run, for web viewers to look
        (:meth:`LiveSession.close` ends it).
    queued : bool
        Every output but the estimate datagram in a thread of its own behind a queue (live
        runs). False: every output on the loop's thread, every frame (a recording played as
        fast as possible, where nothing runs in real time).
    viewer_queue, igtl_queue : int
        Frames queued for the rerun output and for OpenIGTLink; when full, the oldest is
        dropped (counted).
    record_queue : int
        Frames queued for the recording and the CSV file, which never drop: when full, the
        loop waits (a loud warning, counted).
    pin : bool
        The loop's thread on a processor of its own during the run, the other threads and
        child processes off it (:class:`tracker.live.affinity.LoopAffinity`).
    keep_awake : bool
        The processors kept out of their deep sleep states during the run
        (:class:`tracker.live.wake.WakeLatency`).
    collect_between_frames : bool
        Python's garbage collection run between frames, never within one
        (:class:`tracker.live.collection.FrameCollection`).
    realtime : bool
        Each frame's step at a real-time priority, where permitted
        (:class:`tracker.live.priority.FramePriority`).
    """

    estimator: str = "ukf"
    bind: str = LOOPBACK
    joints_port: int | None = DEFAULT_JOINT_PORT
    joint_clock: str = "aligned"
    estimate_to: tuple[str, int] | None = (LOOPBACK, DEFAULT_ESTIMATE_PORT)
    igtl_port: int | None = None
    record_path: str | Path | None = None
    csv_path: str | Path | None = None
    live_clock: bool = True
    images: bool = True
    image_every: int = 2
    jpeg_quality: int | None = 80
    application_id: str = "cathtrack"
    keep_serving: bool = False
    queued: bool = True
    viewer_queue: int = 32
    igtl_queue: int = 8
    record_queue: int = 512
    pin: bool = True
    keep_awake: bool = True
    collect_between_frames: bool = True
    realtime: bool = True

    def __post_init__(self) -> None:
        if self.image_every < 1:
            raise ValueError(f"image_every must be >= 1, got {self.image_every}")
        for name in ("viewer_queue", "igtl_queue", "record_queue"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


def _behind_queue(
    settings: SessionSettings, sink: Sink, capacity: int, keep_all: bool, report
) -> Sink:
    """``sink`` in a thread of its own behind a queue, unless the settings say otherwise."""
    if not settings.queued:
        return sink
    return QueuedSink(sink, capacity, keep_all=keep_all, report=report)


class LiveSession:
    """The live loop with its joint receiver and outputs, opened from :class:`SessionSettings`.

    Opens, in this order: the estimate sender, the OpenIGTLink server and the rerun outputs
    (a port in use fails before anything listens), the joint receiver, the recording and the
    CSV file; if one fails, what was already open is closed again. The sinks run in that
    order. Only the estimate sender runs on the loop's thread (the latency is measured for
    it); every other output is a :class:`~tracker.live.sinks.QueuedSink` with its own thread
    and queue (sizes in the settings): the viewer and OpenIGTLink drop their oldest frame when
    they fall behind, the recording and the CSV file never drop. From then on the loop owns
    them: :meth:`run` closes them all, and so does :meth:`close` (or leaving a ``with`` block)
    when the run never started.

    Parameters
    ----------
    settings : SessionSettings
    scene : replay.simulation.simulator.Scene or anything with catheter, rig, R_w_b, o_b_w_mm
        The catheter model, the rig and the registered base pose.
    rerun_args : argparse.Namespace, optional
        The flags of :func:`tracker.viewer.output.add_rerun_args` (None: no rerun output).
    segmenter : PairSegmenter or ParallelPairSegmenter, optional
        For sources that yield images; its backgrounds go into the recording. The caller
        closes it (a ParallelPairSegmenter's worker process) once the session is over.
    model_toml : str, optional
        The catheter model file's text, stored in the recording (needed with ``record_path``).
    record_metadata : mapping, optional
        What made the session, stored in the recording.
    viewer_methods : sequence of str
        Further estimators that other sinks log to :attr:`viewer` (their series in the
        blueprint).
    truth : callable, optional
        Image time (s) -> true delta_L (rad) or None, drawn in rerun (simulations).
    report : callable
        Receives one line per problem.

    Attributes
    ----------
    tracker : LiveTracker
    joints : JointReceiver or None
    sender : EstimateSender or None
    igtl : IgtlSink or None
    output : tracker.viewer.output.RerunOutput or None
    viewer : RerunSink or None
        The rerun stream, for sinks that log more to it...
    viewer_thread : QueuedSink or None
        ...from its thread only (:meth:`QueuedSink.submit`; rerun's time is per thread),
        when the outputs are queued.
    inputs, outputs : list of str
        What the session listens to and sends to, for the user.
    """

    def __init__(
        self,
        settings: SessionSettings,
        scene,
        *,
        rerun_args=None,
        segmenter: PairSegmenter | ParallelPairSegmenter | None = None,
        model_toml: str | None = None,
        record_metadata: Mapping[str, Any] | None = None,
        viewer_methods: Sequence[str] = (),
        truth: Callable[[float], float | None] | None = None,
        report: Callable[[str], None] = _report_stderr,
    ) -> None:
        if settings.record_path is not None and model_toml is None:
            raise ValueError("recording a session needs the catheter model's text")
        self.settings = settings
        self.scene = scene
        self.segmenter = segmenter
        self.report = report
        catheter, rig = scene.catheter, scene.rig
        R_w_b, o_b_w_mm = scene.R_w_b, scene.o_b_w_mm
        estimator = make_estimator(settings.estimator, catheter)
        self.joints: JointReceiver | None = None
        self.sender: EstimateSender | None = None
        self.igtl: IgtlSink | None = None
        self.output: RerunOutput | None = None
        self.viewer: RerunSink | None = None
        self.viewer_thread: QueuedSink | None = None
        self.inputs: list[str] = []
        self.outputs: list[str] = []
        sinks: list[Sink] = []
        viewer_sink = None
        with contextlib.ExitStack() as stack:  # closes what was opened if the set-up fails
            # ---- outputs first (a port in use fails before anything listens)
            if settings.estimate_to is not None:
                self.sender = EstimateSender(settings.estimate_to, report=report)
                stack.callback(self.sender.close)
                sinks.append(self.sender)
                host, port = self.sender.address
                self.outputs.append(f"estimates to udp://{host}:{port}")
            if settings.igtl_port is not None:
                self.igtl = IgtlSink(
                    catheter,
                    R_w_b,
                    o_b_w_mm,
                    host=settings.bind,
                    port=settings.igtl_port,
                    report=report,
                )
                stack.callback(self.igtl.close)
                sinks.append(
                    _behind_queue(settings, self.igtl, settings.igtl_queue, False, report)
                )
                self.outputs.append(f"OpenIGTLink on tcp://{self.igtl.host}:{self.igtl.port}")
            if rerun_args is not None:
                blueprint = default_blueprint(
                    [settings.estimator, *viewer_methods], live=True, scene=scene
                )
                self.output = open_rerun_output(
                    rerun_args,
                    settings.application_id,
                    blueprint=blueprint,
                    recording_name=settings.application_id,
                    start_time_ns=time.time_ns(),
                    bind=settings.bind,
                    report=report,
                    flush_tick_s=LONG_FLUSH_TICK_S,  # the viewer sink flushes (LiveViewerSink)
                )
            if self.output is not None:
                watched_live = bool(self.output.viewer_url or self.output.served_url)
                self.viewer = RerunSink(
                    self.output.stream,
                    primary=settings.estimator,
                    jpeg_quality=settings.jpeg_quality,
                    time_origin_s=None,  # live times are monotonic stamps: the first frame's
                )
                stack.callback(self.viewer.close)
                viewer_sink = LiveViewerSink(
                    self.viewer,
                    scene,
                    settings.estimator,
                    images=settings.images,
                    image_every=settings.image_every,
                    truth=truth,
                    watch=self.output.watch(),
                    report=report,
                    close_stream=not (settings.keep_serving and self.output.served_url),
                    flush_every_s=0.0 if watched_live else FILE_FLUSH_EVERY_S,
                )
                stack.callback(viewer_sink.close)  # stops the viewer watch too
                sinks.append(
                    _behind_queue(settings, viewer_sink, settings.viewer_queue, False, report)
                )
                if isinstance(sinks[-1], QueuedSink):
                    self.viewer_thread = sinks[-1]
                self.outputs.extend(f"rerun {target}" for target in self.output.targets)

            # ---- inputs
            if settings.joints_port is not None:
                self.joints = JointReceiver(
                    settings.bind, settings.joints_port, clock=settings.joint_clock
                )
                stack.callback(self.joints.close)
                host, port = self.joints.address
                self.inputs.append(f"joints on udp://{host}:{port} ({settings.joint_clock} clock)")

            # ---- files
            if settings.record_path is not None:
                writer = RecordingWriter(
                    settings.record_path,
                    model_toml=model_toml,
                    rig_toml=rig_toml(rig, Pose(R_w_b, o_b_w_mm)),
                    settings=record_metadata,
                    point_unit="px" if rig.kind == "pinhole" else "mm",
                    # Live time stamps are monotonic seconds: log times become wall-clock time.
                    start_time_ns=(
                        time.time_ns() - time.monotonic_ns() if settings.live_clock else 0
                    ),
                )
                stack.callback(writer.close)
                if segmenter is not None:
                    for view, background in zip(VIEWS, segmenter.backgrounds, strict=True):
                        writer.write_background(view, background)
                recording = RecordingSink(writer, settings.estimator, joints=self.joints)
                sinks.append(
                    _behind_queue(settings, recording, settings.record_queue, True, report)
                )
                self.outputs.append(f"recording {settings.record_path}")
            if settings.csv_path is not None:
                csv_sink = CsvSink(settings.csv_path)
                stack.callback(csv_sink.close)
                sinks.append(
                    _behind_queue(settings, csv_sink, settings.record_queue, True, report)
                )
                self.outputs.append(f"CSV {settings.csv_path}")

            self.tracker = LiveTracker(
                Reconstructor(catheter, rig, R_w_b, o_b_w_mm),
                estimator,
                sinks,
                joints=self.joints,
                segmenter=segmenter,
                report=report,
                pin=settings.pin,
                keep_awake=settings.keep_awake,
                collect_between_frames=settings.collect_between_frames,
                realtime=settings.realtime,
            )
            if viewer_sink is not None:
                viewer_sink.summary = self.tracker.summary
            stack.pop_all()  # from here the loop closes every sink and the joint receiver

    def run(
        self,
        source: Iterable,
        *,
        idle_timeout_s: float | None = None,
        max_frames: int | None = None,
        announce: Callable[[], None] | None = None,
    ) -> LiveSummary:
        """Run the loop over ``source`` until it ends, idles, has ``max_frames`` or Ctrl-C.

        Closes every sink, the joint receiver and the source; returns the loop's summary.
        ``announce`` is called once Ctrl-C stops the run cleanly (to tell the user what runs):
        a Ctrl-C from then on ends the run with its summary, whenever it comes.
        """
        try:
            summary = self.tracker.run(
                source, idle_timeout_s=idle_timeout_s, max_frames=max_frames, on_start=announce
            )
        except KeyboardInterrupt:  # Ctrl-C before the loop took it over: close all the same
            self.tracker.close(source)
            summary = self.tracker.summary
            summary.stop_reason = "interrupted"
        if isinstance(self.segmenter, ParallelPairSegmenter):
            summary.segmentation_worker = self.segmenter.describe()
        return summary

    def close(self) -> None:
        """Close everything the session opened (nothing happens twice)."""
        try:
            self.tracker.close()
        finally:
            if self.viewer is not None:
                self.viewer.close()

    def __enter__(self) -> LiveSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
