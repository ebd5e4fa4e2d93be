"""Per-frame bending-plane estimators of the paper and the interface every estimator shares.

Each of the paper's three estimators (DESIGN.md section 5) exists two ways:

- ``closed-form``: the exact global minimiser of the covariance-weighted problem
  (models.rotation_fit), with its standard deviation from the Fisher information;
- ``least-squares``: the paper's baseline, scipy's ``least_squares`` on the unweighted
  residuals of the full kinematic model, started at delta_L = 0 as the paper states it.

Every estimator, the UKF included, has ``name``, ``reset()`` and ``step(observation) ->
Estimate``; :func:`make_estimator` builds any of them by name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.linalg import block_diag
from scipy.optimize import least_squares

from models.bounds import information_from_covariance
from models.catheter import Catheter, ShapeVectors
from models.rotation_fit import fit_rotation_z, rotation_fisher_information
from models.rotations import rotate_z, wrap_angle
from tracker.types import Estimate, Flag, Observation

Array = np.ndarray

DATA_KINDS = ("tip", "body", "velocity")
# Above this standard deviation (rad, ~57 degrees) a frame is reported as uninformative.
UNINFORMATIVE_STD_RAD = 1.0


class Estimator(Protocol):
    """The interface shared by every estimator (per-frame and UKF)."""

    name: str

    def reset(self) -> None:
        """Forget everything learned from earlier frames."""

    def step(self, observation: Observation) -> Estimate:
        """Consume one frame and return the estimate."""


@dataclass(frozen=True)
class Problem:
    """One frame's rotation problem: measured y = Rz(q_r + delta_L) c + noise."""

    y: Array  # (n, 3)
    c: Array  # (n, 3)
    covariance: Array  # (3n, 3n)
    q_r_rad: float
    partial: bool


def build_problem(
    kind: str, observation: Observation, shape: ShapeVectors
) -> Problem | None:
    """Collect the measured and model vectors of one data kind, or None if nothing usable."""
    if kind == "tip":
        if not observation.has_tip():
            return None
        y = np.asarray(observation.tip_b_mm, dtype=float)[None, :]
        c = shape.c_tip_mm[None, :]
        cov = np.asarray(observation.tip_cov_b, dtype=float)
        partial = False
    elif kind == "body":
        # Body Positions: the tip and every segmented backbone marker.
        mask = observation.marker_mask()
        n_markers = shape.c_markers_mm.shape[0]
        if mask.size and mask.size != n_markers:
            raise ValueError(
                f"observation has {mask.size} markers, the catheter model has {n_markers}"
            )
        has_tip = observation.has_tip()
        if not mask.any() and not has_tip:
            return None
        ys, cs, blocks = [], [], []
        if has_tip:
            ys.append(np.asarray(observation.tip_b_mm, dtype=float)[None, :])
            cs.append(shape.c_tip_mm[None, :])
            blocks.append(np.asarray(observation.tip_cov_b, dtype=float))
        if mask.any():
            idx = np.repeat(mask, 3)
            ys.append(np.asarray(observation.markers_b_mm, dtype=float)[mask])
            cs.append(shape.c_markers_mm[mask])
            blocks.append(observation.markers_joint_covariance()[np.ix_(idx, idx)])
        y, c = np.concatenate(ys), np.concatenate(cs)
        cov = block_diag(*blocks)
        if not np.all(np.isfinite(cov)):
            return None
        partial = not (has_tip and mask.size and mask.all())
    elif kind == "velocity":
        if not observation.has_velocity() or shape.u_tip_mm_s is None:
            return None
        y = np.asarray(observation.velocity_b_mm_s, dtype=float)[None, :]
        c = shape.u_tip_mm_s[None, :]
        cov = np.asarray(observation.velocity_cov_b, dtype=float)
        partial = False
    else:
        raise ValueError(f"unknown data kind {kind!r}; expected one of {DATA_KINDS}")
    return Problem(y=y, c=c, covariance=cov, q_r_rad=float(shape.q_r_rad), partial=partial)


