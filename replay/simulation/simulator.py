"""Seeded simulator of bi-plane tracking sessions.

It makes joint trajectories (static holds, bending sweeps, base rotations, constant-rate
ramps), the true torsional loss over time (constant, steps, wind-up with hysteresis), tip
deflection by contact (in the bending plane through the joint values the model sees, as the
paper's experiment did, and out of the plane), and the segmented image points of both views
(orthographic planes or pinhole cameras) with segmentation noise, outliers and dropped markers,
as the :class:`tracker.pipeline.Frame` objects that the live loop consumes.

Points are ordered as in a :class:`~tracker.pipeline.Frame`: the tip first, then the
catheter's markers (:func:`point_arclengths`); each is segmented with independent noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import brentq

from models.catheter import Catheter
from models.imaging import OrthographicPlane, PinholeView, Rig, isotropic_covariance
from models.modal import ModalSegment
from models.rotations import rotate_z
from tracker.types import Frame

JOINT_RANGE_MM = (-1.0, 1.0)
"""Range of q_p and q_d over which the default model is defined, mm."""

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


def bending_sweep(
    q_r_rad: float,
    q_p_range_mm: tuple[float, float],
    q_d_range_mm: tuple[float, float],
    period_s: float,
    duration_s: float,
    frame_rate_hz: float = 20.0,
) -> JointTrajectory:
    """Sweep q_p and q_d sinusoidally over the given ranges at a fixed base rotation.

    Both bending joints start at the middle of their range and swing with the same period.
    """
    if not (np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"sweep period must be positive, got {period_s} s")
    (p0, p1), (d0, d1) = q_p_range_mm, q_d_range_mm
    return sinusoidal(
        mean=[q_r_rad, 0.5 * (p0 + p1), 0.5 * (d0 + d1)],
        amplitude=[0.0, 0.5 * (p1 - p0), 0.5 * (d1 - d0)],
        period_s=[period_s, period_s, period_s],
        duration_s=duration_s,
        frame_rate_hz=frame_rate_hz,
    )


def ramp(q_end: Array, q_dot: Array, n_frames: int, frame_interval_s: float) -> JointTrajectory:
    """Constant joint rates that arrive at ``q_end`` on the last of ``n_frames`` frames.

    Parameters
    ----------
    q_end : array, shape (3,)
        Joint values (rad, mm, mm) at the last frame.
    q_dot : array, shape (3,)
        Joint rates (rad/s, mm/s, mm/s).
    n_frames : int
        Number of frames, >= 1; times are 0, dt, ..., (n_frames - 1) dt.
    frame_interval_s : float
        Frame interval dt, s.
    """
    if int(n_frames) != n_frames or n_frames < 1:
        raise ValueError(f"a ramp needs at least one frame, got {n_frames}")
    if not (np.isfinite(frame_interval_s) and frame_interval_s > 0):
        raise ValueError(f"frame interval must be positive, got {frame_interval_s} s")
    t = np.arange(int(n_frames)) * float(frame_interval_s)
    q_dot = np.asarray(q_dot, dtype=float)
    q = np.asarray(q_end, dtype=float) + (t - t[-1])[:, None] * q_dot
    return JointTrajectory(t, q, np.broadcast_to(q_dot, q.shape).copy())


def torsion_constant(time_s: Array, value_rad: float) -> Array:
    """Constant torsion delta_L = value at every frame time, rad."""
    return np.full(np.shape(time_s), float(value_rad))


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


def _tip_angle_root(segment: ModalSegment, theta_rad: float, q_range: tuple[float, float]):
    grid = np.linspace(q_range[0], q_range[1], 401)
    f = segment.theta(segment.length_mm, grid) - theta_rad
    crossings = np.flatnonzero(np.sign(f[:-1]) * np.sign(f[1:]) <= 0)
    if crossings.size == 0:
        return None, np.degrees(f.min() + theta_rad), np.degrees(f.max() + theta_rad)
    # Of several joint values, the one nearest the straight joint value 0 mm.
    i = crossings[np.argmin(np.abs(grid[crossings]))]
    if f[i] == 0.0:
        return float(grid[i]), None, None
    if f[i + 1] == 0.0:
        return float(grid[i + 1]), None, None
    q = brentq(lambda x: segment.theta(segment.length_mm, x) - theta_rad, grid[i], grid[i + 1])
    return float(q), None, None


def joints_from_tip_angles(
    catheter: Catheter,
    theta_L1_rad: float,
    theta_L2_rad: float,
    q_r_rad: float = 0.0,
    q_range_mm: tuple[float, float] = JOINT_RANGE_MM,
) -> Array:
    """Joint values whose segment tip angles are theta_1(L1) and theta_2(L2).

    Inverts ``theta_i(L_i, q)`` of the model within ``q_range_mm``; the straight configuration
    is theta_L = pi/2 (bending angle ``pi/2 - theta_L = 0``).

    Returns
    -------
    q : array, shape (3,)
        (q_r [rad], q_p [mm], q_d [mm]).
    """
    q = [float(q_r_rad)]
    for label, joint, segment, theta in (
        ("theta_L1", "q_p", catheter.proximal, theta_L1_rad),
        ("theta_L2", "q_d", catheter.distal, theta_L2_rad),
    ):
        if not np.isfinite(theta):
            raise ValueError(f"{label} must be finite, got {theta}")
        root, low, high = _tip_angle_root(segment, float(theta), q_range_mm)
        if root is None:
            raise ValueError(
                f"tip angle {label} = {np.degrees(theta):.4g} deg is not reachable with {joint}"
                f" in [{q_range_mm[0]:g}, {q_range_mm[1]:g}] mm (reachable {low:.4g} to"
                f" {high:.4g} deg)"
            )
        q.append(root)
    return np.array(q)


def point_arclengths(catheter: Catheter) -> tuple[float, ...]:
    """Arclengths of the points in a frame, mm: the tip, then the catheter's markers."""
    return (catheter.length_mm,) + tuple(catheter.marker_arclengths_mm)


