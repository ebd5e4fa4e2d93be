"""What a run of the sensitivity studies is: its settings, study points and tasks.

Each (study, variant, delta_2, level, chunk of ``chunk_trials`` trials) is an independent
:class:`Task` with its own random stream, so the results do not depend on how many workers run
the tasks or in which order.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from models.catheter import Catheter, default_catheter
from models.imaging import default_orthographic_rig, default_pinhole_rig
from replay.simulation.simulator import (
    Scene,
    default_scene,
    in_plane_joint_offset,
    joints_from_tip_angles,
)

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
def scene_for(delta_2_deg: float, view: str) -> Scene:
    """The simulated scene of the default catheter at delta_2 (deg) in the default views."""
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


def row_order(settings: SensitivitySettings) -> list[tuple[str, str]]:
    """The rows of every study point: (method or bound row, "estimator" or "bound")."""
    order = []
    for method in settings.methods:
        if method == BOUND_METHOD:
            order.extend((name, "bound") for name in BOUND_ROWS)
        else:
            order.append((method, "estimator"))
    return order


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
