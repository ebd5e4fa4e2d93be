"""Simulated frame sources for the live loop: the demo's session, as frames or rendered images.

- :class:`SimulatedSource`: the frames of a simulated session (optionally paced);
- :class:`RenderedSource`: their images rendered one after the other in this process (tests);
- :class:`SimulatedCameras`: cameras that behave like cameras: the images are rendered ahead of
  time in a separate process and released at their exposure times (the demo).
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import queue
import signal
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter, default_catheter
from models.imaging import Rig, default_orthographic_rig
from replay.simulation.simulator import (
    JointTrajectory,
    NoiseSettings,
    Scene,
    default_scene,
    simulate_frames,
    sinusoidal,
    torsion_windup,
)
from tracker.io.datagrams import SegmentedMarkers
from tracker.live.sources import ImageSet, PacedSource
from tracker.types import Frame

Array = np.ndarray


# -------------------------------------------------------------------------------- simulation
@dataclass(frozen=True)
class SimulatedSession:
    """A simulated session: the scene, the commanded joints, the true delta_L and the frames."""

    scene: Scene
    trajectory: JointTrajectory
    delta_L_true_rad: Array  # (T,)
    frames: list[Frame]


# The demo's motion: bending sweeps while the base turns back and forth (q_r rad, q_p, q_d mm).
SESSION_MEAN = (0.0, 0.55, 0.2)


SESSION_AMPLITUDE = (2.5, 0.35, 0.6)


SESSION_PERIOD_S = (16.0, 9.0, 6.0)


def session_joints(time_s: float | Array) -> tuple[Array, Array]:
    """Joint values and rates of the simulated session's motion at any time, (..., 3) each.

    The same formula as :func:`~sinusoidal`, for a simulated controller that
    streams the joints at 1 kHz while the frames come at the image rate.
    """
    t = np.asarray(time_s, dtype=float)[..., None]
    mean, amp = np.asarray(SESSION_MEAN), np.asarray(SESSION_AMPLITUDE)
    omega = 2 * np.pi / np.asarray(SESSION_PERIOD_S)
    return mean + amp * np.sin(omega * t), amp * omega * np.cos(omega * t)


def session_trajectory(duration_s: float, frame_rate_hz: float) -> JointTrajectory:
    """The demo's commanded joints at the frame times (:func:`session_joints` sampled)."""
    return sinusoidal(
        mean=list(SESSION_MEAN),
        amplitude=list(SESSION_AMPLITUDE),
        period_s=list(SESSION_PERIOD_S),
        duration_s=duration_s,
        frame_rate_hz=frame_rate_hz,
    )


def simulated_session(
    duration_s: float = 20.0,
    frame_rate_hz: float = 20.0,
    noise: float = 0.5,
    seed: int = 0,
    catheter: Catheter | None = None,
    rig: Rig | None = None,
) -> SimulatedSession:
    """The demo's session: bending sweeps while the base turns, torsion wind-up with play.

    Parameters
    ----------
    duration_s, frame_rate_hz : float
    noise : float
        Segmentation noise sigma in the rig's image unit (mm for the default orthographic rig).
    seed : int
    catheter, rig : optional
        Default catheter model and orthographic rig.
    """
    catheter = default_catheter() if catheter is None else catheter
    rig = default_orthographic_rig() if rig is None else rig
    scene = default_scene(catheter, rig)
    trajectory = session_trajectory(duration_s, frame_rate_hz)
    truth = torsion_windup(trajectory.q[:, 0], play_rad=np.radians(60), offset_rad=np.radians(120))
    frames = simulate_frames(
        scene, trajectory, truth, NoiseSettings(sigma=noise), np.random.default_rng(seed)
    )
    return SimulatedSession(scene, trajectory, truth, frames)


class SimulatedSource(PacedSource):
    """The frames of a simulated session, optionally paced at real time.

    ``joints=False`` yields them as :class:`~tracker.io.udp.SegmentedMarkers` (no joint values)
    for a loop that takes its joints from a :class:`~tracker.io.udp.JointReceiver`.
    """

    def __init__(
        self, frames: Iterable[Frame], speed: float | None = 1.0, joints: bool = True, **kwargs
    ) -> None:
        if not joints:
            frames = (
                SegmentedMarkers(f.time_s, f.uv, f.cov, i)
                for i, f in enumerate(frames)
            )
        super().__init__(frames, speed, **kwargs)


