"""One task of the sensitivity studies: simulate its trials and score every method on them.

One trial
    ``frames_per_trial`` frames at the frame interval, the joints moving at the stated
    constant rates and arriving at the study's configuration on the last frame; a true
    delta_L drawn uniformly on [-pi, pi) (or fixed), constant over the trial; Gaussian
    segmentation noise in both images. The per-frame estimators are scored on the last
    frame (Tip Velocity: the finite difference of the last two), the UKF after the whole
    trial, and the bounds on the last frame (``crb-tip``, ``crb-body``, ``crb-velocity``) and
    on all frames together (``crb-all-frames``: tip and markers of every frame, the limit of
    any estimator that uses the whole trial, such as the UKF).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from models.bounds import block_diagonal, information_from_covariance, std_from_information
from models.catheter import Catheter
from models.pose import Pose
from models.rotation_fit import rotation_fisher_information
from models.rotations import rotate_z, wrap_angle
from replay.parallel import single_blas_thread
from replay.simulation.simulator import (
    FrameBatch,
    NoiseSettings,
    Scene,
    image_sigma,
    ramp,
    simulate_batch,
)
from replay.studies.settings import (
    BASELINE_METHODS,
    BOUND_METHOD,
    CLOSED_FORM_METHODS,
    FILTER_METHODS,
    SIGMA_FLOOR_MM,
    STRAIGHT_RADIUS_MM,
    SensitivitySettings,
    Task,
    scene_for,
)
from tracker.estimators import make_estimator
from tracker.estimators.per_frame import PerFrameEstimator, build_problem_batch, closed_form_batch
from tracker.estimators.ukf_batch import finite_difference_velocity, run_ukf_batch
from tracker.types import Observation, velocity_from_positions

Array = np.ndarray


@dataclass(frozen=True)
class TrialData:
    """One task's trials: the simulated frames, their reconstruction and the truth."""

    batch: FrameBatch
    catheter: Catheter
    scene: Scene
    points_b: Array  # (n, T, P, 3) reconstructed tip and markers in {B}, mm
    # Covariances as the estimators are told them, mm^2: (n, T, P, 3, 3), or (1, 1, P, 3, 3)
    # when they are the same for every trial and frame (orthographic views).
    cov_b: Array
    true_cov_b: Array  # the same at the true points (for the bound)
    c_true: Array  # (T, P, 3) delta_L-independent vectors of the true (deflected) shape
    u_true: Array  # (3,) true tip velocity vector at the last frame, mm/s
    sigma_scale: float  # true noise / noise the estimators are told
    frame_interval_s: float

    @property
    def delta_L_rad(self) -> Array:
        return self.batch.delta_L_rad[:, -1]

    def observations(self, trial: int) -> list[Observation]:
        """The trial's observations, as the Reconstructor would make them from its frames."""
        t = self.batch.trajectory
        cov_b = np.broadcast_to(self.cov_b, self.points_b.shape + (3,))[trial]
        out = []
        for k in range(t.time_s.size):
            velocity = {}
            if k > 0:
                v, cov_v, cross = velocity_from_positions(
                    self.points_b[trial, k, 0],
                    cov_b[k, 0],
                    self.points_b[trial, k - 1, 0],
                    cov_b[k - 1, 0],
                    float(t.time_s[k] - t.time_s[k - 1]),
                )
                velocity = dict(velocity_b_mm_s=v, velocity_cov_b=cov_v, velocity_tip_cov_b=cross)
            out.append(
                Observation(
                    time_s=float(t.time_s[k]),
                    q=t.q[k],
                    q_dot=t.q_dot[k],
                    tip_b_mm=self.points_b[trial, k, 0],
                    tip_cov_b=cov_b[k, 0],
                    markers_b_mm=self.points_b[trial, k, 1:],
                    markers_cov_b=cov_b[k, 1:],
                    **velocity,
                )
            )
        return out


