"""Per-frame bending-plane estimators of the paper and the interface every estimator shares.

Each of the paper's three estimators (docs/design.md section 5) exists two ways:

- ``closed-form``: the exact global minimiser of the covariance-weighted problem
  (models.rotation_fit), with its standard deviation from the Fisher information;
- ``least-squares``: the paper's baseline, scipy's ``least_squares`` on the unweighted
  residuals of the full kinematic model, started at delta_L = 0 as the paper states it.

Every estimator, the UKF included, has ``name``, ``reset()``, ``step(observation) ->
Estimate`` and ``run(observations)`` (:class:`Estimator`); :func:`make_estimator` builds any
of them by name.

The rotation problem of a data kind is built in one place (its model vectors by
:func:`kind_vectors`, its measurements and covariance by :func:`build_problem_batch`'s rule),
from arrays of complete frames (the sensitivity studies: all trials at once) or, by
:func:`build_problem`, from one :class:`Observation`, after dropping what the frame lacks
(the tip or some markers); one frame's model vectors come from the model's points in one
compiled call.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.optimize import least_squares

from models import _fit_kernels as fit_kernels
from models import _shape_kernels as shape_kernels
from models.bounds import information_from_covariance, std_from_information
from models.catheter import Catheter, ShapeVectors
from models.rotation_fit import fit_rotation_z, is_per_vector, rotation_fisher_information
from models.rotations import rotate_z, wrap_angle
from tracker.types import Estimate, Flag, Observation

Array = np.ndarray

DATA_KINDS = ("tip", "body", "velocity")
# Placeholders of a missing tip in the rows of Body Positions (dropped before the fit).
_NAN_3, _EYE_3 = np.full(3, np.nan), np.eye(3)
# Above this standard deviation (rad, ~57 degrees) a frame is reported as uninformative.
UNINFORMATIVE_STD_RAD = 1.0


class Estimator(Protocol):
    """The interface shared by every estimator (per-frame and UKF)."""

    name: str

    def reset(self) -> None:
        """Forget everything learned from earlier frames."""

    def step(self, observation: Observation) -> Estimate:
        """Consume one frame and return the estimate."""

    def run(self, observations: Sequence[Observation]) -> list[Estimate]:
        """Consume frames in order: the estimates of :meth:`step` on each in turn (an
        estimator may do it faster, with the same results; the UKF does)."""
        return [self.step(observation) for observation in observations]


@dataclass(frozen=True)
class Problem:
    """Rotation problems: measured y = Rz(q_r + delta_L) c + noise, batch shape (...).

    One frame has the batch shape ().
    """

    y: Array  # (..., n, 3)
    c: Array  # (..., n, 3)
    # Joint (..., 3n, 3n), or per row (..., n, 3, 3) when the rows are independent
    # (models.rotation_fit.is_per_vector); batch axes broadcast against y's.
    covariance: Array
    q_r_rad: Array | float  # (...)
    partial: bool = False  # some rows of the data kind were not measured


def _check_kind(kind: str) -> None:
    if kind not in DATA_KINDS:
        raise ValueError(f"unknown data kind {kind!r}; expected one of {DATA_KINDS}")


def model_vectors(kind: str, shape: ShapeVectors) -> Array:
    """The model vectors c (..., n, 3) of every row of a data kind.

    Tip Position: the tip; Body Positions: the tip and every backbone marker, in a frame's row
    order ``[tip, marker_0, ...]``; Tip Velocity: the tip velocity (``shape`` made with joint
    rates).
    """
    _check_kind(kind)
    if kind == "body":
        points = np.concatenate([shape.c_tip_mm[..., None, :], shape.c_markers_mm], axis=-2)
    else:
        points = shape.c_tip_mm[..., None, :]
    return kind_vectors(kind, points, shape.u_tip_mm_s)


def kind_vectors(kind: str, points: Array | None, u: Array | None) -> Array:
    """The model vectors c (..., n, 3) of a data kind from the model's points (..., P, 3),
    tip first (as :meth:`~models.catheter.Catheter.points` gives them; Tip Position reads the
    first row only), and the tip velocity u (..., 3) (Tip Velocity)."""
    if kind == "tip":
        return points[..., :1, :]
    if kind == "body":
        return points
    if u is None:
        raise ValueError("Tip Velocity needs shape vectors made with joint rates")
    return u[..., None, :]


def build_problem_batch(
    kind: str,
    shape: ShapeVectors,
    points_b_mm: Array | None = None,
    points_cov_b: Array | None = None,
    velocity_b_mm_s: Array | None = None,
    velocity_cov_b: Array | None = None,
) -> Problem:
    """The rotation problems of one data kind for frames with every point measured.

    Parameters
    ----------
    kind : {"tip", "body", "velocity"}
    shape : ShapeVectors
        Shape vectors at the frames' joint values, batch shape broadcasting against theirs.
    points_b_mm : array, shape (..., P, 3)
        Measured tip and markers in {B}, rows ``[tip, marker_0, ...]`` (Tip Position uses the
        first row only), mm.
    points_cov_b : array, shape (..., P, 3, 3) or (..., 3P, 3P)
        Their covariance per point (independent points) or joint, mm^2.
    velocity_b_mm_s, velocity_cov_b : arrays, shapes (..., 3), (..., 3, 3)
        Measured tip velocity and its covariance (Tip Velocity only), mm/s, mm^2/s^2.
    """
    return _problem(
        kind, model_vectors(kind, shape), shape.q_r_rad, points_b_mm, points_cov_b,
        velocity_b_mm_s, velocity_cov_b,
    )  # fmt: skip


def _problem(kind, c, q_r_rad, points_b_mm, points_cov_b, velocity_b_mm_s, velocity_cov_b):
    """The rotation problems of a data kind with its model vectors c (see
    :func:`build_problem_batch`)."""
    if kind == "velocity":
        y = np.asarray(velocity_b_mm_s, dtype=float)[..., None, :]
        covariance = np.asarray(velocity_cov_b, dtype=float)
    else:
        y = np.asarray(points_b_mm, dtype=float)
        covariance = np.asarray(points_cov_b, dtype=float)
        if kind == "tip":
            per_point = covariance.ndim > 2 and covariance.shape[-3:] == (y.shape[-2], 3, 3)
            y = y[..., :1, :]
            covariance = covariance[..., 0, :, :] if per_point else covariance[..., :3, :3]
    if c.shape != y.shape:
        c = np.broadcast_to(c, np.broadcast_shapes(c.shape, y.shape))
    return Problem(y=y, c=c, covariance=covariance, q_r_rad=q_r_rad)


def build_problem(kind: str, observation: Observation, catheter: Catheter) -> Problem | None:
    """The rotation problem of one frame, or None if the frame has nothing usable for it.

    Body Positions uses whichever rows of ``[tip, marker_0, ...]`` were measured and says so
    with ``partial``; Tip Velocity needs the velocity and the joint rates.
    """
    _check_kind(kind)
    if kind == "tip":
        if not observation.has_tip():
            return None
        # The model's points [tip, markers...] in one compiled call, not the shape vectors.
        q = np.asarray(observation.q, dtype=float)
        c = kind_vectors(kind, catheter.points(q), None)
        tip = np.asarray(observation.tip_b_mm, dtype=float)[None]
        return _problem(kind, c, q[0], tip, observation.tip_cov_b, None, None)
    if kind == "velocity":
        if not observation.has_velocity():
            return None
        return build_problem_batch(
            kind,
            catheter.shape_vectors(observation.q, observation.q_dot),
            velocity_b_mm_s=observation.velocity_b_mm_s,
            velocity_cov_b=observation.velocity_cov_b,
        )
    n_markers = len(catheter.marker_arclengths_mm)
    mask = observation.marker_mask()
    if mask.size and mask.size != n_markers:
        raise ValueError(f"observation has {mask.size} markers, the catheter model has {n_markers}")
    has_tip, present = observation.has_tip(), mask.tolist()
    if not has_tip and not any(present):
        return None
    # Every row [tip, marker_0, ...], with placeholders (NaN, identity) for what is missing.
    if mask.size:
        markers = np.asarray(observation.markers_b_mm, dtype=float)
        markers_cov = np.asarray(observation.markers_cov_b, dtype=float)
    else:
        mask = np.zeros(n_markers, dtype=bool)
        markers = np.full((n_markers, 3), np.nan)
        markers_cov = np.broadcast_to(np.eye(3), (n_markers, 3, 3))
    tip, tip_cov = (observation.tip_b_mm, observation.tip_cov_b) if has_tip else (_NAN_3, _EYE_3)
    points = np.empty((1 + n_markers, 3))
    points[0], points[1:] = tip, markers
    if markers_cov.shape == (n_markers, 3, 3):
        covariance = np.empty((1 + n_markers, 3, 3))
        covariance[0], covariance[1:] = tip_cov, markers_cov
    else:
        covariance = np.zeros((3 + 3 * n_markers,) * 2)
        covariance[:3, :3] = tip_cov
        covariance[3:, 3:] = observation.markers_joint_covariance()
    # The model's points [tip, markers...] in one compiled call, not the shape vectors.
    q = np.asarray(observation.q, dtype=float)
    c = kind_vectors(kind, catheter.points(q), None)
    problem = _problem(kind, c, q[0], points, covariance, None, None)
    if not (has_tip and present and all(present)):
        rows = np.concatenate(([has_tip], mask))
        if covariance.ndim == 3:
            # One row left: its own covariance is the joint one (see is_per_vector).
            covariance = covariance[rows] if rows.sum() > 1 else covariance[rows][0]
        else:
            values = np.repeat(rows, 3)
            covariance = covariance[np.ix_(values, values)]
        problem = Problem(problem.y[rows], problem.c[rows], covariance, problem.q_r_rad, True)
    if not all(map(math.isfinite, problem.covariance.ravel().tolist())):
        return None
    return problem


def closed_form_batch(problem: Problem) -> tuple[Array, Array]:
    """Closed-form delta_L and its Fisher standard deviation for a batch of problems.

    Returns
    -------
    delta_L_rad, std_rad : arrays, shape (...)
        ``std_rad`` is inf where the data carry no information on the angle.
    """
    W = information_from_covariance(problem.covariance)
    if is_per_vector(W, problem.c.shape[-2]):
        W = np.broadcast_to(W, problem.c.shape + (3,))
    else:
        W = np.broadcast_to(W, problem.c.shape[:-2] + W.shape[-2:])
    fit = fit_rotation_z(problem.y, problem.c, W)
    return wrap_angle(fit.phi_rad - problem.q_r_rad), std_from_information(fit.fisher_information)


def _invalid(observation: Observation, flags: Flag) -> Estimate:
    return Estimate(
        time_s=observation.time_s,
        delta_L_rad=float("nan"),
        std_rad=float("nan"),
        q_r_rad=float(observation.q[0]),
        flags=flags | Flag.NO_MEASUREMENT,
    )


class PerFrameEstimator(Estimator):
    """One of the paper's per-frame estimators, solved in closed form or by least squares.

    Parameters
    ----------
    catheter : Catheter
    kind : {"tip", "body", "velocity"}
        Tip Position, Body Positions or Tip Velocity.
    solver : {"closed-form", "least-squares"}
    """

    NAMES = {"tip": "tip-position", "body": "body-positions", "velocity": "tip-velocity"}

    def __init__(self, catheter: Catheter, kind: str, solver: str = "closed-form") -> None:
        # The model's points and the fit are compiled: loaded (or compiled) now, not in a frame.
        shape_kernels.warm_up()
        fit_kernels.warm_up()
        _check_kind(kind)
        if solver not in ("closed-form", "least-squares"):
            raise ValueError(f"unknown solver {solver!r}; use 'closed-form' or 'least-squares'")
        self.catheter = catheter
        self.kind = kind
        self.solver = solver
        self.name = self.NAMES[kind] + ("-lsq" if solver == "least-squares" else "")

    def reset(self) -> None:
        """Per-frame estimators keep no state."""

    def step(self, observation: Observation) -> Estimate:
        problem = build_problem(self.kind, observation, self.catheter)
        if problem is None:
            return _invalid(observation, Flag.NONE)
        flags = Flag.PARTIAL if problem.partial else Flag.NONE
        W = information_from_covariance(problem.covariance)
        if self.solver == "closed-form":
            fit = fit_rotation_z(problem.y, problem.c, W)
            phi, info = float(fit.phi_rad), float(fit.fisher_information)
            radius = float(fit.informative_radius_mm)
        else:
            phi, converged = self._least_squares(observation, problem)
            if not converged:
                flags |= Flag.NOT_CONVERGED
            info = float(rotation_fisher_information(problem.c, W, phi))
            radius = float(np.sqrt(np.sum(problem.c[:, :2] ** 2)))
        std = std_from_information(info)
        if not std < UNINFORMATIVE_STD_RAD:
            flags |= Flag.UNINFORMATIVE
        return Estimate(
            time_s=observation.time_s,
            delta_L_rad=wrap_angle(phi - problem.q_r_rad),
            std_rad=std,
            q_r_rad=float(problem.q_r_rad),
            flags=flags,
            informative_radius_mm=radius,
        )

    def _least_squares(self, observation: Observation, problem: Problem) -> tuple[float, bool]:
        """The paper's problem: unweighted residuals of the full model, delta_L_0 = 0."""
        residual = self._residual_function(observation, problem)
        result = least_squares(residual, x0=np.zeros(1))
        return float(result.x[0]) + float(problem.q_r_rad), bool(result.status > 0)

    def _residual_function(self, observation: Observation, problem: Problem) -> Callable:
        cat, q = self.catheter, np.asarray(observation.q, dtype=float)
        y = problem.y
        if self.kind == "tip":
            return lambda d: y[0] - cat.tip(q, d[0])
        if self.kind == "body":
            mask = observation.marker_mask()
            s = np.asarray(cat.marker_arclengths_mm)[mask]
            if observation.has_tip():
                s = np.concatenate([[cat.length_mm], s])
            return lambda d: (y - cat.backbone(q, d[0], s)).ravel()
        q_dot = np.asarray(observation.q_dot, dtype=float)
        return lambda d: y[0] - cat.tip_twist(q, q_dot, d[0])[:3]


def predicted_measurement(c: Array, q_r_rad: Array, delta_L_rad: Array) -> Array:
    """Rz(q_r + delta_L) c for vectors c (..., 3)."""
    return rotate_z(c, np.asarray(q_r_rad) + np.asarray(delta_L_rad))
