"""The paper's three sensitivity studies, for every estimator, next to the Cramer-Rao bound.

Lawson, Chitale and Simaan (ICRA 2023) judge a bending-plane estimator by how its error
grows (a) with the segmentation noise, (b) over the workspace of tip angles, toward the
straight configuration, and (c) with a tip deflection by contact that the model does not know.
This module reproduces the three studies for the per-frame estimators (Tip Position, Body
Positions, Tip Velocity), the UKF and the Cramer-Rao bound, each for ``delta_2 = 0`` and a
non-planar ``delta_2``, and goes further: pinhole views as well as the paper's planes, an
out-of-plane deflection besides the paper's in-plane one, motion for Tip Velocity with stated
joint rates and frame interval, and the bound for a filter that uses every frame.

One trial
    ``frames_per_trial`` frames at the frame interval, the joints moving at the stated
    constant rates and arriving at the study's configuration on the last frame; a true
    delta_L drawn uniformly on [-pi, pi) (or fixed), constant over the trial; Gaussian
    segmentation noise in both images. The per-frame estimators are scored on the last
    frame (Tip Velocity: the finite difference of the last two), the UKF after the whole
    trial, and the bounds on the last frame (``crb-tip``, ``crb-body``, ``crb-velocity``) and
    on all frames together (``crb-all-frames``: tip and markers of every frame, the limit of
    any estimator that uses the whole trial, such as the UKF).

Speed
    The per-frame closed forms run on all trials of a task at once (one batched
    reconstruction, one batched rotation fit), and so does the UKF: one filter per trial,
    stepped together over the frames by :func:`tracker.estimators.ukf_batch.run_ukf_batch` (the same
    filter as :class:`~tracker.estimators.ukf.BendingPlaneUKF`, to rounding). Only the optional
    least-squares baselines step trial by trial. The UKF and the baselines run on the first
    ``ukf_trials`` trials of every study point (by default all of them).

Tasks and seeds
    Each (study, variant, delta_2, level, chunk of ``chunk_trials`` trials) is an independent
    task with its own random stream, ``SeedSequence(seed, spawn_key=task key)``, so the
    results do not depend on how many workers run them or in which order. Tasks run in-process
    (one worker), on a local process pool, or on a Dask cluster.
"""

from __future__ import annotations

import contextlib
import csv
import ctypes
import dataclasses
import json
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from models.bounds import block_diagonal, information_from_covariance
from models.catheter import Catheter, default_catheter
from models.imaging import default_orthographic_rig, default_pinhole_rig
from models.rotation_fit import rotation_fisher_information
from models.rotations import wrap_angle
from replay.simulation.simulator import (
    FrameBatch,
    NoiseSettings,
    Scene,
    default_scene,
    image_sigma,
    in_plane_joint_offset,
    joints_from_tip_angles,
    ramp,
    simulate_batch,
)
from tracker.estimators import make_estimator
from tracker.estimators.per_frame import PerFrameEstimator, closed_form_batch
from tracker.estimators.ukf_batch import finite_difference_velocity, run_ukf_batch
from tracker.types import Observation, velocity_from_positions

Array = np.ndarray

STUDIES = ("a", "b", "c")
STUDY_TITLES = {
    "a": "error against segmentation noise",
    "b": "error over the workspace of tip angles",
    "c": "error against tip deflection by contact",
}
CLOSED_FORM_METHODS = {"tip-position": "tip", "body-positions": "body", "tip-velocity": "velocity"}
BASELINE_METHODS = {name + "-lsq": kind for name, kind in CLOSED_FORM_METHODS.items()}
FILTER_METHODS = ("ukf", "ukf-position")
BOUND_METHOD = "crb"
METHODS = (*CLOSED_FORM_METHODS, *BASELINE_METHODS, *FILTER_METHODS, BOUND_METHOD)
DEFAULT_METHODS = ("tip-position", "body-positions", "tip-velocity", "ukf", BOUND_METHOD)
# The rows the "crb" method produces, and the estimator each one limits.
BOUND_ROWS = {
    "crb-tip": "tip-position",
    "crb-body": "body-positions",
    "crb-velocity": "tip-velocity",
    "crb-all-frames": "ukf",
}
VIEWS = ("orthographic", "pinhole")
DEFLECTIONS = ("in-plane", "out-of-plane")
DEFLECTION_JOINTS = {"q_p": 1, "q_d": 2}
# Noise the estimators are told when the true noise is zero: a zero covariance has no inverse.
# The weights only matter up to scale, so this changes no estimate.
SIGMA_FLOOR_MM = 1e-3
# Below this horizontal extent of the data a configuration counts as straight (no information).
STRAIGHT_RADIUS_MM = 1e-9
# Bounds up to this (0.1 rad) are the small-noise regime where an efficient estimator attains
# them; beyond it the angle estimate is visibly non-Gaussian.
LINEAR_REGIME_DEG = 6.0
# Quantiles of |N(0, 1)|: an efficient unbiased estimator's |error| at the bound's std.
ABS_NORMAL_QUANTILES = {
    "p25": 0.31863936396437514,
    "median": 0.6744897501960817,
    "p75": 1.1503493803760079,
}
CSV_COLUMNS = (
    "study",
    "variant",
    "delta_2_deg",
    "noise_mm",
    "theta_L1_deg",
    "theta_L2_deg",
    "deflection_mm",
    "method",
    "kind",
    "median_deg",
    "p25_deg",
    "p75_deg",
    "rms_deg",
    "n",
    "valid_fraction",
)


def _levels(start: float, stop: float, count: int) -> tuple[float, ...]:
    return tuple(float(round(x, 12)) for x in np.linspace(start, stop, count))


def _floats(values, name: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a list of numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name} must be finite, got {list(out)}")
    return out


def _names(values, name: str, allowed: Sequence[str]) -> tuple[str, ...]:
    if isinstance(values, str):
        values = (values,)
    out = tuple(str(v) for v in values)
    for v in out:
        if v not in allowed:
            raise ValueError(f"unknown {name} {v!r}; choose from {', '.join(allowed)}")
    if not out:
        raise ValueError(f"no {name} given; choose from {', '.join(allowed)}")
    if len(set(out)) != len(out):
        raise ValueError(f"{name} given twice in {list(out)}")
    return out


