"""Fitting both segments of a catheter model to measured shapes (docs/design.md section 3).

The per-segment fits are those of :mod:`models.calibration`; this module brings measured
whole-catheter shapes into each segment's bending plane, chains the two fits, scores a model
against shapes and cross-validates the fit over held-out configurations.

Two kinds of measurement:

- :class:`PointShapes`: backbone points in the base frame {B} at the same arclengths in every
  shape. The convention of the registration (models/registration.py) holds: the shapes are
  taken with ``delta_L = 0``, so the proximal bending plane is at ``q_r`` about ``z_b``. The
  proximal points, turned back by ``q_r``, are in-plane (x, z) points of the proximal segment;
  the distal points are taken into frame {2} of the fitted proximal segment and turned back
  by the model's ``delta_2``. Both matrices are then refined together on every point in {B}:
  the distal points are the most sensitive measurement of the proximal tip angle (a lever of
  L2), which the per-segment fit of the proximal points alone leaves several times less
  accurate.
- :class:`AngleShapes`: tangent angles of each segment at known arclengths from the segment's
  base, in the segment's own plane (straight: pi/2), as :mod:`models.calibration` defines them.

Pure maths: arrays in, catheters and residuals out.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from models.calibration import (
    CalibrationResult,
    fit_modal_matrix_from_angles,
    fit_modal_matrix_from_points,
)
from models.catheter import Catheter, check_joints
from models.modal import ModalSegment, PowerBasis
from models.rotations import rotate_z

Array = np.ndarray

SEGMENTS = ("proximal", "distal")
JOINT_NAMES = ("q_p", "q_d")
"""The joint that drives each segment."""


@dataclass(frozen=True, eq=False)
class PointShapes:
    """Measured backbone points of ``n`` shapes at ``n_s`` common arclengths.

    Parameters
    ----------
    q : array, shape (n, 3)
        Joint values (q_r [rad], q_p [mm], q_d [mm]); q_r is the bending plane (delta_L = 0).
    arclength_mm : array, shape (n_s,)
        Strictly increasing arclengths of the points from the base of the proximal segment,
        mm, in (0, L1 + L2].
    points_b_mm : array, shape (n, n_s, 3)
        Backbone points in {B}, mm.
    """

    q: Array
    arclength_mm: Array
    points_b_mm: Array

    def __post_init__(self) -> None:
        q = check_joints(self.q)
        s = np.asarray(self.arclength_mm, dtype=float)
        p = np.asarray(self.points_b_mm, dtype=float)
        if q.ndim != 2:
            raise ValueError(f"q must have shape (n, 3), got {q.shape}")
        if s.ndim != 1 or s.size == 0 or np.any(s <= 0.0) or np.any(np.diff(s) <= 0.0):
            raise ValueError("arclengths must be strictly increasing and > 0 mm")
        if p.shape != (q.shape[0], s.size, 3):
            raise ValueError(f"points must have shape ({q.shape[0]}, {s.size}, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points contain non-finite values (NaN or inf)")
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "arclength_mm", s)
        object.__setattr__(self, "points_b_mm", p)

    @property
    def n_shapes(self) -> int:
        return self.q.shape[0]

    def subset(self, index: Array) -> PointShapes:
        return PointShapes(self.q[index], self.arclength_mm, self.points_b_mm[index])

    def samples(self, length_1_mm: float) -> tuple[int, int]:
        """Number of arclengths on the proximal (s <= L1) and on the distal segment."""
        n_1 = int(np.count_nonzero(self.arclength_mm <= length_1_mm))
        return n_1, self.arclength_mm.size - n_1


@dataclass(frozen=True, eq=False)
class AngleShapes:
    """Measured tangent angles of ``n`` shapes, per segment at common arclengths.

    Parameters
    ----------
    q : array, shape (n, 3)
        Joint values (q_r [rad], q_p [mm], q_d [mm]); q_r is not used.
    arclength_mm : tuple of two arrays, shapes (n_1,), (n_2,)
        Arclengths from each segment's own base, mm.
    theta_rad : tuple of two arrays, shapes (n, n_1), (n, n_2)
        Tangent angles of each segment in its own plane, rad (straight: pi/2).
    """

    q: Array
    arclength_mm: tuple[Array, Array]
    theta_rad: tuple[Array, Array]

    def __post_init__(self) -> None:
        q = check_joints(self.q)
        if q.ndim != 2:
            raise ValueError(f"q must have shape (n, 3), got {q.shape}")
        s = tuple(np.asarray(x, dtype=float) for x in self.arclength_mm)
        theta = tuple(np.asarray(x, dtype=float) for x in self.theta_rad)
        for name, s_i, theta_i in zip(SEGMENTS, s, theta, strict=True):
            if theta_i.shape != (q.shape[0], s_i.size):
                raise ValueError(
                    f"{name} angles must have shape ({q.shape[0]}, {s_i.size}), got {theta_i.shape}"
                )
            if not np.all(np.isfinite(theta_i)) or not np.all(np.isfinite(s_i)):
                raise ValueError(f"{name} angles contain non-finite values (NaN or inf)")
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "arclength_mm", s)
        object.__setattr__(self, "theta_rad", theta)

    @property
    def n_shapes(self) -> int:
        return self.q.shape[0]

    def subset(self, index: Array) -> AngleShapes:
        theta = tuple(t[index] for t in self.theta_rad)
        return AngleShapes(self.q[index], self.arclength_mm, theta)

    def samples(self, length_1_mm: float) -> tuple[int, int]:
        return self.arclength_mm[0].size, self.arclength_mm[1].size


Shapes = PointShapes | AngleShapes


@dataclass(frozen=True, eq=False)
class ShapeFit:
    """The fitted catheter and the per-segment calibration results.

    For point shapes ``proximal`` and ``distal`` are the per-segment fits that start the joint
    refinement, whose result is ``catheter``.
    """

    catheter: Catheter
    proximal: CalibrationResult
    distal: CalibrationResult


@dataclass(frozen=True)
class ShapeResiduals:
    """RMS residuals of a model against shapes, per segment and overall.

    ``mm`` is the RMS distance of measured from model points (point shapes; None for angles);
    ``deg`` the RMS tangent-direction error: the angle between measured and model chords of
    consecutive points (point shapes) or the tangent-angle error (angle shapes). Each a dict
    with keys ``proximal``, ``distal``, ``overall`` (NaN where a segment has no samples).
    """

    mm: dict[str, float] | None
    deg: dict[str, float]
    n_shapes: int

    @classmethod
    def from_squares(cls, squares: dict[str, dict[str, Array]], n_shapes: int) -> ShapeResiduals:
        """From squared errors ``{"mm" | "deg": {segment: array}}``."""

        def rms(values: list[Array]) -> float:
            values = np.concatenate([np.ravel(v) for v in values]) if values else np.zeros(0)
            return float(np.sqrt(np.mean(values))) if values.size else float("nan")

        out = {}
        for unit, per_segment in squares.items():
            out[unit] = {name: rms([per_segment[name]]) for name in SEGMENTS}
            out[unit]["overall"] = rms([per_segment[name] for name in SEGMENTS])
        return cls(mm=out.get("mm"), deg=out["deg"], n_shapes=n_shapes)


# ------------------------------------------------------------------------------ checks
def _bases(sizes: tuple[int, int], name: str) -> tuple[PowerBasis, PowerBasis]:
    sizes = tuple(sizes)
    if len(sizes) != 2 or any(int(n) != n or n < 1 for n in sizes):
        raise ValueError(f"{name} basis sizes must be two positive integers, got {sizes}")
    return PowerBasis(int(sizes[0])), PowerBasis(int(sizes[1]))


def check_determined(
    shapes: Shapes,
    template: Catheter,
    psi_sizes: tuple[int, int],
    eta_sizes: tuple[int, int],
    what: str = "",
) -> None:
    """A ValueError (one line) unless the shapes can determine both modal matrices.

    Each segment needs at least ``eta`` distinct values of its joint and at least ``psi``
    distinct arclengths (the ranks of the two factors of the least-squares problem,
    models/calibration.py). ``what`` starts the message (e.g. which fold).
    """
    _bases(psi_sizes, "psi")
    _bases(eta_sizes, "eta")
    counts = shapes.samples(template.proximal.length_mm)
    for k, name in enumerate(SEGMENTS):
        joint = JOINT_NAMES[k]
        distinct = np.unique(shapes.q[:, 1 + k]).size
        if distinct < eta_sizes[k]:
            raise ValueError(
                f"{what}{shapes.n_shapes} configurations with {distinct} distinct {joint}"
                f" value(s) cannot determine the {name} joint basis of size {eta_sizes[k]};"
                f" measure at least {eta_sizes[k]} distinct {joint} values or use a smaller"
                " joint basis"
            )
        if counts[k] < psi_sizes[k]:
            raise ValueError(
                f"{what}{counts[k]} arclength(s) on the {name} segment cannot determine its"
                f" arclength basis of size {psi_sizes[k]}; measure at least {psi_sizes[k]}"
                " points along it or use a smaller arclength basis"
            )


# ------------------------------------------------------------------------------ fitting
def _segment(template: ModalSegment, result: CalibrationResult) -> ModalSegment:
    return ModalSegment(template.length_mm, result.A, result.psi, result.eta)


def _fit_points(
    shapes: PointShapes, template: Catheter, psi: tuple, eta: tuple
) -> tuple[CalibrationResult, CalibrationResult, Catheter]:
    L1 = template.proximal.length_mm
    s = shapes.arclength_mm
    on_1 = s <= L1
    # Proximal: turn each shape back by its bending plane q_r (delta_L = 0) into the x-z plane.
    in_plane_1 = rotate_z(shapes.points_b_mm[:, on_1], -shapes.q[:, :1])
    proximal = fit_modal_matrix_from_points(
        s[on_1], shapes.q[:, 1], in_plane_1[..., [0, 2]], L1, psi[0], eta[0]
    )
    with_proximal = replace(template, proximal=_segment(template.proximal, proximal))
    # Distal: into frame {2} of the fitted proximal segment, then back by delta_2 about z_2.
    frames = with_proximal.frames(shapes.q)
    relative = shapes.points_b_mm[:, ~on_1] - frames.o_2_b[:, None, :]
    in_2 = np.einsum("jba,jkb->jka", frames.R_b_2, relative)
    in_plane_2 = rotate_z(in_2, -template.delta_2_rad)
    distal = fit_modal_matrix_from_points(
        s[~on_1] - L1,
        shapes.q[:, 2],
        in_plane_2[..., [0, 2]],
        template.distal.length_mm,
        psi[1],
        eta[1],
    )
    catheter = replace(with_proximal, distal=_segment(template.distal, distal))
    return proximal, distal, catheter


def _with_matrices(catheter: Catheter, x: Array) -> Catheter:
    """The catheter with both modal matrices taken from ``x = [A_1.ravel(), A_2.ravel()]``."""
    p, d = catheter.proximal, catheter.distal
    return replace(
        catheter,
        proximal=ModalSegment(p.length_mm, x[: p.A.size].reshape(p.A.shape), p.psi, p.eta),
        distal=ModalSegment(d.length_mm, x[p.A.size :].reshape(d.A.shape), d.psi, d.eta),
    )


def _refine_points(catheter: Catheter, shapes: PointShapes) -> Catheter:
    """Both matrices refined together by least squares on every point in {B}.

    Started at the per-segment fits, Levenberg-Marquardt converges in a few iterations; the
    Jacobian is by finite differences (a few dozen parameters, each evaluation one batched
    backbone call).
    """

    def residuals(x: Array) -> Array:
        model = model_points(_with_matrices(catheter, x), shapes)
        return (model - shapes.points_b_mm).ravel()

    start = np.concatenate([catheter.proximal.A.ravel(), catheter.distal.A.ravel()])
    solution = least_squares(residuals, start, method="lm", x_scale="jac")
    if not solution.success:
        raise ValueError(f"the joint fit of both segments did not converge: {solution.message}")
    return _with_matrices(catheter, solution.x)


def fit_shapes(
    shapes: Shapes,
    template: Catheter,
    psi_sizes: tuple[int, int] = (3, 3),
    eta_sizes: tuple[int, int] = (3, 3),
) -> ShapeFit:
    """Fit the modal matrices of both segments (power bases of the given sizes).

    Parameters
    ----------
    shapes : PointShapes or AngleShapes
    template : Catheter
        Gives the segment lengths, ``delta_2``, the markers and the quadrature order of the
        fitted catheter; its modal matrices are not used.
    psi_sizes, eta_sizes : (int, int)
        Sizes of the arclength and joint bases of the proximal and the distal segment.

    Raises
    ------
    ValueError
        One line, if the shapes cannot determine the matrices (:func:`check_determined`) or
        a fit fails.
    """
    check_determined(shapes, template, psi_sizes, eta_sizes)
    psi = _bases(psi_sizes, "psi")
    eta = _bases(eta_sizes, "eta")
    if isinstance(shapes, PointShapes):
        proximal, distal, catheter = _fit_points(shapes, template, psi, eta)
        return ShapeFit(_refine_points(catheter, shapes), proximal, distal)
    results = []
    for k, segment in enumerate((template.proximal, template.distal)):
        results.append(
            fit_modal_matrix_from_angles(
                shapes.arclength_mm[k],
                shapes.q[:, 1 + k],
                shapes.theta_rad[k],
                segment.length_mm,
                psi[k],
                eta[k],
            )
        )
    catheter = replace(
        template,
        proximal=_segment(template.proximal, results[0]),
        distal=_segment(template.distal, results[1]),
    )
    return ShapeFit(catheter, results[0], results[1])


# ------------------------------------------------------------------------------ scoring
def model_points(catheter: Catheter, shapes: PointShapes) -> Array:
    """The model's points of the shapes' configurations, in {B}, shape (n, n_s, 3)."""
    return catheter.backbone(shapes.q, 0.0, shapes.arclength_mm)


def _chords(points: Array) -> Array:
    """Vectors between consecutive points, the first from the base origin, (..., n_s, 3)."""
    start = np.zeros(points.shape[:-2] + (1, 3))
    return np.diff(np.concatenate([start, points], axis=-2), axis=-2)


def _squared_errors(catheter: Catheter, shapes: Shapes) -> dict[str, dict[str, Array]]:
    if isinstance(shapes, AngleShapes):
        squares = {}
        for k, (name, segment) in enumerate(
            zip(SEGMENTS, (catheter.proximal, catheter.distal), strict=True)
        ):
            model = segment.theta(shapes.arclength_mm[k][None, :], shapes.q[:, 1 + k, None])
            squares[name] = np.degrees(shapes.theta_rad[k] - model) ** 2
        return {"deg": squares}
    model = model_points(catheter, shapes)
    distance2 = np.sum((shapes.points_b_mm - model) ** 2, axis=-1)
    measured, fitted = _chords(shapes.points_b_mm), _chords(model)
    cross = np.linalg.norm(np.cross(measured, fitted), axis=-1)
    angle = np.arctan2(cross, np.sum(measured * fitted, axis=-1))
    s = shapes.arclength_mm
    midpoints = 0.5 * (s + np.concatenate([[0.0], s[:-1]]))
    L1 = catheter.proximal.length_mm
    on_1, chord_on_1 = s <= L1, midpoints <= L1
    return {
        "mm": {"proximal": distance2[:, on_1], "distal": distance2[:, ~on_1]},
        "deg": {
            "proximal": np.degrees(angle[:, chord_on_1]) ** 2,
            "distal": np.degrees(angle[:, ~chord_on_1]) ** 2,
        },
    }


def shape_residuals(catheter: Catheter, shapes: Shapes) -> ShapeResiduals:
    """RMS residuals of ``catheter`` against the shapes (see :class:`ShapeResiduals`)."""
    return ShapeResiduals.from_squares(_squared_errors(catheter, shapes), shapes.n_shapes)


def fold_indices(n_shapes: int, folds: int, seed: int = 0) -> list[Array]:
    """Held-out shape indices of each of ``folds`` folds of a seeded shuffle."""
    if int(folds) != folds or not 2 <= folds <= n_shapes:
        raise ValueError(
            f"cross-validation needs 2 to {n_shapes} folds (one per configuration at most),"
            f" got {folds}"
        )
    order = np.random.default_rng(seed).permutation(n_shapes)
    return [np.sort(part) for part in np.array_split(order, int(folds))]


def cross_validate(
    shapes: Shapes,
    template: Catheter,
    psi_sizes: tuple[int, int] = (3, 3),
    eta_sizes: tuple[int, int] = (3, 3),
    folds: int = 5,
    seed: int = 0,
) -> ShapeResiduals:
    """k-fold cross-validated residuals: each fold's shapes scored by a fit to the others.

    Raises
    ------
    ValueError
        One line naming the fold whose training shapes cannot determine the matrices.
    """
    held_out = fold_indices(shapes.n_shapes, folds, seed)
    squares: dict[str, dict[str, list]] = {}
    for k, test in enumerate(held_out):
        train = np.setdiff1d(np.arange(shapes.n_shapes), test)
        training = shapes.subset(train)
        check_determined(
            training,
            template,
            psi_sizes,
            eta_sizes,
            what=f"cross-validation fold {k + 1} of {len(held_out)} (measure more"
            " configurations or use fewer folds): ",
        )
        fitted = fit_shapes(training, template, psi_sizes, eta_sizes).catheter
        for unit, per_segment in _squared_errors(fitted, shapes.subset(test)).items():
            for name, values in per_segment.items():
                squares.setdefault(unit, {}).setdefault(name, []).append(values.ravel())
    joined = {
        unit: {name: np.concatenate(parts) for name, parts in per_segment.items()}
        for unit, per_segment in squares.items()
    }
    return ShapeResiduals.from_squares(joined, shapes.n_shapes)
