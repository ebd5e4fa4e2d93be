"""``cathtrack demo``: the live loop end to end on an embedded simulated rig.

A simulated controller, in a process of its own, streams the joint values of a session at
1 kHz as UDP datagrams over loopback; two simulated cameras (:mod:`~replay.simulation.render`,
default rendering rig: 640x480, f = 2500 px, 400 mm away) deliver the bi-plane images of the
catheter at 20 fps: rendered ahead of time in another process
(:class:`replay.simulation.sources.SimulatedCameras`), released at their exposure times and
stamped on the same monotonic clock as the joints. The live session
(:class:`tracker.live.session.LiveSession`, the same wiring as ``cathtrack track``) receives the
joints on a real socket, interpolates them to each image time, segments the newest pair
(:class:`tracker.vision.pair.PairSegmenter`), reconstructs the markers, runs the UKF and sends
every estimate back to the controller as a UDP datagram. The closed-form Tip Position
estimator runs on the same observations for comparison, in a thread of its own like every
output. Everything goes to rerun (an ``.rrd`` file, and a viewer if asked for); at the end the
accuracy of each method and the loop's latency are printed.

The estimators never see the truth: it is known to the simulated cameras only and joins the
frames in the sinks that score and draw them.
"""

from __future__ import annotations

import functools
import math
import multiprocessing
import select
import signal
import socket
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from models.catheter import default_catheter
from models.rotations import wrap_angle
from replay.compile_ahead import SlowSetUpNotice
from replay.simulation.render import ImagingNuisance, Renderer, RenderSettings, default_render_rig
from replay.simulation.simulator import default_scene
from replay.simulation.sources import SimulatedCameras, session_joints, simulated_session
from tracker.estimators import make_estimator
from tracker.io.datagrams import DatagramError, decode_estimate
from tracker.io.udp import LOOPBACK, JointStreamer
from tracker.live.loop import LiveSummary
from tracker.live.session import LiveSession, SessionSettings
from tracker.live.sinks import LiveStatus, QueuedSink
from tracker.types import Estimate
from tracker.viewer.output import serve_until_interrupted
from tracker.viewer.sink import RerunSink
from tracker.vision.parallel import pair_segmenter

Array = np.ndarray

COMPARE_METHOD = "tip-position"