@dataclass(frozen=True)
class SensitivitySettings:
    """Everything that defines a run of the studies (saved beside the results).

    Parameters
    ----------
    seed : int
        Root of every random stream.
    trials : int
        Monte Carlo trials per study point for the per-frame estimators and the bound.
    ukf_trials : int
        Trials per study point on which the UKF (and any least-squares baseline) runs: the
        first ``min(ukf_trials, trials)`` of the same trials. The default runs the UKF on all
        500 (it is batched over trials, see :func:`ukf_errors`); the least-squares baselines
        step trial by trial, so a run with them may want fewer.
    chunk_trials : int
        Trials per task. Results depend on it (it cuts the random streams), not on workers.
    methods : tuple of str
        Any of :data:`METHODS`; ``"crb"`` adds the bound rows of :data:`BOUND_ROWS`.
    studies : tuple of str
        Any of ``"a"``, ``"b"``, ``"c"``.
    delta_2_deg : tuple of float
        Distal bending-plane angles to run every study for, deg.
    view : {"orthographic", "pinhole"}
        The paper's planes or the default pinhole cameras (noise in mm at the isocentre,
        converted to px with their magnification).
    noise_levels_mm : tuple of float
        Study (a): segmentation noise levels, mm (per image axis, in each view).
    noise_mm : float
        Studies (b) and (c): segmentation noise, mm.
    configuration_theta_L_deg : (float, float)
        Studies (a) and (c): tip angles (theta_L1, theta_L2), deg (90 is straight).
    theta_L1_deg, theta_L2_deg : tuple of float
        Study (b): the grid of tip angles, deg.
    deflection_levels_mm : tuple of float
        Study (c): tip deflections, mm.
    deflections : tuple of str
        Study (c): ``"in-plane"`` (the paper's: the joints that shape the catheter differ
        from the ones the model sees) and/or ``"out-of-plane"``.
    deflection_joint : {"q_p", "q_d"}
        The joint perturbed for an in-plane deflection.
    joint_rates : (float, float, float)
        Constant joint rates during a trial (q_r rad/s, q_p mm/s, q_d mm/s).
    frame_interval_s : float
        Time between frames, s.
    frames_per_trial : int
        Frames per trial, >= 2 (Tip Velocity needs two).
    delta_L_deg : float or None
        True torsional loss, deg; None draws it uniformly on [-180, 180) per trial.
    """

    seed: int = 0
    trials: int = 500
    ukf_trials: int = 500
    chunk_trials: int = 500
    methods: tuple[str, ...] = DEFAULT_METHODS
    studies: tuple[str, ...] = STUDIES
    delta_2_deg: tuple[float, ...] = (0.0, 90.0)
    view: str = "orthographic"
    noise_levels_mm: tuple[float, ...] = _levels(0.0, 5.0, 11)
    noise_mm: float = 1.0
    configuration_theta_L_deg: tuple[float, float] = (45.0, 45.0)
    theta_L1_deg: tuple[float, ...] = _levels(0.0, 180.0, 9)
    theta_L2_deg: tuple[float, ...] = _levels(0.0, 180.0, 9)
    deflection_levels_mm: tuple[float, ...] = _levels(0.0, 10.0, 11)
    deflections: tuple[str, ...] = DEFLECTIONS
    deflection_joint: str = "q_d"
    joint_rates: tuple[float, float, float] = (0.5, 0.25, 0.25)
    frame_interval_s: float = 0.05
    frames_per_trial: int = 10
    delta_L_deg: float | None = None

    def __post_init__(self) -> None:
        def put(name: str, value) -> None:
            object.__setattr__(self, name, value)

        for name in ("seed", "trials", "ukf_trials", "chunk_trials", "frames_per_trial"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value:
                raise ValueError(f"{name} must be an integer, got {value!r}")
            put(name, int(value))
        if self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed}")
        if self.trials < 1:
            raise ValueError(f"trials must be at least 1, got {self.trials}")
        if self.ukf_trials < 0:
            raise ValueError(f"ukf_trials must be non-negative, got {self.ukf_trials}")
        if self.chunk_trials < 1:
            raise ValueError(f"chunk_trials must be at least 1, got {self.chunk_trials}")
        if self.frames_per_trial < 2:
            raise ValueError(
                f"frames_per_trial must be at least 2 (Tip Velocity differences two frames),"
                f" got {self.frames_per_trial}"
            )
        put("methods", _names(self.methods, "method", METHODS))
        put("studies", _names(self.studies, "study", STUDIES))
        put("deflections", _names(self.deflections, "deflection", DEFLECTIONS))
        put("view", _names(self.view, "view", VIEWS)[0])
        put(
            "deflection_joint",
            _names(self.deflection_joint, "deflection joint", tuple(DEFLECTION_JOINTS))[0],
        )
        for name, label in (
            ("delta_2_deg", "delta_2 list"),
            ("noise_levels_mm", "noise levels (study a)"),
            ("theta_L1_deg", "theta_L1 grid (study b)"),
            ("theta_L2_deg", "theta_L2 grid (study b)"),
            ("deflection_levels_mm", "deflection levels (study c)"),
        ):
            values = _floats(getattr(self, name), name)
            if not values:
                raise ValueError(f"the {label} is empty: give at least one value")
            twice = sorted({v for v in values if values.count(v) > 1})
            if twice:
                raise ValueError(f"the {label} has {twice[0]:g} twice")
            put(name, values)
        for name, unit in (("noise_levels_mm", "noise"), ("deflection_levels_mm", "deflection")):
            negative = [v for v in getattr(self, name) if v < 0]
            if negative:
                raise ValueError(f"{unit} levels must be non-negative (mm), got {negative[0]:g}")
        noise = _floats([self.noise_mm], "noise_mm")[0]
        if noise < 0:
            raise ValueError(f"noise must be non-negative (mm), got {noise:g}")
        put("noise_mm", noise)
        config = _floats(self.configuration_theta_L_deg, "configuration_theta_L_deg")
        if len(config) != 2:
            raise ValueError(
                f"configuration_theta_L_deg needs two tip angles (theta_L1, theta_L2), got"
                f" {list(config)}"
            )
        put("configuration_theta_L_deg", config)
        rates = _floats(self.joint_rates, "joint_rates")
        if len(rates) != 3:
            raise ValueError(
                f"joint_rates needs three values (q_r rad/s, q_p mm/s, q_d mm/s), got {list(rates)}"
            )
        put("joint_rates", rates)
        dt = _floats([self.frame_interval_s], "frame_interval_s")[0]
        if dt <= 0:
            raise ValueError(f"frame_interval_s must be positive, got {dt:g}")
        put("frame_interval_s", dt)
        if self.delta_L_deg is not None:
            put("delta_L_deg", _floats([self.delta_L_deg], "delta_L_deg")[0])

    @property
    def effective_ukf_trials(self) -> int:
        return min(self.ukf_trials, self.trials)

    def to_dict(self) -> dict:
        return {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, values: dict) -> SensitivitySettings:
        """Settings from a dict such as the ``settings`` of a saved settings.json."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown setting(s) {', '.join(unknown)}")
        return cls(**values)


def _jsonable(value):
    if isinstance(value, tuple):
        return [_jsonable(v) for v in value]
    return value


# ------------------------------------------------------------------------------ study plan
@dataclass(frozen=True)
class StudyPoint:
    """One point of one study: a configuration, a noise level and a deflection."""

    study: str
    variant: str  # "" or the deflection kind of study (c)
    delta_2_deg: float
    noise_mm: float
    theta_L1_deg: float
    theta_L2_deg: float
    deflection_mm: float
    q: tuple[float, float, float]  # joint values at the last frame (rad, mm, mm)
    joint_offset: tuple[float, float, float]  # in-plane deflection through the joints
    out_of_plane_mm: float
    key: tuple[int, ...]  # (study, variant, delta_2, level, level): seeds and order

    @property
    def bending_deg(self) -> float:
        """Largest bending angle of the two segments, deg (0: straight)."""
        return max(abs(90.0 - self.theta_L1_deg), abs(90.0 - self.theta_L2_deg))

    @property
    def label(self) -> dict[str, object]:
        return {
            "study": self.study,
            "variant": self.variant,
            "delta_2_deg": self.delta_2_deg,
            "noise_mm": self.noise_mm,
            "theta_L1_deg": self.theta_L1_deg,
            "theta_L2_deg": self.theta_L2_deg,
            "deflection_mm": self.deflection_mm,
        }


@dataclass(frozen=True)
class Task:
    """Trials ``[start, stop)`` of one study point."""

    point: StudyPoint
    chunk: int
    start: int
    stop: int

    @property
    def seed_key(self) -> tuple[int, ...]:
        return self.point.key + (self.chunk,)


@lru_cache(maxsize=16)
def _catheter(delta_2_deg: float) -> Catheter:
    return default_catheter(math.radians(delta_2_deg))


@lru_cache(maxsize=16)
def _scene(delta_2_deg: float, view: str) -> Scene:
    rig = default_orthographic_rig() if view == "orthographic" else default_pinhole_rig()
    return default_scene(_catheter(delta_2_deg), rig)


def _configuration(catheter: Catheter, theta_deg: tuple[float, float]) -> tuple[float, ...]:
    q = joints_from_tip_angles(catheter, math.radians(theta_deg[0]), math.radians(theta_deg[1]))
    return tuple(float(x) for x in q)


def study_points(settings: SensitivitySettings) -> list[StudyPoint]:
    """Every point of the selected studies, in a fixed order.

    Raises ValueError (before any work starts) for a tip angle the model cannot reach or a
    deflection no joint offset makes.
    """
    points = []
    cfg = settings.configuration_theta_L_deg
    for d, delta_2 in enumerate(settings.delta_2_deg):
        catheter = _catheter(delta_2)
        q_cfg = _configuration(catheter, cfg)
        base = dict(delta_2_deg=delta_2, joint_offset=(0.0, 0.0, 0.0), out_of_plane_mm=0.0)
        if "a" in settings.studies:
            for i, sigma in enumerate(settings.noise_levels_mm):
                points.append(
                    StudyPoint(
                        "a",
                        "",
                        noise_mm=sigma,
                        theta_L1_deg=cfg[0],
                        theta_L2_deg=cfg[1],
                        deflection_mm=0.0,
                        q=q_cfg,
                        key=(0, 0, d, i, 0),
                        **base,
                    )
                )
        if "b" in settings.studies:
            for i, t1 in enumerate(settings.theta_L1_deg):
                for j, t2 in enumerate(settings.theta_L2_deg):
                    points.append(
                        StudyPoint(
                            "b",
                            "",
                            noise_mm=settings.noise_mm,
                            theta_L1_deg=t1,
                            theta_L2_deg=t2,
                            deflection_mm=0.0,
                            q=_configuration(catheter, (t1, t2)),
                            key=(1, 0, d, i, j),
                            **base,
                        )
                    )
        if "c" in settings.studies:
            joint = DEFLECTION_JOINTS[settings.deflection_joint]
            for v, variant in enumerate(DEFLECTIONS):
                if variant not in settings.deflections:
                    continue
                for i, deflection in enumerate(settings.deflection_levels_mm):
                    offset, out_of_plane = (0.0, 0.0, 0.0), 0.0
                    if variant == "in-plane":
                        offset = tuple(
                            float(x)
                            for x in in_plane_joint_offset(catheter, q_cfg, deflection, joint)
                        )
                    else:
                        out_of_plane = deflection
                    points.append(
                        StudyPoint(
                            "c",
                            variant,
                            delta_2_deg=delta_2,
                            noise_mm=settings.noise_mm,
                            theta_L1_deg=cfg[0],
                            theta_L2_deg=cfg[1],
                            deflection_mm=deflection,
                            q=q_cfg,
                            joint_offset=offset,
                            out_of_plane_mm=out_of_plane,
                            key=(2, v, d, i, 0),
                        )
                    )
    return points


def make_tasks(settings: SensitivitySettings, points: Sequence[StudyPoint]) -> list[Task]:
    """Cut every study point into chunks of ``chunk_trials`` trials."""
    tasks = []
    for point in points:
        for chunk, start in enumerate(range(0, settings.trials, settings.chunk_trials)):
            tasks.append(
                Task(point, chunk, start, min(start + settings.chunk_trials, settings.trials))
            )
    return tasks


# ------------------------------------------------------------------------------ BLAS threads
_OPENBLAS_THREADS = (
    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
    ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
    ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
    ("openblas_get_num_threads", "openblas_set_num_threads"),
)
_openblas_controls: list | None = None


def _openblas() -> list:
    """(get, set) thread-count functions of every OpenBLAS loaded here (numpy's, scipy's)."""
    global _openblas_controls
    if _openblas_controls is None:
        _openblas_controls = []
        try:
            with open("/proc/self/maps") as maps:
                paths = sorted({ln.split()[-1] for ln in maps if "openblas" in ln.lower()})
        except OSError:  # not Linux: leave the threads alone
            paths = []
        for path in paths:
            try:
                lib = ctypes.CDLL(path)
            except OSError:
                continue
            for get, put in _OPENBLAS_THREADS:
                if hasattr(lib, get) and hasattr(lib, put):
                    _openblas_controls.append((getattr(lib, get), getattr(lib, put)))
                    break
    return _openblas_controls


_blas_lock = threading.Lock()
_blas_users = 0
_blas_previous: list[int] = []


@contextlib.contextmanager
def single_blas_thread():
    """Run the block with OpenBLAS on one thread, then restore the previous thread counts.

    The studies are parallel over tasks; inside a task the linear algebra is on tiny matrices
    (the UKF factorises a 12 x 12 covariance per frame), where OpenBLAS's own threads only
    cost: on a 2-core machine shared with other work they made a UKF step 10 to 30 times
    slower (about 2 ms instead of 0.2 ms). Tasks running in threads of one process (a Dask
    worker) share the setting: the first one in sets it, the last one out restores it.
    """
    global _blas_users, _blas_previous
    with _blas_lock:
        if _blas_users == 0:
            controls = _openblas()
            _blas_previous = [get() for get, _ in controls]
            for _, put in controls:
                put(1)
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0:
                for (_, put), n in zip(_openblas(), _blas_previous, strict=True):
                    put(n)


# ------------------------------------------------------------------------------ one task
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
    scene = _scene(point.delta_2_deg, settings.view)
    catheter, rig = scene.catheter, scene.rig
    dt = settings.frame_interval_s
    trajectory = ramp(point.q, settings.joint_rates, settings.frames_per_trial, dt)
    if settings.delta_L_deg is None:
        delta_L = rng.uniform(-np.pi, np.pi, n)
    else:
        delta_L = np.full(n, math.radians(settings.delta_L_deg))
    sigma_true = image_sigma(rig.front, point.noise_mm)
    sigma_model = image_sigma(rig.front, max(point.noise_mm, SIGMA_FLOOR_MM))
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
    R_b_w = scene.R_w_b.T
    points_w = rig.reconstruct(batch.uv_front, batch.uv_side)
    points_b = (points_w - scene.o_b_w_mm) @ R_b_w.T
    if rig.kind == "orthographic":
        # The reconstruction is linear: one covariance for every point, trial and frame.
        cov_w = rig.reconstruction_covariance(batch.points_w[:1, :1], cov_image, cov_image)
        true_cov_w = cov_w
    else:
        cov_w = rig.reconstruction_covariance(points_w, cov_image, cov_image)
        true_cov_w = rig.reconstruction_covariance(batch.points_w, cov_image, cov_image)
    # True shape vectors: delta_L-independent (rotate the true points back by delta_1).
    q_true = trajectory.q + np.asarray(point.joint_offset)
    points_true_b = (batch.points_w[0] - scene.o_b_w_mm) @ R_b_w.T
    c_true = _rotate_back(points_true_b, q_true[:, 0] + batch.delta_L_rad[0])
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
        points_b=points_b,
        cov_b=R_b_w @ cov_w @ scene.R_w_b,
        true_cov_b=R_b_w @ true_cov_w @ scene.R_w_b,
        c_true=c_true,
        u_true=u_true,
        sigma_scale=sigma_true / sigma_model,
        frame_interval_s=dt,
    )


def _rotate_back(points_b: Array, delta_1: Array) -> Array:
    c, s = np.cos(delta_1)[:, None], np.sin(delta_1)[:, None]
    out = points_b.copy()
    out[..., 0] = c * points_b[..., 0] + s * points_b[..., 1]
    out[..., 1] = -s * points_b[..., 0] + c * points_b[..., 1]
    return out


def _frame(cov: Array, k: int) -> Array:
    """Frame k of covariances (n, T, ...) that may be broadcast over frames (n, 1, ...)."""
    return cov[:, k] if cov.shape[1] > 1 else cov[:, 0]


def closed_form_errors(data: TrialData, kind: str) -> Array:
    """Signed errors (rad) of one per-frame closed form on the last frame of every trial."""
    traj = data.batch.trajectory
    n = data.points_b.shape[0]
    shape = data.catheter.shape_vectors(traj.q[-1], traj.q_dot[-1])
    if kind == "tip":
        y = data.points_b[:, -1, :1]
        c = shape.c_tip_mm[None]
        cov = _frame(data.cov_b, -1)[:, 0]
    elif kind == "body":
        # Body Positions: the tip and every backbone marker (the rows of a frame).
        y = data.points_b[:, -1]
        c = np.concatenate([shape.c_tip_mm[None], shape.c_markers_mm])
        cov = block_diagonal(_frame(data.cov_b, -1))
    else:
        dt = data.frame_interval_s
        y = ((data.points_b[:, -1, 0] - data.points_b[:, -2, 0]) / dt)[:, None]
        c = shape.u_tip_mm_s[None]
        cov = (_frame(data.cov_b, -1)[:, 0] + _frame(data.cov_b, -2)[:, 0]) / dt**2
    c = np.broadcast_to(c, (n,) + c.shape)
    delta_L, _ = closed_form_batch(c, y, cov, np.full(n, traj.q[-1, 0]))
    return wrap_angle(delta_L - data.delta_L_rad)


def bound_std(data: TrialData) -> dict[str, Array]:
    """Cramer-Rao bounds on the std of delta_L per trial, rad, for the rows of BOUND_ROWS."""
    n = data.points_b.shape[0]
    phi = data.batch.trajectory.q[:, 0] + data.batch.delta_L_rad  # (n, T)
    cov = data.true_cov_b
    dt = data.frame_interval_s

    def info(c: Array, covariance: Array, angle: Array) -> Array:
        c = np.broadcast_to(c, angle.shape + c.shape[-2:])
        value = rotation_fisher_information(c, information_from_covariance(covariance), angle)
        # Straight (no horizontal extent, up to rounding): no information at all.
        straight = np.sqrt(np.sum(c[..., :2] ** 2, axis=(-2, -1))) < STRAIGHT_RADIUS_MM
        return np.where(straight, 0.0, value)

    infos = {
        "crb-tip": info(data.c_true[-1, :1], _frame(cov, -1)[:, 0], phi[:, -1]),
        "crb-body": info(data.c_true[-1], block_diagonal(_frame(cov, -1)), phi[:, -1]),
        "crb-velocity": info(
            data.u_true[None], (_frame(cov, -1)[:, 0] + _frame(cov, -2)[:, 0]) / dt**2, phi[:, -1]
        ),
        "crb-all-frames": np.sum(info(data.c_true, block_diagonal(cov), phi), axis=-1),
    }
    out = {}
    for name, value in infos.items():
        with np.errstate(divide="ignore"):
            std = np.where(value > 0, 1.0 / np.sqrt(np.maximum(value, 1e-300)), np.inf)
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


# ------------------------------------------------------------------------------ execution
def _workers(workers: int | None) -> int:
    return (os.cpu_count() or 1) if workers is None else int(workers)


def _execute(
    function: Callable,
    settings: SensitivitySettings,
    tasks: Sequence,
    workers: int | None,
    scheduler: str | None,
    progress: bool,
    description: str,
) -> list:
    """``[function(settings, task) for task in tasks]`` in task order, run in parallel."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from tqdm import tqdm

    workers = _workers(workers)
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")

    def progress_bar():
        return tqdm(
            total=len(tasks),
            desc=description,
            unit="task",
            disable=not progress,
            file=sys.stderr,
            dynamic_ncols=True,
        )

    if scheduler:
        with progress_bar() as bar:
            return _execute_dask(function, settings, tasks, scheduler, bar)
    if workers == 1 or len(tasks) <= 1:
        results = []
        with progress_bar() as bar:
            for task in tasks:
                results.append(function(settings, task))
                bar.update()
        return results
    with ProcessPoolExecutor(max_workers=min(workers, len(tasks))) as pool:
        # Submit before the bar exists: its monitor thread must not be alive when the pool
        # forks its workers.
        futures = {pool.submit(function, settings, task): i for i, task in enumerate(tasks)}
        results = [None] * len(tasks)
        with progress_bar() as bar:
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
        return results


