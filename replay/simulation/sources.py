"""Simulated frame sources for the live loop: the demo's session, as frames or rendered images."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
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
    trajectory = sinusoidal(
        mean=list(SESSION_MEAN),
        amplitude=list(SESSION_AMPLITUDE),
        period_s=list(SESSION_PERIOD_S),
        duration_s=duration_s,
        frame_rate_hz=frame_rate_hz,
    )
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