def in_plane_joint_offset(
    catheter: Catheter,
    q: Array,
    deflection_mm: float,
    joint: int = 2,
    max_offset_mm: float = 2.0,
) -> Array:
    """Joint offset that moves the tip by ``deflection_mm`` within the segment's bending plane.

    This is how the paper made contact deflection: the catheter bends as if its joints were
    ``q + offset`` while the model sees ``q``. The offset is on one bending joint (1 = q_p,
    2 = q_d, default q_d: a contact at the tip bends the distal segment most), positive, and the
    smallest that displaces the tip by the given distance.

    Returns
    -------
    offset : array, shape (3,)
        Joint offset (rad, mm, mm), zero except at ``joint``.
    """
    if joint not in (1, 2):
        raise ValueError(f"deflection joint must be 1 (q_p) or 2 (q_d), got {joint}")
    if not (np.isfinite(deflection_mm) and deflection_mm >= 0):
        raise ValueError(f"deflection must be finite and non-negative, got {deflection_mm} mm")
    q = np.asarray(q, dtype=float)
    offset = np.zeros(3)
    if deflection_mm == 0.0:
        return offset
    tip = catheter.tip(q)
    grid = np.linspace(0.0, max_offset_mm, 401)
    trial = np.zeros((grid.size, 3))
    trial[:, joint] = grid
    moved = np.linalg.norm(catheter.tip(q + trial) - tip, axis=-1) - deflection_mm
    above = np.flatnonzero(moved >= 0.0)
    if above.size == 0:
        raise ValueError(
            f"a {deflection_mm:g} mm tip deflection is not reachable by a joint offset of up to"
            f" {max_offset_mm:g} mm (largest {moved.max() + deflection_mm:.3g} mm)"
        )
    k = above[0]

    def distance(x: float) -> float:
        trial_q = q.copy()
        trial_q[joint] += x
        return float(np.linalg.norm(catheter.tip(trial_q) - tip)) - deflection_mm

    offset[joint] = brentq(distance, grid[k - 1], grid[k])
    return offset