def _execute_dask(function, settings, tasks, scheduler: str, bar) -> list:
    try:
        from dask.distributed import Client, as_completed
    except ImportError as exc:  # pragma: no cover - dask is a dependency
        raise ValueError("--scheduler needs dask.distributed installed") from exc
    try:
        client = Client(scheduler, set_as_default=False, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"cannot connect to the Dask scheduler at {scheduler}: {exc}") from exc
    try:
        futures = client.map(function, [settings] * len(tasks), tasks, pure=False)
        index = {future.key: i for i, future in enumerate(futures)}
        results = [None] * len(tasks)
        for future in as_completed(futures, loop=client.loop):
            results[index[future.key]] = future.result()
            bar.update()
        return results
    finally:
        client.close()


# ------------------------------------------------------------------------------ statistics
@dataclass(frozen=True)
class SensitivityResult:
    """Every row of every study table, and how the run went."""

    settings: SensitivitySettings
    rows: dict[str, list[dict]]  # study -> rows with the CSV_COLUMNS
    elapsed_s: float
    workers: int
    scheduler: str | None


def summarise(values: Array, kind: str) -> dict[str, float]:
    """Median, quartiles and RMS of |error| in degrees (bounds: of an efficient estimator)."""
    values = np.asarray(values, dtype=float)
    n = values.size
    if kind == "bound":
        rms = float(np.sqrt(np.mean(values**2))) if n else math.nan
        stats = {name: factor * rms for name, factor in ABS_NORMAL_QUANTILES.items()}
        stats["rms"] = rms
        return {
            **{f"{k}_deg": math.degrees(v) for k, v in stats.items()},
            "n": n,
            "valid_fraction": 1.0,
        }
    valid = np.isfinite(values)
    err = np.abs(values[valid])
    if err.size == 0:
        stats = dict.fromkeys(("median", "p25", "p75", "rms"), math.nan)
    else:
        p25, median, p75 = np.percentile(err, [25, 50, 75])
        stats = {"median": median, "p25": p25, "p75": p75, "rms": np.sqrt(np.mean(err**2))}
    return {
        **{f"{k}_deg": math.degrees(float(v)) for k, v in stats.items()},
        "n": int(err.size),
        "valid_fraction": float(valid.mean()) if n else 0.0,
    }


