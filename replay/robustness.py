"""Is the filter ever confidently wrong? Metrics per method, and lab sessions to measure them.

:func:`robustness_metrics` scores one method's estimates over a session: RMS and maximum
error, the share of frames whose +/-2 sigma interval covers the truth, the mean NEES, and the
frames and configurations where the method is *confidently wrong* (error above
``wrong_deg`` while its std is below ``confident_deg``: 30 and 10 degrees by default). The
evaluation report prints them per method.

:func:`simulate_lab_session` makes a session with everything a lab meets at once
(:class:`~replay.simulation.simulator.LabConditions`): configurations held with small joint
motion (some of them nearly straight), base rotations between them with torsion wind-up and
play, a contact deviation of the joints per configuration, a model whose bending gain is off,
wrong and missing markers. :func:`run_methods_on_session` runs estimators over it and scores
them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from models.catheter import Catheter
from models.imaging import default_orthographic_rig
from models.rotations import wrap_angle
from replay.simulation.simulator import (
    JointTrajectory,
    LabConditions,
    contact_joint_offsets,
    default_scene,
    simulate_frames,
    torsion_windup,
    truth_catheter,
)
from tracker.estimators import make_estimator
from tracker.reconstruction import Reconstructor
from tracker.types import Frame

Array = np.ndarray

WRONG_DEG = 30.0
"""An error above this (degrees) is wrong..."""
CONFIDENT_DEG = 10.0
"""...and confidently so when the reported std is below this (degrees)."""


@dataclass(frozen=True)
class RobustnessMetrics:
    """One method's accuracy and honesty over the scored frames of a session.

    Attributes
    ----------
    method : str
    frames : int
        Scored frames.
    valid : float
        Share of scored frames with an estimate.
    rms_deg, max_deg : float
        RMS and largest absolute error over the scored frames with an estimate, degrees.
    coverage_2sigma : float
        Share of those whose +/-2 std interval covers the truth.
    mean_nees : float
        Mean of ``error^2 / std^2`` over them.
    confidently_wrong_frames : int
        Frames with an error above ``WRONG_DEG`` and a std below ``CONFIDENT_DEG``.
    confidently_wrong_configurations : int
        Configurations with at least one such frame.
    """

    method: str
    frames: int
    valid: float
    rms_deg: float
    max_deg: float
    coverage_2sigma: float
    mean_nees: float
    confidently_wrong_frames: int
    confidently_wrong_configurations: int


def robustness_metrics(
    method: str,
    errors_rad: Array,
    std_rad: Array,
    configuration: Array | None = None,
    scored: Array | None = None,
    wrong_deg: float = WRONG_DEG,
    confident_deg: float = CONFIDENT_DEG,
) -> RobustnessMetrics:
    """Score one method's estimates.

    Parameters
    ----------
    method : str
    errors_rad : array, shape (F,)
        Wrapped estimate - truth per frame, rad; NaN where the method gave no estimate.
    std_rad : array, shape (F,)
        Reported std per frame, rad.
    configuration : array, shape (F,), optional
        Configuration label per frame (any hashable; None or negative: none).
    scored : array of bool, shape (F,), optional
        Frames that count (default: all).
    wrong_deg, confident_deg : float
        Thresholds of a confidently wrong frame.
    """
    errors = np.asarray(errors_rad, dtype=float)
    std = np.asarray(std_rad, dtype=float)
    scored = np.ones(errors.size, dtype=bool) if scored is None else np.asarray(scored, bool)
    valid = scored & np.isfinite(errors) & np.isfinite(std) & (std > 0)
    n = int(scored.sum())
    err = np.abs(errors[valid])
    s = std[valid]
    wrong = valid & (np.abs(np.nan_to_num(errors)) > math.radians(wrong_deg)) & (
        np.nan_to_num(std, nan=np.inf) < math.radians(confident_deg)
    )
    configurations = 0
    if configuration is not None and wrong.any():
        labels = np.asarray(configuration, dtype=object)[wrong]
        configurations = len({c for c in labels if c is not None and not _negative(c)})
    elif wrong.any():
        configurations = 1
    if err.size == 0:
        return RobustnessMetrics(method, n, 0.0, math.nan, math.nan, math.nan, math.nan, 0, 0)
    return RobustnessMetrics(
        method=method,
        frames=n,
        valid=float(valid.sum() / n) if n else 0.0,
        rms_deg=math.degrees(float(np.sqrt(np.mean(err * err)))),
        max_deg=math.degrees(float(err.max())),
        coverage_2sigma=float(np.mean(err <= 2.0 * s)),
        mean_nees=float(np.mean((err / s) ** 2)),
        confidently_wrong_frames=int(wrong.sum()),
        confidently_wrong_configurations=configurations,
    )


def _negative(label) -> bool:
    try:
        return label < 0
    except TypeError:
        return False


# ------------------------------------------------------------------------ lab sessions
@dataclass(frozen=True)
class LabSessionSettings:
    """A simulated lab session (markers only, the paper's orthographic planes).

    Parameters
    ----------
    seed : int
    configurations : int
        Joint configurations held in turn.
    frames_per_configuration, transition_frames : int
        Frames held at each configuration and frames of each move between two.
    frame_rate_hz : float
    noise_mm : float
        Segmentation noise in the image planes, mm.
    conditions : LabConditions
    offset_deg : float or None
        Torsion offset of the session (None: drawn uniformly).
    near_straight_every : int
        Every this-many-th configuration is nearly straight (|q_p|, |q_d| <
        ``near_straight_mm``); 0: none.
    near_straight_mm : float
    q_p_abs_range_mm, q_d_range_mm : tuple of float
        Joint ranges of the bent configurations (|q_p| with a random sign), mm.
    base_turn_range_deg : tuple of float
        Base rotation between configurations (random sign), degrees.
    hold_motion : tuple of float
        Amplitude of the joint motion during a hold (q_r rad, q_p mm, q_d mm)...
    hold_period_s : float
        ...and its period, s.
    """

    seed: int = 0
    configurations: int = 12
    frames_per_configuration: int = 60
    transition_frames: int = 20
    frame_rate_hz: float = 20.0
    noise_mm: float = 0.11
    conditions: LabConditions = field(
        default_factory=lambda: LabConditions(
            model_scale_error=0.05,
            contact_joint_std_mm=0.08,
            outlier_probability=0.03,
            outlier_magnitude=5.0,
            dropout_probability=0.03,
            windup_play_rad=math.radians(40.0),
        )
    )
    offset_deg: float | None = None
    near_straight_every: int = 4
    near_straight_mm: float = 0.08
    q_p_abs_range_mm: tuple[float, float] = (0.3, 0.95)
    q_d_range_mm: tuple[float, float] = (-0.8, 0.8)
    base_turn_range_deg: tuple[float, float] = (30.0, 150.0)
    hold_motion: tuple[float, float, float] = (0.0, 0.08, 0.08)
    hold_period_s: float = 2.5


@dataclass(frozen=True)
class LabSession:
    """Frames of a lab session and the configuration of each (-1: moving between two)."""

    settings: LabSessionSettings
    catheter: Catheter
    frames: list[Frame]
    configuration: Array  # (F,) int
    truth_rad: Array  # (F,)

    @property
    def scored(self) -> Array:
        return self.configuration >= 0


def _smoothstep(x: Array) -> Array:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def lab_trajectory(settings: LabSessionSettings, rng: np.random.Generator):
    """Joint values and rates of the session, the configuration of each frame and the
    configurations' nominal joints."""
    s = settings
    hold, move = s.frames_per_configuration, s.transition_frames
    dt = 1.0 / s.frame_rate_hz
    q0 = np.zeros((s.configurations, 3))
    for c in range(s.configurations):
        if s.near_straight_every and c % s.near_straight_every == s.near_straight_every - 1:
            q0[c, 1:] = rng.uniform(-s.near_straight_mm, s.near_straight_mm, 2)
        else:
            q0[c, 1] = rng.uniform(*s.q_p_abs_range_mm) * rng.choice([-1.0, 1.0])
            q0[c, 2] = rng.uniform(*s.q_d_range_mm)
        if c:
            turn = math.radians(rng.uniform(*s.base_turn_range_deg)) * rng.choice([-1.0, 1.0])
            q0[c, 0] = q0[c - 1, 0] + turn
    amplitude = np.asarray(s.hold_motion, dtype=float)
    omega = 2 * math.pi / s.hold_period_s
    phase = np.array([0.0, 0.5 * math.pi, math.pi])
    qs, labels = [], []
    for c in range(s.configurations):
        tau = np.arange(hold) * dt
        wave = np.sin(omega * tau[:, None] + phase) - np.sin(phase)
        qs.append(q0[c] + amplitude * wave)
        labels.append(np.full(hold, c))
        if c + 1 < s.configurations:
            x = _smoothstep((np.arange(1, move + 1)) / (move + 1))[:, None]
            qs.append(qs[-1][-1] + x * (q0[c + 1] - qs[-1][-1]))
            labels.append(np.full(move, -1))
    q = np.concatenate(qs)
    time_s = np.arange(q.shape[0]) * dt
    q_dot = np.gradient(q, time_s, axis=0)
    return JointTrajectory(time_s, q, q_dot), np.concatenate(labels), q0


def simulate_lab_session(catheter: Catheter, settings: LabSessionSettings) -> LabSession:
    """A seeded session with all of ``settings.conditions`` at once (see the module notes).

    The frames report the commanded joints of the model ``catheter``; the truth bends as
    :func:`~replay.simulation.simulator.truth_catheter` says, with the configuration's
    contact offset, and its torsion winds up with the base.
    """
    s = settings
    lab = s.conditions
    rng = np.random.default_rng([s.seed, 11])
    trajectory, configuration, _ = lab_trajectory(s, rng)
    offset = (
        rng.uniform(-math.pi, math.pi) if s.offset_deg is None else math.radians(s.offset_deg)
    )
    truth = wrap_angle(torsion_windup(trajectory.q[:, 0], lab.windup_play_rad, offset))
    contact = contact_joint_offsets(rng, s.configurations, lab.contact_joint_std_mm)
    # The move to a configuration already has its contact (made at the end of the move).
    following = np.maximum.accumulate(configuration)
    following = np.where(configuration < 0, following + 1, configuration)
    offsets = contact[np.minimum(following, s.configurations - 1)]
    scene = default_scene(catheter, default_orthographic_rig())
    truth_scene = replace(scene, catheter=truth_catheter(catheter, lab.model_scale_error))
    frames = simulate_frames(
        truth_scene, trajectory, truth, lab.noise(s.noise_mm), rng, model_joint_offset=offsets
    )
    return LabSession(s, catheter, frames, configuration, np.asarray(truth, dtype=float))


def run_methods_on_session(
    session: LabSession, methods: Sequence[str]
) -> tuple[dict[str, RobustnessMetrics], dict[str, tuple[Array, Array]]]:
    """Run the named estimators over a session and score them.

    Returns the metrics per method and, per method, the per-frame errors and stds (rad).
    """
    scene = default_scene(session.catheter, default_orthographic_rig())
    reconstructor = Reconstructor(session.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    observations = reconstructor.observe_batch(session.frames)
    metrics, series = {}, {}
    for name in methods:
        estimator = make_estimator(name, session.catheter)
        estimates = estimator.run(observations)
        delta = np.array([e.delta_L_rad for e in estimates])
        std = np.array([e.std_rad for e in estimates])
        errors = wrap_angle(delta - session.truth_rad)
        metrics[name] = robustness_metrics(
            name, errors, std, session.configuration, session.scored
        )
        series[name] = (errors, std)
    return metrics, series


__all__ = [
    "CONFIDENT_DEG",
    "LabSession",
    "LabSessionSettings",
    "RobustnessMetrics",
    "WRONG_DEG",
    "lab_trajectory",
    "robustness_metrics",
    "run_methods_on_session",
    "simulate_lab_session",
]