def out_of_plane_profile(catheter: Catheter, arclength_mm: Array) -> Array:
    """Shape of an out-of-plane contact deflection along the catheter, 1 at the tip.

    A cantilever from the base of the bending section loaded at the tip:
    ``w(s) / w(L) = (s/L)^2 (3 - s/L) / 2``.
    """
    x = np.asarray(arclength_mm, dtype=float) / catheter.length_mm
    return 0.5 * x**2 * (3.0 - x)


def out_of_plane_offsets_b(
    catheter: Catheter, delta_1_rad: Array, deflection_mm: Array | float
) -> Array:
    """Displacements of the frame's points by an out-of-plane tip deflection, in {B}, mm.

    The points move along the normal ``Rz(delta_1) y_b`` of the bending plane by
    ``deflection_mm`` times :func:`out_of_plane_profile`, so the tip moves by
    ``deflection_mm`` out of the plane.

    Returns
    -------
    offsets_b : array, shape (..., 1 + n_markers, 3)
        For bending-plane angles of shape (...).
    """
    profile = out_of_plane_profile(catheter, np.asarray(point_arclengths(catheter)))
    delta_1 = np.asarray(delta_1_rad, dtype=float)
    w = np.asarray(deflection_mm, dtype=float)[..., None] * profile
    normal = np.stack([-np.sin(delta_1), np.cos(delta_1), np.zeros_like(delta_1)], -1)
    return w[..., :, None] * normal[..., None, :]


def image_sigma(view: OrthographicPlane | PinholeView, sigma_mm: float) -> float:
    """Segmentation noise in the view's image unit for ``sigma_mm`` at the world origin.

    An orthographic plane images in mm (the same number); a pinhole camera in px, scaled by its
    magnification ``f / depth`` at the world origin (the isocentre of the default rigs).
    """
    if isinstance(view, OrthographicPlane):
        return float(sigma_mm)
    depth_mm = float(view.t_cam_w[2])
    if depth_mm <= 0:
        raise ValueError("the world origin is behind the camera: no magnification defined")
    return float(sigma_mm) * float(view.K[0, 0]) / depth_mm


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
    rig: Rig
    R_w_b: Array
    o_b_w_mm: Array


def default_scene(catheter: Catheter, rig: Rig) -> Scene:
    """Base 15 mm below the world origin, z_b along world z (up in both images)."""
    return Scene(catheter, rig, np.eye(3), np.array([0.0, 0.0, -15.0]))


def true_points_b(catheter: Catheter, q: Array, delta_L: Array) -> Array:
    """Tip and markers in {B}, shape (T, 1 + n_markers, 3)."""
    return catheter.backbone(q, delta_L, np.asarray(point_arclengths(catheter)))


def simulate_frames(
    scene: Scene,
    trajectory: JointTrajectory,
    delta_L_rad: Array,
    noise: NoiseSettings,
    rng: np.random.Generator,
    model_joint_offset: Array | None = None,
    out_of_plane_mm: Array | float = 0.0,
) -> list[Frame]:
    """Frames of a session: true shape from the joints, projected into both views, noisy.

    Parameters
    ----------
    scene : Scene
        Catheter, rig (orthographic planes or pinhole cameras) and registered base pose.
    trajectory : JointTrajectory
        Commanded joint values and rates at the frame times.
    delta_L_rad : float or array (T,)
        True torsional loss at every frame, rad.
    noise : NoiseSettings
        Segmentation noise in image units (mm in a plane, px in a camera; see
        :func:`image_sigma`).
    rng : numpy.random.Generator
    model_joint_offset : array (3,) or (T, 3), optional
        In-plane contact deflection made as the paper's experiment did: the catheter bends as
        if its joints were ``q + offset`` while the frames report the commanded ``q`` (see
        :func:`in_plane_joint_offset`).
    out_of_plane_mm : float or array (T,)
        Out-of-plane contact deflection of the tip, mm (see :func:`out_of_plane_offsets_b`).

    Raises
    ------
    ValueError
        If a point falls behind a pinhole camera.
    """
    q_true = trajectory.q if model_joint_offset is None else trajectory.q + model_joint_offset
    delta_L = np.broadcast_to(np.asarray(delta_L_rad, dtype=float), trajectory.time_s.shape)
    points_b = true_points_b(scene.catheter, q_true, delta_L)
    if np.any(np.asarray(out_of_plane_mm) != 0.0):
        deflection = np.broadcast_to(np.asarray(out_of_plane_mm, float), delta_L.shape)
        points_b = points_b + out_of_plane_offsets_b(
            scene.catheter, q_true[..., 0] + delta_L, deflection
        )
    points_w = points_b @ scene.R_w_b.T + scene.o_b_w_mm
    n_frames, n_points = points_w.shape[:2]
    cov = np.broadcast_to(isotropic_covariance(noise.sigma), (n_points, 2, 2))
    views = []
    for view in scene.rig.views:
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
            uv=tuple(uv[i] for uv in views),
            cov=(cov,) * len(views),
            delta_L_true_rad=float(delta_L[i]),
        )
        for i in range(n_frames)
    ]