def _row_order(settings: SensitivitySettings) -> list[tuple[str, str]]:
    order = []
    for method in settings.methods:
        if method == BOUND_METHOD:
            order.extend((name, "bound") for name in BOUND_ROWS)
        else:
            order.append((method, "estimator"))
    return order


def tabulate(settings: SensitivitySettings, results: Sequence[TaskResult]) -> dict[str, list]:
    """Rows of every study table from the task results (chunks joined in trial order)."""
    by_point: dict[tuple, list[TaskResult]] = {}
    points: dict[tuple, StudyPoint] = {}
    for result in results:
        by_point.setdefault(result.task.point.key, []).append(result)
        points[result.task.point.key] = result.task.point
    rows: dict[str, list[dict]] = {study: [] for study in settings.studies}
    for key in sorted(by_point):
        chunks = sorted(by_point[key], key=lambda r: r.task.chunk)
        point = points[key]
        for method, kind in _row_order(settings):
            parts = [r.values[method] for r in chunks if method in r.values]
            values = np.concatenate(parts) if parts else np.zeros(0)
            row = {**point.label, "method": method, "kind": kind, **summarise(values, kind)}
            rows[point.study].append(row)
    return rows


def run_sensitivity(
    settings: SensitivitySettings,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> SensitivityResult:
    """Run the selected studies; the tables depend on the settings only.

    Parameters
    ----------
    workers : int, optional
        Local worker processes (default: the number of CPUs; 1 runs in this process).
    scheduler : str, optional
        Address of a Dask scheduler (``tcp://host:8786``) to run the tasks on instead.
    progress : bool
        Show a progress bar on stderr.
    """
    started = time.perf_counter()
    points = study_points(settings)
    tasks = make_tasks(settings, points)
    results = _execute(run_task, settings, tasks, workers, scheduler, progress, "sensitivity")
    rows = tabulate(settings, results)
    used = 0 if scheduler else _workers(workers)
    return SensitivityResult(settings, rows, time.perf_counter() - started, used, scheduler)


# ------------------------------------------------------------------------------ baseline
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


def baseline_agreement(
    settings: SensitivitySettings,
    trials_per_point: int = 2,
    tolerance_rad: float = 1e-3,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> dict[str, float]:
    """How often the paper's least-squares baseline agrees with the closed form.

    Runs the first ``trials_per_point`` trials of every study point (the same frames the
    studies score) through both solvers. Returns, per estimator, the fraction of trials where
    the two estimates differ by less than ``tolerance_rad`` (wrapped); ``"all"`` over every
    solve, ``"bent"`` over the solves away from the straight configuration (where the cost does
    not depend on delta_L, so any angle minimises it), and the number of solves ``"trials"``.
    """
    points = study_points(settings)
    tasks = [Task(p, 0, 0, min(trials_per_point, settings.trials)) for p in points]
    results = _execute(baseline_task, settings, tasks, workers, scheduler, progress, "baseline")
    bent = np.concatenate([np.full(t.stop - t.start, t.point.bending_deg >= 1.0) for t in tasks])
    rates: dict[str, float] = {}
    joined, joined_bent = [], []
    for name in CLOSED_FORM_METHODS:
        diff = np.concatenate([r[name] for r in results])
        agree = np.abs(np.nan_to_num(diff, nan=np.inf)) < tolerance_rad
        rates[name] = float(agree.mean())
        joined.append(agree)
        joined_bent.append(agree[bent])
    rates["all"] = float(np.concatenate(joined).mean())
    rates["bent"] = float(np.concatenate(joined_bent).mean())
    rates["trials"] = float(sum(a.size for a in joined))
    return rates


# ------------------------------------------------------------------------------ outputs
def _format(value) -> str:
    if isinstance(value, float):
        return repr(round(value, 9)) if math.isfinite(value) else str(value)
    return str(value)


def write_tables(result: SensitivityResult, out_dir: Path) -> list[Path]:
    paths = []
    for study, rows in result.rows.items():
        path = out_dir / f"study_{study}.csv"
        with path.open("w", newline="") as f:
            writer = csv.writer(f, lineterminator="\n")
            writer.writerow(CSV_COLUMNS)
            for row in rows:
                writer.writerow([_format(row[c]) for c in CSV_COLUMNS])
        paths.append(path)
    return paths


def read_table(path: Path) -> list[dict]:
    """Rows of a study CSV with numbers parsed (for tests and further analysis)."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    text = {"study", "variant", "method", "kind"}
    return [{k: (v if k in text else float(v)) for k, v in row.items()} for row in rows]


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("cathtrack")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def write_settings(result: SensitivityResult, out_dir: Path) -> Path:
    s = result.settings
    record = {
        "cathtrack_version": _version(),
        "seed": s.seed,
        "settings": s.to_dict(),
        "notes": {
            "units": "noise and deflection in mm, angles in degrees, joint rates in rad/s, mm/s,"
            " mm/s, frame interval in s",
            "ukf_trials": f"the UKF runs on the first {s.effective_ukf_trials} of the {s.trials}"
            " trials of every point; the per-frame estimators and bounds on all of them",
            "bound_rows": "rms_deg is the Cramer-Rao bound on the std of delta_L; median/p25/p75"
            " are those of |error| of an efficient unbiased estimator (0.674, 0.319, 1.150 x)",
            "views": "default_orthographic_rig (noise in mm in the plane) or default_pinhole_rig"
            " (noise in mm at the isocentre, times f / distance = px)",
        },
        "run": {
            "workers": result.workers,
            "scheduler": result.scheduler,
            "elapsed_s": round(result.elapsed_s, 3),
        },
    }
    path = out_dir / "settings.json"
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path


def load_settings(path: Path) -> SensitivitySettings:
    """Settings from a settings.json written by a previous run (or a bare settings dict)."""
    try:
        record = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    values = record.get("settings", record) if isinstance(record, dict) else None
    if not isinstance(values, dict):
        raise ValueError(f"{path}: expected a JSON object of settings")
    return SensitivitySettings.from_dict(values)


def write_outputs(result: SensitivityResult, out_dir: Path | str) -> list[Path]:
    """Write CSV tables, PNG figures, summary.md and settings.json into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = write_tables(result, out_dir)
    paths += write_figures(result, out_dir)
    summary = out_dir / "summary.md"
    summary.write_text(summary_markdown(result))
    paths += [summary, write_settings(result, out_dir)]
    return paths


# ------------------------------------------------------------------------------ findings
@dataclass(frozen=True)
class Finding:
    """One of the paper's qualitative findings, checked on this run's tables."""

    claim: str
    holds: bool | None  # None: the run lacks the methods or studies to check it
    detail: str


def _index(rows: list[dict]) -> dict[tuple, dict]:
    return {
        (
            r["variant"],
            r["delta_2_deg"],
            r["noise_mm"],
            r["theta_L1_deg"],
            r["theta_L2_deg"],
            r["deflection_mm"],
            r["method"],
        ): r
        for r in rows
    }


def _median(rows_index: dict, point: tuple, method: str) -> float:
    row = rows_index.get(point + (method,))
    return math.nan if row is None else float(row["median_deg"])


def _points(rows: list[dict]) -> list[tuple]:
    seen = []
    for r in rows:
        p = (
            r["variant"],
            r["delta_2_deg"],
            r["noise_mm"],
            r["theta_L1_deg"],
            r["theta_L2_deg"],
            r["deflection_mm"],
        )
        if p not in seen:
            seen.append(p)
    return seen


def _bending(point: tuple) -> float:
    """Largest bending angle of a point's configuration, deg."""
    return max(abs(90.0 - point[3]), abs(90.0 - point[4]))


def _tolerance(n_a: float, n_b: float, sigmas: float = 3.0) -> float:
    """Relative difference of two sample medians of |error| that Monte Carlo noise explains.

    The median of |N(0, s^2)| over n samples has a relative standard error of about
    1.17 / sqrt(n); ``sigmas`` of those for the difference of two independent medians.
    """
    return sigmas * 1.17 * math.sqrt(1.0 / max(n_a, 1) + 1.0 / max(n_b, 1))


def _compare(index: dict, pts: list[tuple], better: str, worse: Sequence[str]) -> tuple:
    """Points where ``better`` is not above the best of ``worse`` beyond Monte Carlo noise."""
    ok, ratios = [], []
    for p in pts:
        row = index.get(p + (better,))
        rivals = [index[p + (m,)] for m in worse if p + (m,) in index]
        if row is None or not rivals or not math.isfinite(row["median_deg"]) or row["n"] == 0:
            continue
        rival = min(rivals, key=lambda r: r["median_deg"])
        if rival["median_deg"] <= 0:
            ok.append(row["median_deg"] <= 1e-9)
            continue
        ratio = row["median_deg"] / rival["median_deg"]
        ratios.append(ratio)
        ok.append(ratio <= 1.0 + _tolerance(row["n"], rival["n"], sigmas=4.0))
    mean_ratio = float(np.exp(np.mean(np.log(ratios)))) if ratios else math.nan
    return ok, mean_ratio


def findings(rows: dict[str, list[dict]]) -> list[Finding]:
    """Check the paper's qualitative findings, and the UKF and the bound, on the tables.

    "At least as good" holds when the geometric mean of the ratio of medians over the study
    points is at most 1 and no single point is worse by more than Monte Carlo noise explains
    (four standard errors, see :func:`_tolerance`: with hundreds of points, three would fail by
    chance). The straight configuration, where nothing is observable, is left out.
    """
    out = []
    all_rows = [r for study_rows in rows.values() for r in study_rows]
    methods = {r["method"] for r in all_rows}
    index = _index(all_rows)
    bent = [p for p in _points(all_rows) if _bending(p) >= 1.0]
    exact_rows = rows.get("a", []) + rows.get("b", [])  # no deflection: the model is exact
    exact = [p for p in _points(exact_rows) if _bending(p) >= 1.0]
    position = [m for m in ("tip-position", "body-positions") if m in methods]

    claim = "Body Positions is at least as good as Tip Position"
    if {"tip-position", "body-positions"} <= methods:
        ok, ratio = _compare(index, bent, "body-positions", ["tip-position"])
        out.append(
            Finding(
                claim,
                all(ok) and ratio <= 1.0,
                (
                    f"not worse beyond Monte Carlo noise (4 standard errors) at {sum(ok)} of"
                    f" {len(ok)} bent study points; median error body / tip {ratio:.2f} on average"
                    " (geometric mean)"
                ),
            )
        )
    else:
        out.append(Finding(claim, None, "needs tip-position and body-positions"))

    claim = "Tip Velocity is the most sensitive to noise"
    a_rows = rows.get("a", [])
    if a_rows and "tip-velocity" in methods and position and len(_points(a_rows)) > 1:
        a_index, details, ok = _index(a_rows), [], True
        for delta_2 in sorted({r["delta_2_deg"] for r in a_rows}):
            levels = [p for p in _points(a_rows) if p[1] == delta_2]
            low, high = min(levels, key=lambda p: p[2]), max(levels, key=lambda p: p[2])
            growth = {
                m: _median(a_index, high, m) - _median(a_index, low, m)
                for m in [*position, "tip-velocity"]
            }
            ok &= all(growth["tip-velocity"] > growth[m] for m in position)
            details.append(
                f"delta_2 = {delta_2:g} deg, {low[2]:g} to {high[2]:g} mm: median grows by "
                + ", ".join(f"{g:.1f} deg ({m})" for m, g in growth.items())
            )
        out.append(Finding(claim, ok, "; ".join(details)))
    else:
        out.append(Finding(claim, None, "needs study a, tip-velocity and a position estimator"))

    claim = "Position-based errors grow toward the straight configuration"
    b_rows = rows.get("b", [])
    if b_rows and position and len(_points(b_rows)) > 3:
        b_index, details, ok = _index(b_rows), [], True
        for delta_2 in sorted({r["delta_2_deg"] for r in b_rows}):
            grid = [p for p in _points(b_rows) if p[1] == delta_2]
            bend = np.array([_bending(p) for p in grid])
            for m in position:
                err = np.array([_median(b_index, p, m) for p in grid])
                near = float(err[bend <= np.percentile(bend, 25)].mean())
                far = float(err[bend >= np.percentile(bend, 75)].mean())
                ok &= near > far
                details.append(
                    f"{m}, delta_2 = {delta_2:g} deg: {near:.1f} deg in the straightest quarter"
                    f" of the grid, {far:.1f} deg in the most bent quarter"
                )
        out.append(Finding(claim, ok, "; ".join(details)))
    else:
        out.append(
            Finding(claim, None, "needs study b (4 points or more) and a position estimator")
        )

    claim = "Position-based errors grow with deflection"
    c_rows = rows.get("c", [])
    if c_rows and position:
        c_index, details, ok = _index(c_rows), [], True
        for variant in [v for v in DEFLECTIONS if any(r["variant"] == v for r in c_rows)]:
            for delta_2 in sorted({r["delta_2_deg"] for r in c_rows}):
                levels = [p for p in _points(c_rows) if p[0] == variant and p[1] == delta_2]
                low, high = min(levels, key=lambda p: p[5]), max(levels, key=lambda p: p[5])
                for m in position:
                    before, after = _median(c_index, low, m), _median(c_index, high, m)
                    in_plane_planar = variant == "in-plane" and delta_2 % 180.0 == 0.0
                    if not in_plane_planar:
                        n_low, n_high = c_index[low + (m,)]["n"], c_index[high + (m,)]["n"]
                        ok &= after > before * (1.0 + _tolerance(n_low, n_high))
                    note = " (stays in the bending plane: no error expected)" * in_plane_planar
                    details.append(
                        f"{m}, {variant}, delta_2 = {delta_2:g} deg: {before:.1f} -> {after:.1f}"
                        f" deg from {low[5]:g} to {high[5]:g} mm{note}"
                    )
        out.append(Finding(claim, ok, "; ".join(details)))
    else:
        out.append(Finding(claim, None, "needs study c and a position estimator"))

    claim = "The UKF is at or below the per-frame estimators (model exact)"
    per_frame = [m for m in CLOSED_FORM_METHODS if m in methods]
    if "ukf" in methods and per_frame:
        ok, ratio = _compare(index, exact, "ukf", per_frame)
        out.append(
            Finding(
                claim,
                all(ok) and bool(ok) and ratio <= 1.0,
                (
                    f"not above the best per-frame estimator beyond Monte Carlo noise (4 standard"
                    f" errors) at {sum(ok)} of {len(ok)} bent points of studies a and b; median"
                    f" error UKF /"
                    f" best per-frame {ratio:.2f} on average (geometric mean)"
                ),
            )
        )

    claim = "The per-frame position estimators sit on the bound where the model is exact"
    if "crb-tip" in methods and position and a_rows:
        bound_of = {estimator: bound for bound, estimator in BOUND_ROWS.items()}
        a_index, small, large = _index(a_rows), [], []
        for p in _points(a_rows):
            for m in position:
                row, bound = a_index.get(p + (m,)), a_index.get(p + (bound_of[m],))
                if row and bound and p[2] > 0 and 0 < bound["rms_deg"] < math.inf:
                    ratio = row["rms_deg"] / bound["rms_deg"]
                    (small if bound["rms_deg"] <= LINEAR_REGIME_DEG else large).append(ratio)
        if small:
            n = min(r["n"] for r in a_rows if r["method"] in position)
            tol = 4.0 / math.sqrt(2.0 * n)  # four relative standard errors of an RMS
            detail = (
                f"RMS error / Cramer-Rao bound from {min(small):.2f} to {max(small):.2f} where"
                f" the bound is below {LINEAR_REGIME_DEG:g} deg (Monte Carlo tolerance +/-"
                f" {tol:.2f})"
            )
            if large:
                detail += (
                    f"; {min(large):.2f} to {max(large):.2f} at larger noise, where the"
                    " estimators leave the linear regime the bound describes"
                )
            holds = bool(1 - tol <= min(small) and max(small) <= 1 + tol)
            out.append(Finding(claim, holds, detail))
    return out


def summary_markdown(result: SensitivityResult) -> str:
    """A short markdown summary: what was run, the key numbers and the findings."""
    s = result.settings
    rates = ", ".join(f"{v:g}" for v in s.joint_rates)
    lines = [
        "# Sensitivity studies",
        "",
        f"Seed {s.seed}; {s.trials} trials per point for the per-frame estimators and the bound,"
        f" {s.effective_ukf_trials} for the UKF; {s.view} views; delta_2 = "
        + ", ".join(f"{d:g}" for d in s.delta_2_deg)
        + " deg.",
        f"Each trial: {s.frames_per_trial} frames {s.frame_interval_s:g} s apart, joint rates"
        f" (q_r, q_p, q_d) = ({rates}) (rad/s, mm/s, mm/s), true delta_L "
        + ("uniform on [-180, 180) deg" if s.delta_L_deg is None else f"{s.delta_L_deg:g} deg")
        + ".",
        "Errors are |estimate - truth| of delta_L in degrees: median [25th, 75th percentile].",
        "Bounds: the median |error| of an efficient estimator (0.674 x the Cramer-Rao std);"
        " crb-all-frames uses every frame of a trial (the limit for the UKF).",
        "",
    ]
    for study, rows in result.rows.items():
        lines += [f"## Study {study}: {STUDY_TITLES[study]}", ""]
        lines += _study_table(study, rows, s)
        lines.append("")
    lines += ["## The paper's findings on this run", ""]
    for finding in findings(result.rows):
        mark = {True: "holds", False: "does not hold", None: "not checked"}[finding.holds]
        lines.append(f"- **{finding.claim}**: {mark} ({finding.detail}).")
    lines += ["", f"Run time {result.elapsed_s:.1f} s."]
    return "\n".join(lines) + "\n"


def _cell(row: dict | None) -> str:
    if row is None:
        return ""
    if not math.isfinite(row["median_deg"]):
        return "inf" if row["median_deg"] == math.inf else "-"
    return f"{row['median_deg']:.2f} [{row['p25_deg']:.2f}, {row['p75_deg']:.2f}]"


def _study_table(study: str, rows: list[dict], s: SensitivitySettings) -> list[str]:
    order = [m for m, _ in _row_order(s)]
    index = _index(rows)
    pts = _points(rows)
    if study == "a":
        wanted = [
            p
            for p in pts
            if p[2] in {min(s.noise_levels_mm), max(s.noise_levels_mm)} or math.isclose(p[2], 1.0)
        ]
        label = lambda p: f"delta_2 {p[1]:g}, noise {p[2]:g} mm"  # noqa: E731
    elif study == "b":
        by_d2 = {}
        for p in pts:
            by_d2.setdefault(p[1], []).append(p)
        wanted = []
        for group in by_d2.values():
            wanted.append(min(group, key=_bending))
            wanted.append(max(group, key=_bending))
        label = lambda p: f"delta_2 {p[1]:g}, theta_L = ({p[3]:g}, {p[4]:g})"  # noqa: E731
    else:
        wanted = [
            p for p in pts if p[5] in {min(s.deflection_levels_mm), max(s.deflection_levels_mm)}
        ]
        label = lambda p: f"delta_2 {p[1]:g}, {p[0]} {p[5]:g} mm"  # noqa: E731
    header = "| point | " + " | ".join(order) + " |"
    lines = [header, "|---|" + "---:|" * len(order)]
    for p in wanted:
        lines.append(
            f"| {label(p)} | " + " | ".join(_cell(index.get(p + (m,))) for m in order) + " |"
        )
    if study == "b":
        lines.append("")
        lines.append("(Straightest and most bent grid points; every point is in study_b.csv.)")
    return lines


# ------------------------------------------------------------------------------ figures
METHOD_COLOURS = {
    "tip-position": "tab:blue",
    "body-positions": "tab:orange",
    "tip-velocity": "tab:green",
    "ukf": "tab:red",
    "ukf-position": "tab:purple",
    "tip-position-lsq": "tab:cyan",
    "body-positions-lsq": "tab:brown",
    "tip-velocity-lsq": "tab:olive",
    "crb-all-frames": "tab:red",
}
PLOT_FLOOR_DEG = 1e-2
PLOT_CEILING_DEG = 180.0


def _colour(method: str) -> str:
    return METHOD_COLOURS.get(BOUND_ROWS.get(method, method), "tab:gray")


def _clip(values) -> Array:
    return np.clip(np.asarray(values, dtype=float), PLOT_FLOOR_DEG, PLOT_CEILING_DEG)


def _line_panel(ax, rows: list[dict], x_column: str, order: list[tuple[str, str]]) -> None:
    for method, kind in order:
        mine = sorted((r for r in rows if r["method"] == method), key=lambda r: r[x_column])
        if not mine:
            continue
        x = [r[x_column] for r in mine]
        colour = _colour(method)
        if kind == "bound":
            ax.plot(
                x, _clip([r["median_deg"] for r in mine]), "--", color=colour, lw=1.2, label=method
            )
            continue
        ax.plot(
            x,
            _clip([r["median_deg"] for r in mine]),
            "-o",
            color=colour,
            ms=3,
            lw=1.6,
            label=method,
        )
        ax.fill_between(
            x,
            _clip([r["p25_deg"] for r in mine]),
            _clip([r["p75_deg"] for r in mine]),
            color=colour,
            alpha=0.15,
            lw=0,
        )
        # An estimator that gave no estimate in some trials (the UKF's gate refusing data the
        # model cannot explain): say how often it answered, at the bottom of the panel.
        for r in mine:
            if r["valid_fraction"] < 0.995:
                ax.annotate(
                    f"{100 * r['valid_fraction']:.0f}%",
                    (r[x_column], 1.6 * PLOT_FLOOR_DEG),
                    color=colour,
                    fontsize=6.5,
                    ha="center",
                )
    ax.set_yscale("log")
    ax.set_ylim(PLOT_FLOOR_DEG, 2 * PLOT_CEILING_DEG)
    ax.grid(True, which="major", alpha=0.3)


def _legend(fig, axes) -> None:
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right upper", fontsize=7.5, frameon=False)


def _figure(n_rows: int, n_cols: int, width: float, height: float):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * n_cols, height * n_rows), layout="constrained")
    axes = fig.subplots(n_rows, n_cols, squeeze=False, sharey=True)
    return fig, axes