@dataclass(frozen=True)
class DemoSettings:
    """What the demo simulates and how it logs.

    Parameters
    ----------
    seconds : float
        Length of the session, s (it runs in real time).
    frame_rate_hz, joint_rate_hz : float
        Image pairs and joint datagrams per second.
    seed : int
        Seeds the rendered scene and the sensor noise.
    estimator : str
        The loop's estimator (its estimates go back to the controller).
    compare : tuple of str
        Estimators run on the same observations for the table and the plots.
    images, image_every, jpeg_quality :
        Images in the rerun recording: at all, every n-th pair, JPEG quality.
    start_delay_s : float
        Time between setting up and the first exposure (sockets ready, first pair rendered).
    image_noise_gray : float
        Sensor noise of the rendered images, gray levels.
    image_nuisance : ImagingNuisance
        How each frame differs from the backgrounds (gain drift and flicker, offset, gamma,
        vibration, a moved camera; none by default).
    keep_awake : bool
        The processors kept out of their deep sleep states while the loop runs
        (:class:`tracker.live.wake.WakeLatency`; where permitted).
    segmentation_worker : bool
        The views after the first segmented in a worker process, at the same time as the
        first (:mod:`tracker.vision.parallel`; with two processors or more).
    collect_between_frames : bool
        Python's garbage collection run between frames only
        (:class:`tracker.live.collection.FrameCollection`).
    realtime : bool
        Each frame's work (the loop's and the worker's) at a real-time priority, where
        permitted (:class:`tracker.live.priority.FramePriority`).
    """

    seconds: float = 15.0
    frame_rate_hz: float = 20.0
    joint_rate_hz: float = 1000.0
    seed: int = 0
    estimator: str = "ukf"
    compare: tuple[str, ...] = (COMPARE_METHOD,)
    images: bool = True
    image_every: int = 2
    jpeg_quality: int = 80
    start_delay_s: float = 0.3
    image_noise_gray: float = RenderSettings().noise_sigma_gray
    image_nuisance: ImagingNuisance = ImagingNuisance()
    keep_awake: bool = True
    segmentation_worker: bool = True
    collect_between_frames: bool = True
    realtime: bool = True

    def __post_init__(self) -> None:
        if not self.seconds > 0:
            raise ValueError(f"the session must last a positive time, got {self.seconds} s")
        if self.seconds * self.frame_rate_hz < 2:
            raise ValueError("the demo needs at least 2 frames: give more --seconds")
        for name in ("frame_rate_hz", "joint_rate_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


# -------------------------------------------------------------------------- controller
def _joints_before(joints_at: Callable, lead_s: float, time_s: float):
    """The motion ``joints_at`` for a stream started ``lead_s`` before its time 0."""
    return joints_at(time_s - lead_s)


def _controller(conn, joints_at: Callable, rate_hz: float) -> None:
    """The simulated controller's process: joints out at ``rate_hz``, estimates in, counted.

    Speaks over ``conn``: sends its estimate address; takes ``("start", joints_to,
    start_s, lead_s)`` and then ``("stop", expected, timeout_s)``, after which it waits up to
    ``timeout_s`` for ``expected`` estimates and answers with its counts.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the demo's to handle
    counts = {"received": 0, "valid": 0, "malformed": 0, "sent": 0}
    streamer = None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.bind((LOOPBACK, 0))
        conn.send(sock.getsockname())
        expected, deadline = None, math.inf
        while expected is None or (counts["received"] < expected and time.monotonic() < deadline):
            timeout = 0.5 if expected is None else max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([sock, conn], [], [], timeout)
            if sock in ready:
                try:
                    message = decode_estimate(sock.recv(256))
                    counts["received"] += 1
                    counts["valid"] += int(message.valid)
                except DatagramError:
                    counts["malformed"] += 1
            if conn in ready:
                try:
                    command = conn.recv()
                except EOFError:  # the demo has gone
                    break
                if command[0] == "start":
                    _, joints_to, start_s, lead_s = command
                    # Streaming from lead_s before the session's time 0, as a controller
                    # that runs before the cameras start.
                    motion = functools.partial(_joints_before, joints_at, lead_s)
                    streamer = JointStreamer(joints_to, motion, rate_hz, start_s=start_s - lead_s)
                    streamer.start()
                else:
                    if streamer is not None:
                        streamer.stop()
                        counts["sent"] = streamer.sent
                    expected = command[1] if command[1] is not None else 0
                    deadline = time.monotonic() + command[2]
        if streamer is not None and expected is None:
            streamer.stop()
    try:
        conn.send(counts)
    except OSError:
        pass


class SimulatedController:
    """The robot controller's side, in its own process: joints out at 1 kHz, estimates in.

    Its estimate socket (loopback, a port the OS picks: :attr:`estimate_address`) is open from
    the start and counts the estimate datagrams; :meth:`start` then streams the joint
    datagrams (:class:`tracker.io.udp.JointStreamer`). A process of its own, as a real
    controller is another machine: its 1 kHz never competes with the loop for the
    interpreter.

    Parameters
    ----------
    joints_at : callable
        Seconds since ``start_s`` -> (q, q_dot); a module-level function (it is sent to the
        process).
    rate_hz : float
    """

    def __init__(
        self, joints_at: Callable[[float], tuple[Array, Array]], rate_hz: float
    ) -> None:
        self.rate_hz = float(rate_hz)
        self.received = self.valid = self.malformed = self.sent = 0
        self.lost: str | None = None  # why the counts did not come back, if they did not
        context = multiprocessing.get_context("spawn")  # no fork of a threaded process
        self._conn, child = context.Pipe()
        self._process = context.Process(
            target=_controller, args=(child, joints_at, self.rate_hz), name="controller",
            daemon=True,
        )
        self._process.start()
        child.close()
        if not self._conn.poll(120.0):
            self._process.terminate()
            raise RuntimeError("the simulated controller did not start")
        self.estimate_address: tuple[str, int] = tuple(self._conn.recv())
        self._stopped = False

    def start(
        self, joints_to: tuple[str, int], start_s: float, lead_s: float = 0.0
    ) -> SimulatedController:
        """Stream the motion's joints to ``joints_to``, its time 0 at ``start_s`` (monotonic),
        from ``lead_s`` before it: sample ``k`` at ``start_s - lead_s + k / rate_hz``."""
        self._conn.send(("start", tuple(joints_to), float(start_s), float(lead_s)))
        return self

    def stop(self, expected: int | None = None, timeout_s: float = 1.0) -> None:
        """Stop streaming joints; wait (up to ``timeout_s``) for ``expected`` estimates."""
        if self._stopped:
            return
        self._stopped = True
        try:
            self._conn.send(("stop", expected, float(timeout_s)))
            if self._conn.poll(timeout_s + 5.0):
                counts = self._conn.recv()
                self.received, self.valid = counts["received"], counts["valid"]
                self.malformed, self.sent = counts["malformed"], counts["sent"]
            else:
                self.lost = f"the controller process did not answer within {timeout_s + 5.0:g} s"
        except (OSError, EOFError) as exc:
            self.lost = f"the controller process ended ({type(exc).__name__})"
        self._process.join(2.0)
        if self._process.is_alive():
            self._process.terminate()
        self._conn.close()


# ------------------------------------------------------------------------------ sinks
@dataclass
class MethodScore:
    """One method's estimates and the truth at their times (rad)."""

    name: str
    estimates: list[Estimate] = field(default_factory=list)
    truth_rad: list[float] = field(default_factory=list)

    def add(self, estimate: Estimate, truth_rad: float | None) -> None:
        self.estimates.append(estimate)
        self.truth_rad.append(math.nan if truth_rad is None else float(truth_rad))

    def row(self) -> dict[str, float]:
        """RMS, median absolute, max absolute error (deg), valid fraction, 2-sigma coverage."""
        n = len(self.estimates)
        valid = np.array([e.valid for e in self.estimates], dtype=bool)
        truth = np.array(self.truth_rad, dtype=float)
        scored = valid & np.isfinite(truth)
        delta_L = np.array([e.delta_L_rad for e in self.estimates], dtype=float)
        std = np.array([e.std_rad for e in self.estimates], dtype=float)
        err = np.abs(wrap_angle(delta_L[scored] - truth[scored]))
        if err.size == 0:
            nan = math.nan
            return dict(rms_deg=nan, median_deg=nan, max_deg=nan, valid=0.0, coverage=nan, n=n)
        return dict(
            rms_deg=float(np.degrees(np.sqrt(np.mean(err**2)))),
            median_deg=float(np.degrees(np.median(err))),
            max_deg=float(np.degrees(np.max(err))),
            valid=float(np.mean(valid)) if n else 0.0,
            coverage=float(np.mean(err <= 2 * std[scored])),
            n=n,
        )


class ScoreSink:
    """Scores the loop's estimator and runs the comparison estimators (a live-loop sink).

    Each comparison estimator steps on the loop's observation of the frame, so all methods
    see exactly the same reconstructed markers; their estimates go to the viewer too, logged
    in the viewer's own thread (rerun's time is per thread). The demo runs this sink behind a
    :class:`~tracker.live.sinks.QueuedSink` that keeps every frame.

    Parameters
    ----------
    method : str
        The loop's estimator.
    others : mapping of name to estimator
    truth : callable
        Image time -> true delta_L (rad) or None.
    viewer : RerunSink, optional
    viewer_thread : QueuedSink, optional
        The viewer's sink thread (:attr:`LiveSession.viewer_thread`): the comparison
        estimates are logged there; without it, here.
    """

    name = "score"

    def __init__(
        self,
        method: str,
        others: dict,
        truth: Callable,
        viewer: RerunSink | None = None,
        viewer_thread: QueuedSink | None = None,
    ) -> None:
        self.truth, self.others = truth, others
        self.viewer, self.viewer_thread = viewer, viewer_thread
        self.scores = {name: MethodScore(name) for name in (method, *others)}
        self.method = method

    def handle(self, frame, observation, estimate, latency_s, status=LiveStatus.NONE) -> None:
        truth = self.truth(frame.time_s)
        self.scores[self.method].add(estimate, truth)
        for name, estimator in self.others.items():
            other = estimator.step(observation)
            self.scores[name].add(other, truth)
            if self.viewer is None:
                continue
            log = functools.partial(self.viewer.log_estimate, name, other, truth)
            if self.viewer_thread is not None:
                self.viewer_thread.submit(log)
            else:
                log()

    def close(self) -> None:
        """Nothing to release: the viewer sink this one writes through is closed on its own."""


@dataclass(frozen=True)
class DemoResult:
    """What a demo run measured (for benchmarks; the table prints the same)."""

    summary: LiveSummary
    scores: dict[str, MethodScore]
    estimates_sent: int
    estimates_received: int
    late_frames: int
    render_ms: float


# ------------------------------------------------------------------------------ report
def _ms(value: float) -> str:
    return f"{value:.1f}" if math.isfinite(value) else "-"


def header_line(settings: DemoSettings) -> str:
    """What is about to run (printed first: the run takes its length in real time)."""
    frames = int(round(settings.seconds * settings.frame_rate_hz))
    return (
        f"cathtrack demo: {settings.seconds:g} s simulated session in real time, {frames}"
        f" bi-plane image pairs (640x480, f = 2500 px) at {settings.frame_rate_hz:g} fps"
        f" rendered ahead in a process of their own and segmented live, joints at"
        f" {settings.joint_rate_hz:g} Hz over loopback UDP from a controller process, torsion"
        f" wind-up 120 deg with 60 deg of play, seed {settings.seed}"
    )


def report_lines(
    settings: DemoSettings,
    scores: dict[str, MethodScore],
    summary: LiveSummary,
    controller: SimulatedController,
    estimates_sent: int,
    rrd_path: Path | None,
    viewers: Sequence[str],
    late_frames: int,
) -> list[str]:
    """The printed result: an accuracy table per method, then the live loop's figures."""
    lines = [
        "",
        "| method | RMS error (deg) | median abs (deg) | max abs (deg) | valid frames |"
        " within 2 sigma |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, score in scores.items():
        r = score.row()
        role = " (live, sent)" if name == settings.estimator else " (same observations)"
        lines.append(
            f"| {name}{role} | {r['rms_deg']:.2f} | {r['median_deg']:.2f} | {r['max_deg']:.2f} |"
            f" {100 * r['valid']:.0f}% | {100 * r['coverage']:.0f}% |"
        )
    lat, cyc = summary.latency_ms, summary.cycle_ms
    joints = summary.joints
    stages = [  # where the latency goes
        "| of which " + " / ".join(summary.stage_ms) + ", p50 (ms) | "
        + " / ".join(_ms(ms["p50"]) for ms in summary.stage_ms.values()) + " |"
    ] if summary.stage_ms else []  # fmt: skip
    lines += [
        "",
        "| live loop | |",
        "|---|---:|",
        f"| frames processed / dropped / predict-only | {summary.frames_processed} /"
        f" {summary.frames_dropped} / {summary.frames_without_joints} |",
        f"| pairs dropped for a newer one (loop busy) | {summary.frames_superseded} |",
        f"| latency image -> estimate sent, p50 / p99 (ms) | {_ms(lat.get('p50', math.nan))} /"
        f" {_ms(lat.get('p99', math.nan))} |",
        *stages,
        "| latency p50 in each third of the run (ms) | "
        + (" / ".join(_ms(ms) for ms in summary.latency_thirds_ms) or "-") + " |",
        f"| latency image -> loop done, p50 / p99 (ms) | {_ms(cyc.get('p50', math.nan))}"
        f" / {_ms(cyc.get('p99', math.nan))} |",
        f"| estimates per second | {summary.frames_processed / max(summary.duration_s, 1e-9):.1f}"
        " |",
    ]
    if joints is not None:
        lines.append(f"| joint datagrams received / used | {joints.received} / {joints.accepted} |")
    received = (
        f"{controller.received} of {estimates_sent} sent ({controller.valid} valid)"
        if controller.lost is None
        else f"unknown: {controller.lost}"
    )
    lines.append(f"| estimates received by the controller | {received} |")
    for name in sorted(set(summary.sink_dropped) | set(summary.sink_stalls)):
        dropped, stalls = summary.sink_dropped.get(name, 0), summary.sink_stalls.get(name, 0)
        lines.append(f"| {name}: frames dropped / waits (behind) | {dropped} / {stalls} |")
    lines.append(f"| image pairs rendered too late for real time | {late_frames} |")
    if summary.kept_awake is not None:
        awake = "yes" if summary.kept_awake else "no (frames may start cold)"
        lines.append(f"| processors kept awake between frames | {awake} |")
    if summary.realtime is not None:
        realtime = "yes" if summary.realtime else "no (other work can hold them up)"
        lines.append(f"| frames at a real-time priority (loop and worker) | {realtime} |")
    if summary.segmentation_worker is not None:
        lines.append(
            f"| views segmented side by side (a worker process) | {summary.segmentation_worker} |"
        )
    if summary.garbage_collection is not None:
        lines.append(f"| garbage collected between frames | {summary.garbage_collection} |")
    if rrd_path is not None:
        size = rrd_path.stat().st_size / 1e6 if rrd_path.exists() else math.nan
        lines.append(f"| rerun recording | {rrd_path} ({size:.1f} MB) |")
    for viewer in viewers:
        lines.append(f"| rerun | {viewer} |")
    lines += ["", f"stopped: {summary.stop_reason}"]
    if rrd_path is not None:
        lines.append(f"view it: rerun {rrd_path}")
    return lines


def _report_stderr(message: str) -> None:
    print(f"cathtrack demo: {message}", file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------- run
def run_demo(
    settings: DemoSettings,
    rerun_args,
    *,
    out: Callable[[str], None] = print,
    report: Callable[[str], None] = _report_stderr,
    on_result: Callable[[DemoResult], None] | None = None,
) -> int:
    """Run the demo; print its table with ``out``. Returns 0, or 130 after Ctrl-C.

    Parameters
    ----------
    settings : DemoSettings
    rerun_args : argparse.Namespace
        The flags of :func:`tracker.viewer.output.add_rerun_args` (``save``, ``connect``...).
    on_result : callable, optional
        Receives the :class:`DemoResult` once the run is over.
    """
    catheter = default_catheter()
    scene = default_scene(catheter, default_render_rig())
    session = simulated_session(
        settings.seconds,
        settings.frame_rate_hz,
        noise=0.0,
        seed=settings.seed,
        catheter=catheter,
        rig=scene.rig,
    )
    renderer = Renderer(
        catheter,
        scene.rig,
        scene.R_w_b,
        scene.o_b_w_mm,
        RenderSettings(noise_sigma_gray=settings.image_noise_gray),
        seed=settings.seed,
        nuisance=settings.image_nuisance,
    )
    compare = tuple(m for m in settings.compare if m != settings.estimator)
    notice = SlowSetUpNotice(report)  # the kernels, compiled if not cached
    with notice.during():
        segmenter = pair_segmenter(
            catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm, renderer.backgrounds,
            parallel=None if settings.segmentation_worker else False, report=report,
            realtime=settings.realtime,
        )
        others = {name: make_estimator(name, catheter) for name in compare}
    # The cameras and the controller are processes of their own, started first: they come
    # up while the session is set up.
    cameras = SimulatedCameras(
        renderer, session.frames, settings.seed, 0.5 / settings.frame_rate_hz
    )
    controller = None
    summary = None
    try:
        controller = SimulatedController(session_joints, settings.joint_rate_hz)
        # The loop's joint receiver and the controller's estimate socket: loopback, ports the
        # OS picks. With --serve the rerun stream stays open after the run, for web viewers.
        live_settings = SessionSettings(
            estimator=settings.estimator,
            bind=LOOPBACK,
            joints_port=0,
            joint_clock="sender",
            estimate_to=controller.estimate_address,
            images=settings.images,
            image_every=settings.image_every,
            jpeg_quality=settings.jpeg_quality,
            application_id="cathtrack-demo",
            keep_serving=True,
            keep_awake=settings.keep_awake,
            collect_between_frames=settings.collect_between_frames,
            realtime=settings.realtime,
        )
        with notice.during():  # the session's estimator
            live_session = LiveSession(
                live_settings,
                scene,
                rerun_args=rerun_args,
                segmenter=segmenter,
                viewer_methods=compare,
                truth=cameras.truth,
                report=report,
            )
        with live_session as live:
            scorer = ScoreSink(
                settings.estimator, others, cameras.truth, live.viewer, live.viewer_thread
            )
            # Every frame scored; closed before the viewer, whose thread logs its estimates.
            live.tracker.add_sink(
                QueuedSink(scorer, 1 << 16, keep_all=True, report=report),
                before=live.viewer_thread,
            )
            out(header_line(settings))
            if live.output is not None:
                out(f"cathtrack demo: rerun to {'; '.join(live.output.targets)}")
            started = time.monotonic()
            ahead = min(len(session.frames), cameras.max_ahead)
            if ahead > 400:  # more than half a minute on a slow machine: say what it waits for
                out(f"cathtrack demo: rendering {ahead} image pairs ahead ...")
            ready = cameras.render_ahead()
            out(
                f"cathtrack demo: {ready} image pairs rendered ahead ({cameras.render_ms:.0f} ms"
                f" a pair, {time.monotonic() - started:.1f} s of waiting); the session starts"
            )
            start_s = time.monotonic() + settings.start_delay_s
            cameras.start(start_s)
            controller.start(live.joints.address, start_s, lead_s=settings.start_delay_s)
            try:
                summary = live.run(cameras)  # closes the sinks, the receiver and the source
            finally:
                controller.stop(expected=live.sender.sent)
            output = live.output
            lines = report_lines(
                settings,
                scorer.scores,
                summary,
                controller,
                live.sender.sent,
                None if output is None or output.served_url else output.rrd_path,
                [] if output is None else [t for t in output.targets if not t.startswith("file")],
                cameras.late,
            )
            for line in lines:
                out(line)
            if on_result is not None:
                on_result(
                    DemoResult(
                        summary,
                        scorer.scores,
                        live.sender.sent,
                        controller.received,
                        cameras.late,
                        cameras.render_ms,
                    )
                )
            if output is not None and output.served_url is not None and not summary.interrupted:
                serve_until_interrupted(output, out)
    except KeyboardInterrupt:  # Ctrl-C before the loop took it over
        out("cathtrack demo: interrupted")
        return 130
    finally:
        if controller is not None:
            controller.stop()
        cameras.close()
        segmenter.close()
    return 130 if summary.interrupted else 0