@dataclass(frozen=True)
class FrameBatch:
    """Many independent trials of the same short trajectory, as arrays (for Monte Carlo).

    Trial ``i`` is the session ``frames(i)``; the arrays keep the batch axis first so that
    reconstruction and the closed-form estimators can run on all trials at once.
    """

    trajectory: JointTrajectory  # the commanded joints of every trial, T frames
    delta_L_rad: Array  # (n, T) true torsional loss
    points_w: Array  # (n, T, P, 3) true points in {W}, mm (tip first, then markers)
    uv: tuple[Array, ...]  # per view (n, T, P, 2) segmented points, NaN where dropped
    cov: tuple[Array, ...]  # per view (P, 2, 2) segmentation-noise covariance, image unit

    @property
    def n_trials(self) -> int:
        return int(self.uv[0].shape[0])

    def frames(self, trial: int) -> list[Frame]:
        """Trial ``trial`` as the frames the live loop consumes."""
        t = self.trajectory
        return [
            Frame(
                time_s=float(t.time_s[k]),
                q=t.q[k],
                q_dot=t.q_dot[k],
                uv=tuple(uv[trial, k] for uv in self.uv),
                cov=self.cov,
                delta_L_true_rad=float(self.delta_L_rad[trial, k]),
            )
            for k in range(t.time_s.size)
        ]


def _noisy_images(uv: Array, noise: NoiseSettings, rng: np.random.Generator) -> Array:
    uv = uv + noise.sigma * rng.standard_normal(uv.shape)
    if noise.outlier_probability > 0:
        outlier = rng.random(uv.shape[:-1]) < noise.outlier_probability
        direction = rng.standard_normal(uv.shape)
        direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
        uv = np.where(outlier[..., None], uv + noise.outlier_magnitude * direction, uv)
    if noise.dropout_probability > 0:
        dropped = rng.random(uv.shape[:-1]) < noise.dropout_probability
        uv = np.where(dropped[..., None], np.nan, uv)
    return uv


def simulate_batch(
    scene: Scene,
    trajectory: JointTrajectory,
    delta_L_rad: Array,
    noise: NoiseSettings,
    rng: np.random.Generator,
    model_joint_offset: Array | None = None,
    out_of_plane_mm: float = 0.0,
) -> FrameBatch:
    """n independent noisy trials of one trajectory, vectorised (the sensitivity studies).

    The same model as :func:`simulate_frames`; the shape integrals are computed once per
    frame of the trajectory and only rotated per trial, because delta_L enters only through a
    rotation about z_b.

    Parameters
    ----------
    delta_L_rad : array, shape (n,) or (n, T)
        True torsional loss of every trial (constant, or per frame), rad.
    model_joint_offset : array, shape (3,), optional
        In-plane deflection through the joints (see :func:`simulate_frames`).
    out_of_plane_mm : float
        Out-of-plane tip deflection, mm.

    Notes
    -----
    Random numbers are drawn in a fixed order (front view, then side view; noise, then
    outliers and dropouts only when their probabilities are non-zero), so a seeded generator
    gives the same batch every time.
    """
    catheter = scene.catheter
    T = trajectory.time_s.size
    delta_L = np.asarray(delta_L_rad, dtype=float)
    if delta_L.ndim == 1:
        delta_L = np.repeat(delta_L[:, None], T, axis=1)
    if delta_L.ndim != 2 or delta_L.shape[1] != T:
        raise ValueError(f"delta_L_rad must have shape (n,) or (n, {T}), got {delta_L.shape}")
    q_true = trajectory.q if model_joint_offset is None else trajectory.q + model_joint_offset
    shape = catheter.shape_vectors(q_true)
    c = np.concatenate([shape.c_tip_mm[:, None, :], shape.c_markers_mm], axis=1)  # (T, P, 3)
    delta_1 = q_true[:, 0] + delta_L  # (n, T)
    points_b = rotate_z(c[None], delta_1[..., None])
    if out_of_plane_mm != 0.0:
        points_b = points_b + out_of_plane_offsets_b(catheter, delta_1, out_of_plane_mm)
    points_w = points_b @ scene.R_w_b.T + scene.o_b_w_mm
    n_points = c.shape[1]
    cov = np.broadcast_to(isotropic_covariance(noise.sigma), (n_points, 2, 2)).copy()
    uv = tuple(_noisy_images(view.project(points_w), noise, rng) for view in scene.rig.views)
    covs = tuple(cov.copy() for _ in scene.rig.views)
    return FrameBatch(trajectory, delta_L, points_w, uv, covs)