def _footnote(s: SensitivitySettings, noise: str) -> str:
    return (
        f"{noise}; median |error| with 25-75% band; dashed: Cramer-Rao bound as the median"
        f" |error| of an efficient estimator (clipped at {PLOT_CEILING_DEG:g} deg); n%: share"
        f" of trials with an estimate; {s.trials} trials per point ({s.effective_ukf_trials}"
        f" for the UKF); {s.view} views; seed {s.seed}"
    )


def figure_study_a(result: SensitivityResult):
    s = result.settings
    rows = result.rows["a"]
    order = _row_order(s)
    fig, axes = _figure(1, len(s.delta_2_deg), 4.6, 3.6)
    for ax, delta_2 in zip(axes[0], s.delta_2_deg, strict=True):
        _line_panel(ax, [r for r in rows if r["delta_2_deg"] == delta_2], "noise_mm", order)
        ax.set_title(
            f"delta_2 = {delta_2:g} deg, theta_L = {s.configuration_theta_L_deg[0]:g},"
            f" {s.configuration_theta_L_deg[1]:g} deg",
            fontsize=9,
        )
        ax.set_xlabel("segmentation noise sigma (mm)")
    axes[0, 0].set_ylabel("bending-plane error |delta_L| (deg)")
    _legend(fig, axes)
    fig.suptitle("(a) error against segmentation noise", fontsize=11)
    _add_footnote(fig, _footnote(s, "noise per image axis in both views"))
    return fig