class RenderedSource(PacedSource):
    """Rendered bi-plane images of simulated frames, as :class:`ImageSet`.

    Parameters
    ----------
    renderer : replay.simulation.render.Renderer
        Pinhole rig, catheter and background of the images.
    frames : iterable of Frame
        Joint values and true delta_L of each image (their segmented points are ignored).
    seed : int
        Seeds the sensor noise.
    speed : float or None
    """

    def __init__(self, renderer, frames: Iterable[Frame], seed: int = 0, speed=1.0, **kwargs):
        rng = np.random.default_rng(seed)

        def pairs() -> Iterator[ImageSet]:
            for f in frames:
                images = renderer.render(f.q, f.delta_L_true_rad, rng).images
                yield ImageSet(f.time_s, tuple(images))

        super().__init__(pairs(), speed, **kwargs)


# ------------------------------------------------------------------------ simulated cameras
def _render_ahead(renderer, q, delta_L_rad, seed, pairs, progress, released, max_ahead, stop):
    """The render process: every pair in order, at most ``max_ahead`` ahead of the release.

    ``progress`` holds (pairs rendered, seconds spent rendering), ``released`` the number of
    pairs the cameras have released; a failure goes to ``pairs`` as its message.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the demo's to handle
    try:
        rng = np.random.default_rng(seed)
        for k in range(len(q)):
            if k == max_ahead:
                with contextlib.suppress(OSError, AttributeError):
                    # The session runs: render the rest below the loop's priority.
                    os.nice(10)
            while k - released.value >= max_ahead:
                if stop.wait(0.005):
                    break
            if stop.is_set():
                break
            started = time.perf_counter()
            images = renderer.render(q[k], delta_L_rad[k], rng).images
            pairs.put((k, tuple(images)))
            with progress.get_lock():
                progress[0] += 1
                progress[1] += time.perf_counter() - started
        # The queue's pairs are still on their way: stay until they are all taken.
        while released.value < len(q) and not stop.wait(0.05):
            pass
    except Exception as exc:  # handed to the cameras, which raise it in the loop's thread
        pairs.put((-1, f"{type(exc).__name__}: {exc}"))
    if stop.is_set():
        pairs.cancel_join_thread()  # the cameras stopped reading: do not wait for them


FETCH_LEAD_S = 0.01
"""How long before its exposure :class:`SimulatedCameras` takes a pair from its renderer, s."""


class SimulatedCameras:
    """Simulated triggered cameras: a live source of :class:`ImageSet` at exposure times.

    Pair ``k`` shows the catheter at the frames' joints and true delta_L at ``t_k``. The pairs
    are rendered in a separate process, in order and ahead of time (at most ``max_ahead``
    pairs ahead), so that rendering never takes the loop's interpreter nor, once
    :meth:`render_ahead` has waited for them before the session, its processor; pair ``k`` is
    then released at its exposure time ``start_s + t_k`` on the monotonic clock (``start_s``
    given to :meth:`start`) and stamped with it, as a camera with a hardware time stamp would
    deliver it. The source is ``live``: the loop captures it in its own thread and takes the
    newest pair. A pair that still comes from the renderer after its exposure time (a session
    longer than ``max_ahead`` pairs on a slow machine) is released late, stamped with its
    exposure time, and counted in ``late`` (more than ``late_after_s`` after the exposure).

    Parameters
    ----------
    renderer : replay.simulation.render.Renderer
    frames : sequence of Frame
        The session's frames (their joints, truth and times; their points are ignored).
    seed : int
        Seeds the sensor noise.
    late_after_s : float
        A pair released later than this after its exposure counts as late, s.
    max_ahead : int
        Pairs rendered and not yet released, at most (about 0.6 MB each: 320 pairs, 16 s at
        20 fps, are 200 MB).
    """

    time_is_monotonic = True
    live = True

    def __init__(
        self,
        renderer,
        frames: Sequence[Frame],
        seed: int = 0,
        late_after_s: float = 0.025,
        max_ahead: int = 320,
    ) -> None:
        self.times_s = np.array([float(f.time_s) for f in frames])
        self.truth_rad = np.array([float(f.delta_L_true_rad) for f in frames])
        self.late_after_s = float(late_after_s)
        self.max_ahead = int(max_ahead)
        self.start_s: float | None = None
        self.late = 0
        self.released = 0
        self._truth: dict[float, float] = {}
        self._stop = threading.Event()
        context = multiprocessing.get_context("spawn")  # no fork of a threaded process
        self._pairs = context.Queue()
        self._progress = context.Array("d", 2)
        self._released = context.Value("l", 0)
        self._stop_render = context.Event()
        q = np.array([f.q for f in frames], dtype=float)
        self._process = context.Process(
            target=_render_ahead,
            args=(
                renderer, q, self.truth_rad, seed, self._pairs, self._progress,
                self._released, self.max_ahead, self._stop_render,
            ),
            name="simulated-cameras",
            daemon=True,
        )  # fmt: skip
        self._process.start()

    @property
    def rendered(self) -> int:
        """Pairs rendered so far."""
        return int(self._progress[0])

    @property
    def render_ms(self) -> float:
        """Mean time to render a pair so far, ms (NaN before the first)."""
        n, spent_s = self._progress[0], self._progress[1]
        return 1e3 * spent_s / n if n else math.nan

    def render_ahead(self, timeout_s: float = 300.0) -> int:
        """Wait until the pairs are rendered ahead: all of them, or ``max_ahead``.

        The session then costs the renderer nothing (a session longer than ``max_ahead``
        pairs renders the rest as it goes, at a lower priority than the loop). Returns the
        pairs ready.
        """
        target = min(self.times_s.size, self.max_ahead)
        deadline = time.monotonic() + timeout_s
        while self.rendered < target and time.monotonic() < deadline:
            if not self._process.is_alive():
                raise RuntimeError("the simulated cameras' renderer stopped")
            time.sleep(0.01)
        return self.rendered

    def start(self, start_s: float) -> SimulatedCameras:
        """Set the monotonic time of the session's time 0 (before iterating)."""
        self.start_s = float(start_s)
        self._truth = {
            self.start_s + float(t): float(truth)
            for t, truth in zip(self.times_s, self.truth_rad, strict=True)
        }
        return self

    def truth(self, time_s: float) -> float | None:
        """True delta_L (rad) of the pair stamped ``time_s``."""
        return self._truth.get(float(time_s))

    def __iter__(self) -> Iterator[ImageSet]:
        if self.start_s is None:
            raise RuntimeError("SimulatedCameras.start(start_s) was not called")
        for k, t in enumerate(self.times_s):
            exposure_s = self.start_s + float(t)
            # Take the pair from the renderer shortly before its exposure rather than right
            # after the last pair was released: unpacking it holds the interpreter, and right
            # after a release the loop is working on that pair.
            early = exposure_s - FETCH_LEAD_S - time.monotonic()
            if early > 0 and self._stop.wait(early):
                return
            images = None
            while images is None:
                if self._stop.is_set():
                    return
                try:
                    index, images = self._pairs.get(timeout=0.05)
                except queue.Empty:
                    if not self._process.is_alive():
                        raise RuntimeError("the simulated cameras' renderer stopped") from None
                    continue
                if index < 0:
                    raise RuntimeError(f"the simulated cameras' renderer failed: {images}")
            wait = exposure_s - time.monotonic()
            if wait > 0:
                if self._stop.wait(wait):
                    return
            elif -wait > self.late_after_s:
                self.late += 1
            self.released = k + 1
            self._released.value = k + 1
            yield ImageSet(exposure_s, images)

    def close(self) -> None:
        """Stop releasing and rendering; end the render process."""
        self._stop.set()
        self._stop_render.set()
        self._process.join(2.0)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(1.0)
        self._pairs.close()
        self._pairs.cancel_join_thread()