@dataclass(frozen=True)
class LabConditions:
    """What a lab meets beyond segmentation noise (the ``cathtrack simulate`` options).

    Parameters
    ----------
    model_scale_error : float
        Relative model error: the true catheter bends ``1 + model_scale_error`` times as much
        as the model says (every modal-matrix column of a joint-dependent basis function is
        scaled; the straight configuration stays straight). 0.05 is a 5 % error.
    contact_joint_std_mm : float
        Contact deviation, mm: per configuration the catheter bends as if q_p and q_d were off
        by independent normal deviations of this std (:func:`contact_joint_offsets`).
    outlier_probability : float
        Probability that a segmented point in one view is a gross error.
    outlier_magnitude : float
        Size of such an error, image units (mm in a plane, px in a camera).
    dropout_probability : float
        Probability that a point is not segmented in one view.
    windup_play_rad : float
        Torsion wind-up with this play (:func:`torsion_windup`), rad; 0: no wind-up.
    """

    model_scale_error: float = 0.0
    contact_joint_std_mm: float = 0.0
    outlier_probability: float = 0.0
    outlier_magnitude: float = 10.0
    dropout_probability: float = 0.0
    windup_play_rad: float = 0.0

    def __post_init__(self) -> None:
        for name in ("contact_joint_std_mm", "outlier_magnitude", "windup_play_rad"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and non-negative, got {value}")
        if not (np.isfinite(self.model_scale_error) and self.model_scale_error > -1):
            raise ValueError(f"model_scale_error must be > -1, got {self.model_scale_error}")
        NoiseSettings(0.0, self.outlier_probability, self.outlier_magnitude,
                      self.dropout_probability)  # fmt: skip

    def noise(self, sigma: float) -> NoiseSettings:
        """Segmentation noise ``sigma`` (image units) with these outliers and dropouts."""
        return NoiseSettings(
            sigma, self.outlier_probability, self.outlier_magnitude, self.dropout_probability
        )


def truth_catheter(catheter: Catheter, model_scale_error: float) -> Catheter:
    """The catheter as it really bends when the model errs by ``model_scale_error``."""
    if model_scale_error == 0.0:
        return catheter
    probe = np.linspace(-1.0, 1.0, 5)
    segments = []
    for segment in (catheter.proximal, catheter.distal):
        values = segment.eta.values(probe)
        varying = np.ptp(values, axis=0) > 0
        A = np.array(segment.A, dtype=float)
        A[:, varying] *= 1.0 + model_scale_error
        segments.append(replace(segment, A=A))
    return replace(catheter, proximal=segments[0], distal=segments[1])


def contact_joint_offsets(rng: np.random.Generator, n: int, std_mm: float) -> Array:
    """Joint offsets (rad, mm, mm) of n configurations: q_p and q_d off by N(0, std^2)."""
    offsets = np.zeros((n, 3))
    if std_mm > 0:
        offsets[:, 1:] = std_mm * rng.standard_normal((n, 2))
    return offsets