def _add_footnote(fig, text: str) -> None:
    """The small print under a figure: settings, units and what the lines mean."""
    fig.text(0.01, -0.02, text, fontsize=6.5, ha="left", va="top", wrap=True)


def figure_study_c(result: SensitivityResult):
    s = result.settings
    rows = result.rows["c"]
    order = _row_order(s)
    variants = [v for v in DEFLECTIONS if v in s.deflections]
    fig, axes = _figure(len(variants), len(s.delta_2_deg), 4.6, 3.3)
    for i, variant in enumerate(variants):
        for ax, delta_2 in zip(axes[i], s.delta_2_deg, strict=True):
            _line_panel(
                ax,
                [r for r in rows if r["delta_2_deg"] == delta_2 and r["variant"] == variant],
                "deflection_mm",
                order,
            )
            how = "joints offset" if variant == "in-plane" else "normal to the plane"
            ax.set_title(f"{variant} ({how}), delta_2 = {delta_2:g} deg", fontsize=8.5)
            ax.set_xlabel("tip deflection (mm)")
        axes[i, 0].set_ylabel("error |delta_L| (deg)")
    _legend(fig, axes)
    fig.suptitle("(c) error against tip deflection by contact", fontsize=11)
    _add_footnote(
        fig,
        _footnote(
            s,
            f"noise {s.noise_mm:g} mm; in-plane: the catheter bends as if {s.deflection_joint}"
            " were larger than the model sees (the paper's experiment); out-of-plane: the tip is"
            " pushed normal to the bending plane (cantilever profile)",
        ),
    )
    return fig