def simulate_task(settings: SensitivitySettings, task: Task) -> TrialData:
    """Simulate and reconstruct the trials of one task from its own random stream."""
    point = task.point
    rng = np.random.default_rng(np.random.SeedSequence(settings.seed, spawn_key=task.seed_key))
    n = task.stop - task.start
    scene = scene_for(point.delta_2_deg, settings.view)
    pose = Pose(scene.R_w_b, scene.o_b_w_mm)
    catheter, rig = scene.catheter, scene.rig
    dt = settings.frame_interval_s
    trajectory = ramp(point.q, settings.joint_rates, settings.frames_per_trial, dt)
    if settings.delta_L_deg is None:
        delta_L = rng.uniform(-np.pi, np.pi, n)
    else:
        delta_L = np.full(n, math.radians(settings.delta_L_deg))
    sigma_true = image_sigma(rig.views[0], point.noise_mm)
    sigma_model = image_sigma(rig.views[0], max(point.noise_mm, SIGMA_FLOOR_MM))
    batch = simulate_batch(
        scene,
        trajectory,
        delta_L,
        NoiseSettings(sigma=sigma_true),
        rng,
        model_joint_offset=np.asarray(point.joint_offset),
        out_of_plane_mm=point.out_of_plane_mm,
    )
    cov_image = np.eye(2) * sigma_model**2
    points_w = rig.reconstruct(*batch.uv)
    if rig.kind == "orthographic":
        # The reconstruction is linear: one covariance for every point, trial and frame.
        cov_w = rig.reconstruction_covariance(batch.points_w[:1, :1], cov_image, cov_image)
        true_cov_w = cov_w
    else:
        cov_w = rig.reconstruction_covariance(points_w, cov_image, cov_image)
        true_cov_w = rig.reconstruction_covariance(batch.points_w, cov_image, cov_image)
    # True shape vectors: delta_L-independent (rotate the true points back by delta_1).
    q_true = trajectory.q + np.asarray(point.joint_offset)
    delta_1 = q_true[:, 0] + batch.delta_L_rad[0]
    c_true = rotate_z(pose.base_from_world(batch.points_w[0]), -delta_1[:, None])
    shape = catheter.shape_vectors(q_true[-1], trajectory.q_dot[-1])
    # The out-of-plane offset turns with the base as well: its velocity is q_r_dot z x w.
    offset_tip = c_true[-1, 0] - shape.c_tip_mm
    u_true = shape.u_tip_mm_s + trajectory.q_dot[-1, 0] * np.array(
        [-offset_tip[1], offset_tip[0], 0.0]
    )
    return TrialData(
        batch=batch,
        catheter=catheter,
        scene=scene,
        points_b=pose.base_from_world(points_w),
        cov_b=pose.covariance_to_base(cov_w),
        true_cov_b=pose.covariance_to_base(true_cov_w),
        c_true=c_true,
        u_true=u_true,
        sigma_scale=sigma_true / sigma_model,
        frame_interval_s=dt,
    )


def _frame(cov: Array, k: int) -> Array:
    """Frame k of covariances (n, T, ...) that may be broadcast over frames (n, 1, ...)."""
    return cov[:, k] if cov.shape[1] > 1 else cov[:, 0]


def closed_form_errors(data: TrialData, kind: str) -> Array:
    """Signed errors (rad) of one per-frame closed form on the last frame of every trial."""
    traj = data.batch.trajectory
    shape = data.catheter.shape_vectors(traj.q[-1], traj.q_dot[-1])
    points, cov = data.points_b[:, -1], _frame(data.cov_b, -1)
    if kind == "velocity":
        velocity, velocity_cov, _ = velocity_from_positions(
            points[:, 0],
            cov[:, 0],
            data.points_b[:, -2, 0],
            _frame(data.cov_b, -2)[:, 0],
            data.frame_interval_s,
        )
        problem = build_problem_batch(
            kind, shape, velocity_b_mm_s=velocity, velocity_cov_b=velocity_cov
        )
    else:
        problem = build_problem_batch(kind, shape, points, cov)
    delta_L, _ = closed_form_batch(problem)
    return wrap_angle(delta_L - data.delta_L_rad)


def bound_std(data: TrialData) -> dict[str, Array]:
    """Cramer-Rao bounds on the std of delta_L per trial, rad, for the rows of BOUND_ROWS."""
    n = data.points_b.shape[0]
    phi = data.batch.trajectory.q[:, 0] + data.batch.delta_L_rad  # (n, T)
    cov = data.true_cov_b
    # The finite difference's covariance (the positions only complete the call).
    tip = data.c_true[-1, 0]
    _, velocity_cov, _ = velocity_from_positions(
        tip, _frame(cov, -1)[:, 0], tip, _frame(cov, -2)[:, 0], data.frame_interval_s
    )

    def info(c: Array, covariance: Array, angle: Array) -> Array:
        c = np.broadcast_to(c, angle.shape + c.shape[-2:])
        value = rotation_fisher_information(c, information_from_covariance(covariance), angle)
        # Straight (no horizontal extent, up to rounding): no information at all.
        straight = np.sqrt(np.sum(c[..., :2] ** 2, axis=(-2, -1))) < STRAIGHT_RADIUS_MM
        return np.where(straight, 0.0, value)

    infos = {
        "crb-tip": info(data.c_true[-1, :1], _frame(cov, -1)[:, 0], phi[:, -1]),
        "crb-body": info(data.c_true[-1], block_diagonal(_frame(cov, -1)), phi[:, -1]),
        "crb-velocity": info(data.u_true[None], velocity_cov, phi[:, -1]),
        "crb-all-frames": np.sum(info(data.c_true, block_diagonal(cov), phi), axis=-1),
    }
    out = {}
    for name, value in infos.items():
        std = std_from_information(value)
        out[name] = np.broadcast_to(std * data.sigma_scale, (n,)).copy()
        if data.sigma_scale == 0.0:
            out[name] = np.zeros(n)
    return out


