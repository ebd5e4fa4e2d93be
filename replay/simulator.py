"""Seeded simulator of bi-plane tracking sessions.

It makes joint trajectories, the true torsional loss over time, and the segmented image
points of both views with segmentation noise, outliers and dropped markers, as the
:class:`tracker.pipeline.Frame` objects that the live loop consumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter
from models.imaging import BiplaneRig, isotropic_covariance
from tracker.pipeline import Frame

Array = np.ndarray


@dataclass(frozen=True)
class JointTrajectory:
    """Joint values and rates sampled at the frame times."""

    time_s: Array  # (T,)
    q: Array  # (T, 3): q_r [rad], q_p [mm], q_d [mm]
    q_dot: Array  # (T, 3): rad/s, mm/s, mm/s

    def __post_init__(self) -> None:
        T = np.asarray(self.time_s).shape[0]
        if np.asarray(self.q).shape != (T, 3) or np.asarray(self.q_dot).shape != (T, 3):
            raise ValueError("trajectory q and q_dot must have shape (T, 3) for T frame times")
        if T > 1 and np.any(np.diff(self.time_s) <= 0):
            raise ValueError("trajectory times must increase strictly")


def frame_times(duration_s: float, frame_rate_hz: float) -> Array:
    if not (duration_s > 0 and frame_rate_hz > 0):
        raise ValueError(
            f"duration and frame rate must be positive, got {duration_s} s, {frame_rate_hz} Hz"
        )
    return np.arange(int(round(duration_s * frame_rate_hz))) / frame_rate_hz


def hold(q: Array, duration_s: float, frame_rate_hz: float = 20.0) -> JointTrajectory:
    """A static hold at joint values q."""
    t = frame_times(duration_s, frame_rate_hz)
    q = np.broadcast_to(np.asarray(q, dtype=float), (t.size, 3)).copy()
    return JointTrajectory(t, q, np.zeros_like(q))


def sinusoidal(
    mean: Array, amplitude: Array, period_s: Array, duration_s: float, frame_rate_hz: float = 20.0
) -> JointTrajectory:
    """Each joint q_i = mean_i + amplitude_i sin(2 pi t / period_i): sweeps and base turns."""
    t = frame_times(duration_s, frame_rate_hz)[:, None]
    mean, amp = np.asarray(mean, float), np.asarray(amplitude, float)
    omega = 2 * np.pi / np.asarray(period_s, float)
    return JointTrajectory(t[:, 0], mean + amp * np.sin(omega * t), amp * omega * np.cos(omega * t))


def base_rotation(
    q_bend: Array, speed_rad_s: float, duration_s: float, frame_rate_hz: float = 20.0
) -> JointTrajectory:
    """Constant-speed base rotation at fixed bending joints (q_p, q_d)."""
    t = frame_times(duration_s, frame_rate_hz)
    q = np.column_stack([speed_rad_s * t, np.full_like(t, q_bend[0]), np.full_like(t, q_bend[1])])
    q_dot = np.zeros_like(q)
    q_dot[:, 0] = speed_rad_s
    return JointTrajectory(t, q, q_dot)


def torsion_windup(q_r_rad: Array, play_rad: float, offset_rad: float = 0.0) -> Array:
    """Torsion that winds up as the base turns, with hysteresis (a play operator).

    The tip rotation follows the base only once the base has turned ``play_rad`` beyond it,
    so delta_L = tip - base stays within ``offset +/- play`` and lags every reversal.
    """
    if play_rad < 0:
        raise ValueError(f"play must be non-negative, got {play_rad} rad")
    x = np.asarray(q_r_rad, dtype=float)
    y = np.empty_like(x)
    tip = x[0]
    for i, xi in enumerate(x):
        tip = min(max(tip, xi - play_rad), xi + play_rad)
        y[i] = tip
    return y - x + offset_rad


def torsion_steps(time_s: Array, step_times_s: Array, values_rad: Array) -> Array:
    """Piecewise-constant torsion: values_rad[k] from step_times_s[k - 1] on (len = steps + 1)."""
    values = np.asarray(values_rad, dtype=float)
    steps = np.asarray(step_times_s, dtype=float)
    if values.size != steps.size + 1:
        raise ValueError("torsion steps need one more value than step times")
    return values[np.searchsorted(steps, np.asarray(time_s), side="right")]


@dataclass(frozen=True)
class NoiseSettings:
    """Segmentation noise in image units (mm in the plane, or px)."""

    sigma: float = 1.0
    outlier_probability: float = 0.0
    outlier_magnitude: float = 10.0
    dropout_probability: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma) and self.sigma >= 0):
            raise ValueError(f"noise sigma must be finite and non-negative, got {self.sigma}")
        for name in ("outlier_probability", "dropout_probability"):
            p = getattr(self, name)
            if not 0 <= p <= 1:
                raise ValueError(f"{name} must lie in [0, 1], got {p}")


@dataclass(frozen=True)
class Scene:
    """The catheter, the rig and the registered base pose of a simulated session."""

    catheter: Catheter
    rig: BiplaneRig
    R_w_b: Array
    o_b_w_mm: Array


def default_scene(catheter: Catheter, rig: BiplaneRig) -> Scene:
    """Base 15 mm below the world origin, z_b along world z (up in both images)."""
    return Scene(catheter, rig, np.eye(3), np.array([0.0, 0.0, -15.0]))


def true_points_b(catheter: Catheter, q: Array, delta_L: Array) -> Array:
    """Tip and markers in {B}, shape (T, 1 + n_markers, 3)."""
    s = (catheter.length_mm,) + catheter.marker_arclengths_mm
    return catheter.backbone(q, delta_L, np.asarray(s))


def simulate_frames(
    scene: Scene,
    trajectory: JointTrajectory,
    delta_L_rad: Array,
    noise: NoiseSettings,
    rng: np.random.Generator,
    model_joint_offset: Array | None = None,
) -> list[Frame]:
    """Frames of a session: true shape from the joints, projected into both views, noisy.

    Parameters
    ----------
    model_joint_offset : array (3,) or (T, 3), optional
        Contact deflection made as the paper's experiment did: the catheter bends as if its
        joints were ``q + offset`` while the frames report the commanded ``q``.
    """
    q_true = trajectory.q if model_joint_offset is None else trajectory.q + model_joint_offset
    delta_L = np.broadcast_to(np.asarray(delta_L_rad, dtype=float), trajectory.time_s.shape)
    points_b = true_points_b(scene.catheter, q_true, delta_L)
    points_w = points_b @ scene.R_w_b.T + scene.o_b_w_mm
    n_frames, n_points = points_w.shape[:2]
    cov = np.broadcast_to(isotropic_covariance(noise.sigma), (n_points, 2, 2))
    views = []
    for view in (scene.rig.front, scene.rig.side):
        uv = view.project(points_w)
        uv = uv + noise.sigma * rng.standard_normal(uv.shape)
        outlier = rng.random((n_frames, n_points)) < noise.outlier_probability
        direction = rng.standard_normal(uv.shape)
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        uv = np.where(outlier[..., None], uv + noise.outlier_magnitude * direction, uv)
        dropped = rng.random((n_frames, n_points)) < noise.dropout_probability
        views.append(np.where(dropped[..., None], np.nan, uv))
    return [
        Frame(
            time_s=float(trajectory.time_s[i]),
            q=trajectory.q[i],
            q_dot=trajectory.q_dot[i],
            uv_front=views[0][i],
            uv_side=views[1][i],
            cov_front=cov,
            cov_side=cov,
            delta_L_true_rad=float(delta_L[i]),
        )
        for i in range(n_frames)
    ]