def _invalid(observation: Observation, flags: Flag) -> Estimate:
    return Estimate(
        time_s=observation.time_s,
        delta_L_rad=float("nan"),
        std_rad=float("nan"),
        q_r_rad=float(observation.q[0]),
        flags=flags | Flag.NO_MEASUREMENT,
    )


def _std_flags(std: float) -> Flag:
    return Flag.UNINFORMATIVE if not std < UNINFORMATIVE_STD_RAD else Flag.NONE


class PerFrameEstimator:
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
        if kind not in DATA_KINDS:
            raise ValueError(f"unknown data kind {kind!r}; expected one of {DATA_KINDS}")
        if solver not in ("closed-form", "least-squares"):
            raise ValueError(f"unknown solver {solver!r}; use 'closed-form' or 'least-squares'")
        self.catheter = catheter
        self.kind = kind
        self.solver = solver
        self.name = self.NAMES[kind] + ("-lsq" if solver == "least-squares" else "")

    def reset(self) -> None:
        """Per-frame estimators keep no state."""

    def step(self, observation: Observation) -> Estimate:
        use_rates = self.kind == "velocity" and observation.has_velocity()
        q_dot = observation.q_dot if use_rates else None
        shape = self.catheter.shape_vectors(observation.q, q_dot)
        problem = build_problem(self.kind, observation, shape)
        if problem is None:
            return _invalid(observation, Flag.NONE)
        W = information_from_covariance(problem.covariance)
        flags = Flag.PARTIAL if problem.partial else Flag.NONE
        if self.solver == "closed-form":
            fit = fit_rotation_z(problem.y, problem.c, W)
            phi = float(fit.phi_rad)
            info = float(fit.fisher_information)
        else:
            phi, converged = self._least_squares(observation, problem)
            flags |= Flag.NONE if converged else Flag.NOT_CONVERGED
            info = float(rotation_fisher_information(problem.c, W, phi))
        std = 1.0 / np.sqrt(info) if info > 0 else float("inf")
        radius = float(np.sqrt(np.sum(problem.c[:, :2] ** 2)))
        return Estimate(
            time_s=observation.time_s,
            delta_L_rad=wrap_angle(phi - problem.q_r_rad),
            std_rad=float(std),
            q_r_rad=problem.q_r_rad,
            flags=flags | _std_flags(std),
            informative_radius_mm=radius,
        )

    def _least_squares(self, observation: Observation, problem: Problem) -> tuple[float, bool]:
        """The paper's problem: unweighted residuals of the full model, delta_L_0 = 0."""
        residual = self._residual_function(observation, problem)
        result = least_squares(residual, x0=np.zeros(1))
        return float(result.x[0]) + problem.q_r_rad, bool(result.status > 0)

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


def closed_form_batch(
    c: Array, y: Array, covariance: Array, q_r_rad: Array
) -> tuple[Array, Array]:
    """Closed-form delta_L and its Fisher standard deviation for a batch of frames.

    Parameters
    ----------
    c, y : array, shape (B, n, 3)
        Model and measured vectors in {B}.
    covariance : array, shape (B, 3n, 3n) or (3n, 3n)
    q_r_rad : array, shape (B,)
    """
    W = information_from_covariance(covariance)
    W = np.broadcast_to(W, c.shape[:-2] + W.shape[-2:])
    fit = fit_rotation_z(y, c, W)
    with np.errstate(divide="ignore"):
        std = np.where(fit.fisher_information > 0, 1 / np.sqrt(fit.fisher_information), np.inf)
    return wrap_angle(fit.phi_rad - q_r_rad), std


def predicted_measurement(c: Array, q_r_rad: Array, delta_L_rad: Array) -> Array:
    """Rz(q_r + delta_L) c for vectors c (..., 3)."""
    return rotate_z(c, np.asarray(q_r_rad) + np.asarray(delta_L_rad))