def stepped_errors(data: TrialData, method: str, trials: int) -> Array:
    """Signed errors (rad) of an estimator stepped frame by frame on the first trials.

    The UKF runs over every frame of the trial and is scored on its last estimate; a
    least-squares baseline runs on the last frame. Invalid estimates are NaN. (The studies run
    the UKF through :func:`ukf_errors`, which gives the same errors for all trials at once.)
    """
    errors = np.full(trials, np.nan)
    if method in BASELINE_METHODS:
        estimator = PerFrameEstimator(data.catheter, BASELINE_METHODS[method], "least-squares")
    else:
        estimator = make_estimator(method, data.catheter)
    for i in range(trials):
        observations = data.observations(i)
        estimator.reset()
        if method in BASELINE_METHODS:
            estimate = estimator.step(observations[-1])
        else:
            for observation in observations:
                estimate = estimator.step(observation)
        if estimate.valid:
            errors[i] = wrap_angle(estimate.delta_L_rad - data.delta_L_rad[i])
    return errors


def ukf_errors(data: TrialData, method: str, trials: int) -> Array:
    """Signed errors (rad) of the UKF after the last frame of each of the first trials.

    :func:`tracker.estimators.ukf_batch.run_ukf_batch` runs one filter per trial on the observations
    :meth:`TrialData.observations` makes (tip, markers, finite-difference velocity), all trials
    at once; it is the same filter as :class:`BendingPlaneUKF` stepped trial by
    trial (:func:`stepped_errors`). Invalid estimates are NaN.
    """
    settings = make_estimator(method, data.catheter).settings
    traj = data.batch.trajectory
    points = data.points_b[:trials]
    cov = data.cov_b[:trials] if data.cov_b.shape[0] > 1 else data.cov_b
    velocity, velocity_cov, cross = finite_difference_velocity(
        traj.time_s, points[:, :, 0], cov[:, :, 0]
    )
    result = run_ukf_batch(
        data.catheter,
        settings,
        traj.time_s,
        traj.q,
        traj.q_dot,
        points[:, :, 0],
        cov[:, :, 0],
        points[:, :, 1:],
        cov[:, :, 1:],
        velocity,
        velocity_cov,
        cross,
    )
    return wrap_angle(result.delta_L_rad[:, -1] - data.delta_L_rad[:trials])


@dataclass(frozen=True)
class TaskResult:
    """Signed errors (estimators) or bound stds (bound rows) per trial of one task, rad."""

    task: Task
    values: dict[str, Array] = field(default_factory=dict)


def run_task(settings: SensitivitySettings, task: Task) -> TaskResult:
    """Simulate one task's trials and score every method on them."""
    with single_blas_thread():
        return _run_task(settings, task)


def _run_task(settings: SensitivitySettings, task: Task) -> TaskResult:
    data = simulate_task(settings, task)
    values: dict[str, Array] = {}
    stepped = max(0, min(task.stop, settings.effective_ukf_trials) - task.start)
    for method in settings.methods:
        if method in CLOSED_FORM_METHODS:
            values[method] = closed_form_errors(data, CLOSED_FORM_METHODS[method])
        elif method == BOUND_METHOD:
            values.update(bound_std(data))
        elif method in FILTER_METHODS and stepped:
            values[method] = ukf_errors(data, method, stepped)
        elif stepped:
            values[method] = stepped_errors(data, method, stepped)
    return TaskResult(task, values)


def baseline_task(settings: SensitivitySettings, task: Task) -> dict[str, Array]:
    """Closed form and least-squares baseline on the same frames: wrapped differences, rad."""
    with single_blas_thread():
        data = simulate_task(settings, task)
        out = {}
        for name, kind in CLOSED_FORM_METHODS.items():
            closed = closed_form_errors(data, kind)
            baseline = stepped_errors(data, name + "-lsq", closed.size)
            out[name] = wrap_angle(baseline - closed)
        return out