def figure_study_b(result: SensitivityResult):
    from matplotlib.colors import LogNorm

    s = result.settings
    rows = result.rows["b"]
    panels = [m for m, kind in _row_order(s) if kind == "estimator"]
    panels += [m for m in ("crb-body", "crb-all-frames") if BOUND_METHOD in s.methods]
    fig, axes = _figure(len(s.delta_2_deg), len(panels), 2.5, 2.45)
    norm = LogNorm(vmin=0.1, vmax=PLOT_CEILING_DEG)
    t1, t2 = sorted(set(s.theta_L1_deg)), sorted(set(s.theta_L2_deg))
    image = None
    for i, delta_2 in enumerate(s.delta_2_deg):
        for ax, method in zip(axes[i], panels, strict=True):
            grid = np.full((len(t2), len(t1)), np.nan)
            for r in rows:
                if r["delta_2_deg"] == delta_2 and r["method"] == method:
                    grid[t2.index(r["theta_L2_deg"]), t1.index(r["theta_L1_deg"])] = r["median_deg"]
            image = ax.imshow(
                np.clip(grid, 0.1, PLOT_CEILING_DEG),
                origin="lower",
                norm=norm,
                cmap="viridis",
                extent=_extent(t1, t2),
                aspect="auto",
                interpolation="nearest",
            )
            ax.plot([90], [90], "w+", ms=6)
            ax.set_title(f"{method}\ndelta_2 = {delta_2:g} deg", fontsize=8)
            ax.tick_params(labelsize=7)
            if i == len(s.delta_2_deg) - 1:
                ax.set_xlabel("theta_L1 (deg)", fontsize=8)
        axes[i, 0].set_ylabel("theta_L2 (deg)", fontsize=8)
    if image is not None:
        bar = fig.colorbar(image, ax=axes, shrink=0.8)
        bar.set_label("median |error| (deg); bounds: of an efficient estimator", fontsize=8)
    fig.suptitle(
        f"(b) error over the workspace (+ = straight), noise {s.noise_mm:g} mm, {s.trials} trials"
        f" per point ({s.effective_ukf_trials} for the UKF), {s.view} views, seed {s.seed}",
        fontsize=10,
    )
    return fig


def _extent(x: list[float], y: list[float]) -> list[float]:
    def edges(v: list[float]) -> tuple[float, float]:
        step = (v[-1] - v[0]) / (len(v) - 1) if len(v) > 1 else 1.0
        return v[0] - step / 2, v[-1] + step / 2

    return [*edges(x), *edges(y)]


FIGURES = {"a": figure_study_a, "b": figure_study_b, "c": figure_study_c}


def write_figures(result: SensitivityResult, out_dir: Path, dpi: int = 110) -> list[Path]:
    """One PNG per study (Agg, no display needed)."""
    paths = []
    for study in result.rows:
        path = Path(out_dir) / f"study_{study}.png"
        FIGURES[study](result).savefig(path, dpi=dpi, bbox_inches="tight")
        paths.append(path)
    return paths
