"""Simulated frame sources for the live loop: the demo's session, as frames or rendered images.

- :class:`SimulatedSource`: the frames of a simulated session (optionally paced);
- :class:`RenderedSource`: their images rendered one after the other in this process (tests);
- :class:`SimulatedCameras`: cameras that behave like cameras: the images are rendered ahead of
  time in a separate process and released at their exposure times (the demo).
"""

from __future__ import annotations

import collections
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
from multiprocessing import shared_memory

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
RING_SLOTS = 4
"""Pairs in the shared-memory ring between the render process and the cameras."""
RENDER_AHEAD_BYTES = 1 << 30
"""The images :class:`SimulatedCameras` render ahead, at most, bytes."""


def _ring_slots(memory: shared_memory.SharedMemory, shapes) -> list[list[Array]]:
    """The ring's slots over ``memory``: slot k holds one uint8 image per view."""
    slots, offset = [], 0
    for _ in range(RING_SLOTS):
        views = []
        for shape in shapes:
            size = math.prod(shape)
            views.append(np.ndarray(shape, np.uint8, memory.buf, offset))
            offset += size
        slots.append(views)
    return slots


def _copy_into(slot: list[Array], images) -> None:
    for view, image in zip(slot, images, strict=True):
        np.copyto(view, image)


def _render_ahead(
    renderer, q, delta_L_rad, seed, ring_name, shapes, free, filled, failures, progress,
    released, max_ahead, stop,
):  # fmt: skip
    """The render process: every pair in order, at most ``max_ahead`` ahead of the release,
    each copied into the next slot of the shared-memory ring as soon as one is free.

    ``free`` and ``filled`` count the ring's free and filled slots, ``progress`` holds (pairs
    rendered, seconds spent rendering), ``released`` the number of pairs the cameras have
    released; a failure goes to ``failures`` as its message.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the demo's to handle
    memory = shared_memory.SharedMemory(ring_name)
    slots = _ring_slots(memory, shapes)
    try:
        rng = np.random.default_rng(seed)
        pending: collections.deque = collections.deque()  # rendered, not yet in the ring
        rendered = filled_count = 0
        while filled_count < len(q) and not stop.is_set():
            can_render = rendered < len(q) and rendered - released.value < max_ahead
            # Fill a free slot first (at once when there is more to render, else waiting).
            if pending and free.acquire(block=not can_render, timeout=0.05):
                _copy_into(slots[filled_count % RING_SLOTS], pending.popleft())
                filled_count += 1
                filled.release()
            elif can_render:
                if rendered == max_ahead:
                    with contextlib.suppress(OSError, AttributeError):
                        # The session runs: render the rest below the loop's priority.
                        os.nice(10)
                started = time.perf_counter()
                pending.append(renderer.render(q[rendered], delta_L_rad[rendered], rng).images)
                rendered += 1
                with progress.get_lock():
                    progress[0] += 1
                    progress[1] += time.perf_counter() - started
            elif not pending:
                stop.wait(0.005)  # max_ahead pairs wait for their release
    except Exception as exc:  # handed to the cameras, which raise it in the loop's thread
        failures.put(f"{type(exc).__name__}: {exc}")
    finally:
        del slots  # the ring's arrays first: the memory does not close under them
        memory.close()


FETCH_LEAD_S = 0.01
"""How long before its exposure :class:`SimulatedCameras` takes a pair from its renderer, s."""


class SimulatedCameras:
    """Simulated triggered cameras: a live source of :class:`ImageSet` at exposure times.

    Pair ``k`` shows the catheter at the frames' joints and true delta_L at ``t_k``. The pairs
    are rendered in a separate process, in order and ahead of time (at most ``max_ahead``
    pairs ahead), so that rendering never takes the loop's interpreter nor, once
    :meth:`render_ahead` has waited for them before the session, its processor. They reach
    this process through a ring of :data:`RING_SLOTS` pairs in shared memory, each copied in
    by the render process as soon as a slot is free, long before it is due: taking a pair
    is a copy out of the ring (a fraction of a millisecond), not a transfer through a pipe
    that needs the render process on a processor while the loop waits (5 ms at the median
    and up to 29 ms on a slow machine, which made frames late). Pair ``k`` is then released
    at its exposure time ``start_s + t_k`` on the monotonic clock (``start_s`` given to
    :meth:`start`) and stamped with it, as a camera with a hardware time stamp would
    deliver it. The source is ``live``: the loop captures it in its own thread and takes the
    newest pair. A pair that still comes from the renderer after its exposure time (a session
    longer than ``max_ahead`` pairs on a slow machine) is released late, stamped with its
    exposure time, and counted in ``late`` (more than ``late_after_s`` after the exposure).

    Parameters
    ----------
    renderer : replay.simulation.render.Renderer
        Its ``backgrounds`` give the images' sizes.
    frames : sequence of Frame
        The session's frames (their joints, truth and times; their points are ignored).
    seed : int
        Seeds the sensor noise.
    late_after_s : float
        A pair released later than this after its exposure counts as late, s.
    max_ahead : int, optional
        Pairs rendered and not yet released, at most (default: as many as
        :data:`RENDER_AHEAD_BYTES` hold, in the render process: 1747 pairs of 640x480, 87 s
        at 20 fps). Past them, the rest is rendered during the session, at a lower priority
        than the loop; a machine that renders a pair in more than about a frame period then
        releases them late (one where a pair took 32 ms did, in a 60 s demo with 320 ahead).
    """

    time_is_monotonic = True
    live = True

    def __init__(
        self,
        renderer,
        frames: Sequence[Frame],
        seed: int = 0,
        late_after_s: float = 0.025,
        max_ahead: int | None = None,
    ) -> None:
        shapes = tuple(tuple(np.shape(b)) for b in renderer.backgrounds)
        pair_bytes = sum(math.prod(shape) for shape in shapes)
        if max_ahead is None:
            max_ahead = max(RENDER_AHEAD_BYTES // pair_bytes, RING_SLOTS)
        self.times_s = np.array([float(f.time_s) for f in frames])
        self.truth_rad = np.array([float(f.delta_L_true_rad) for f in frames])
        self.late_after_s = float(late_after_s)
        self.max_ahead = int(max_ahead)
        self.start_s: float | None = None
        self.late = 0
        self.released = 0
        self._truth: dict[float, float] = {}
        self._stop = threading.Event()
        self._memory = shared_memory.SharedMemory(create=True, size=RING_SLOTS * pair_bytes)
        self._slots = _ring_slots(self._memory, shapes)
        context = multiprocessing.get_context("spawn")  # no fork of a threaded process
        self._free = context.Semaphore(RING_SLOTS)
        self._filled = context.Semaphore(0)
        self._failures = context.Queue()
        self._progress = context.Array("d", 2)
        self._released = context.Value("l", 0)
        self._stop_render = context.Event()
        q = np.array([f.q for f in frames], dtype=float)
        self._process = context.Process(
            target=_render_ahead,
            args=(
                renderer, q, self.truth_rad, seed, self._memory.name, shapes, self._free,
                self._filled, self._failures, self._progress, self._released,
                self.max_ahead, self._stop_render,
            ),
            name="simulated-cameras",
            daemon=True,
        )  # fmt: skip
        self._process.start()

    @property
    def period_s(self) -> float | None:
        """The cameras' frame period (the median interval between exposures), s; None for
        fewer than two pairs. The live loop primes for the second pair with it."""
        if self.times_s.size < 2:
            return None
        return float(np.median(np.diff(self.times_s)))

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
            self._check_renderer()
            time.sleep(0.01)
        return self.rendered

    def _check_renderer(self) -> None:
        """Raise the render process's failure, or that it has stopped, if it has."""
        try:
            failure = self._failures.get_nowait()
        except queue.Empty:
            failure = None
        if failure is not None:
            raise RuntimeError(f"the simulated cameras' renderer failed: {failure}")
        if not self._process.is_alive():
            raise RuntimeError("the simulated cameras' renderer stopped")

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
            # Take the pair out of the ring shortly before its exposure rather than right
            # after the last pair was released: right after a release the loop is working
            # on that pair.
            early = exposure_s - FETCH_LEAD_S - time.monotonic()
            if early > 0 and self._stop.wait(early):
                return
            while not self._filled.acquire(timeout=0.05):
                if self._stop.is_set():
                    return
                self._check_renderer()
            if self._stop.is_set():
                return
            # Copied out: the loop keeps a frame's images (its sinks, its rehearsal) after
            # the slot has been filled again.
            images = tuple(slot.copy() for slot in self._slots[k % RING_SLOTS])
            self._free.release()
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
        """Stop releasing and rendering; end the render process; free the ring."""
        self._stop.set()
        self._stop_render.set()
        self._process.join(2.0)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(1.0)
        self._failures.close()
        self._failures.cancel_join_thread()
        if self._memory is not None:
            self._slots = []
            # A capture thread that did not stop in time may still be copying a pair out:
            # the mapping then goes with its last array; the name goes now.
            with contextlib.suppress(BufferError):
                self._memory.close()
            self._memory.unlink()
            self._memory = None
