"""Calibration of a segment's modal shape matrix A from measured shapes (docs/design.md section 3).

The modal model ``theta(s, q) = psi(s / L)^T A eta(q)`` is linear in ``A``. Sampled on a grid of
arclengths ``s_k`` and joint values ``q_j`` it reads, row by row,

    theta(s_k, q_j) = (eta(q_j) kron psi(s_k / L))^T vec(A)

(``vec`` stacks the columns of ``A``), so measured tangent angles give ``A`` by linear least
squares. Measured backbone points give ``A`` by nonlinear least squares on the points,
started from the linear fit of the tangent angles of the chords between consecutive points.

Everything here is pure maths: arrays in, a :class:`CalibrationResult` out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from models.modal import Basis, ModalSegment, SegmentQuadrature

Array = np.ndarray

DEFAULT_QUADRATURE_ORDER = 16


@dataclass(frozen=True)
class CalibrationResult:
    """A fitted modal matrix and how well the data determined it.

    Attributes
    ----------
    A : array, shape (psi.size, eta.size)
        Fitted modal shape matrix (read-only).
    residual_rms_rad : float or None
        Root mean square of the angle residuals, rad (fits to tangent angles; else None).
    residual_rms_mm : float or None
        Root mean square of the point-distance residuals, mm (fits to points; else None).
    n_samples : int
        Number of measured samples used (angles, or 2-D points).
    rank : int
        Numerical rank of the design matrix (angles) or of the residual Jacobian at the
        solution (points); equal to ``A.size`` for a successful fit.
    condition_number : float
        2-norm condition number of that matrix. Large values mean that some combinations of
        the entries of ``A`` are poorly determined by the samples.
    length_mm : float
        Segment length L used to normalise the arclength, mm.
    psi, eta : Basis
        The arclength and joint bases of the fit.
    """

    A: Array
    residual_rms_rad: float | None
    residual_rms_mm: float | None
    n_samples: int
    rank: int
    condition_number: float
    length_mm: float
    psi: Basis
    eta: Basis

    def __post_init__(self) -> None:
        A = np.array(self.A, dtype=float)
        A.setflags(write=False)
        object.__setattr__(self, "A", A)

    def segment(self) -> ModalSegment:
        """The fitted segment model."""
        return ModalSegment(length_mm=self.length_mm, A=self.A, psi=self.psi, eta=self.eta)


# ---------------------------------------------------------------------------- input checks
def _check_length(length_mm: float) -> float:
    length = float(length_mm)
    if not np.isfinite(length) or length <= 0.0:
        raise ValueError(f"segment length must be positive and finite, got {length_mm}")
    return length


def _check_vector(x: Array, name: str) -> Array:
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D array, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    return x


def _check_arclengths(arclength_mm: Array, length_mm: float) -> Array:
    s = _check_vector(arclength_mm, "arclength_mm")
    if np.any(s < 0.0) or np.any(s > length_mm):
        raise ValueError(
            f"arclength_mm must lie in [0, {length_mm}] mm (the segment), "
            f"got min {s.min():.6g}, max {s.max():.6g}"
        )
    return s


def _check_determined(matrix: Array, basis_size: int, values: Array, what: str) -> int:
    """Rank of a basis-sample matrix, or a ValueError saying which samples are missing."""
    rank = int(np.linalg.matrix_rank(matrix))
    if rank < basis_size:
        n_distinct = np.unique(values).size
        raise ValueError(
            f"the samples cannot determine A: the {what} basis has {basis_size} terms but the "
            f"samples give it rank {rank} ({n_distinct} distinct {what} values); "
            f"measure at least {basis_size} distinct {what} values"
        )
    return rank


def _solve_angles(
    s_unit: Array, q_mm: Array, theta_rad: Array, psi: Basis, eta: Basis, s_mm: Array
) -> tuple[Array, int, float]:
    """Least-squares A for theta (n_q, n_s) on the grid, with the rank and condition number.

    With every (q_j, s_k) pair sampled, the design matrix is the Kronecker product
    ``Eta kron Psi`` and its pseudo-inverse is ``pinv(Eta) kron pinv(Psi)``; so the full
    least-squares solution is ``A = pinv(Psi) Theta^T pinv(Eta)^T``, computed as two small
    least-squares solves instead of one with n_q * n_s rows. Rank and singular values
    multiply the same way.
    """
    Psi = psi.values(s_unit)  # (n_s, n_psi)
    Eta = eta.values(q_mm)  # (n_q, n_eta)
    rank_psi = _check_determined(Psi, psi.size, s_mm, "arclength")
    rank_eta = _check_determined(Eta, eta.size, q_mm, "joint")
    X = np.linalg.lstsq(Psi, theta_rad.T, rcond=None)[0]  # (n_psi, n_q) = pinv(Psi) Theta^T
    A = np.linalg.lstsq(Eta, X.T, rcond=None)[0].T  # (n_psi, n_eta)
    condition = float(np.linalg.cond(Psi) * np.linalg.cond(Eta))
    return A, rank_psi * rank_eta, condition


# ---------------------------------------------------------------------------- public API
def fit_modal_matrix_from_angles(
    arclength_mm: Array,
    q_mm: Array,
    theta_rad: Array,
    length_mm: float,
    psi: Basis,
    eta: Basis,
) -> CalibrationResult:
    """Fit A to tangent angles measured on a grid of arclengths and joint values.

    Parameters
    ----------
    arclength_mm : array, shape (n_s,)
        Arclengths of the measured tangent angles, mm from the segment base, in [0, L].
    q_mm : array, shape (n_q,)
        Joint values (push/pull) of the measured shapes, mm.
    theta_rad : array, shape (n_q, n_s)
        Tangent angles theta(s_k, q_j), rad, measured from the segment's local x-axis toward
        its z-axis (straight segment: pi/2).
    length_mm : float
        Segment length L, mm.
    psi, eta : Basis
        Arclength basis (in s / L) and joint basis (in q, mm).

    Returns
    -------
    CalibrationResult
        With ``residual_rms_rad`` set.

    Raises
    ------
    ValueError
        On shape mismatch, non-finite data, arclengths outside the segment, or samples that
        cannot determine A (fewer distinct arclengths than ``psi.size`` or distinct joint
        values than ``eta.size``).
    """
    length = _check_length(length_mm)
    s = _check_arclengths(arclength_mm, length)
    q = _check_vector(q_mm, "q_mm")
    theta = np.asarray(theta_rad, dtype=float)
    if theta.shape != (q.size, s.size):
        raise ValueError(
            f"theta_rad must have shape (n_q, n_s) = ({q.size}, {s.size}), got {theta.shape}"
        )
    if not np.all(np.isfinite(theta)):
        raise ValueError("theta_rad contains non-finite values (NaN or inf)")
    A, rank, condition = _solve_angles(s / length, q, theta, psi, eta, s)
    residual = theta - eta.values(q) @ A.T @ psi.values(s / length).T
    return CalibrationResult(
        A=A,
        residual_rms_rad=float(np.sqrt(np.mean(residual**2))),
        residual_rms_mm=None,
        n_samples=int(theta.size),
        rank=rank,
        condition_number=condition,
        length_mm=length,
        psi=psi,
        eta=eta,
    )


def chord_angles(arclength_mm: Array, points_mm: Array) -> tuple[Array, Array]:
    """Tangent-angle estimates from consecutive backbone points, with the origin at s = 0.

    The chord from the point at ``s_{k-1}`` to the point at ``s_k`` (``s_{-1} = 0`` at the
    origin) has the direction of the tangent at its midpoint arclength up to O(h^2) in the
    spacing h. Angles are unwrapped along the segment, the first one taken within pi of the
    straight segment's pi/2.

    Parameters
    ----------
    arclength_mm : array, shape (n_s,)
        Strictly increasing arclengths > 0 of the points, mm.
    points_mm : array, shape (n_q, n_s, 2)
        In-plane (x, z) points, mm.

    Returns
    -------
    midpoints_mm : array, shape (n_s,)
    theta_rad : array, shape (n_q, n_s)
    """
    s = np.concatenate([[0.0], arclength_mm])
    p = np.concatenate([np.zeros(points_mm.shape[:-2] + (1, 2)), points_mm], axis=-2)
    d = np.diff(p, axis=-2)
    theta = np.arctan2(d[..., 1], d[..., 0])
    theta[..., 0] = np.mod(theta[..., 0] + np.pi / 2, 2.0 * np.pi) - np.pi / 2
    return 0.5 * (s[:-1] + s[1:]), np.unwrap(theta, axis=-1)


def fit_modal_matrix_from_points(
    arclength_mm: Array,
    q_mm: Array,
    points_mm: Array,
    length_mm: float,
    psi: Basis,
    eta: Basis,
    initial: Array | None = None,
    quadrature_order: int = DEFAULT_QUADRATURE_ORDER,
) -> CalibrationResult:
    """Fit A to backbone points measured in the segment's own bending plane.

    The model point is ``p(s, q) = int_0^s [cos theta, sin theta] ds`` integrated with
    Gauss-Legendre quadrature as in :mod:`models.catheter`. A is first estimated linearly from
    the chord angles (:func:`chord_angles`, unless ``initial`` is given) and then refined by
    ``scipy.optimize.least_squares`` on the point residuals with the analytic Jacobian.

    Parameters
    ----------
    arclength_mm : array, shape (n_s,)
        Strictly increasing arclengths of the points, mm, in (0, L].
    q_mm : array, shape (n_q,)
        Joint values of the measured shapes, mm.
    points_mm : array, shape (n_q, n_s, 2)
        Backbone points (x, z), mm, in the segment's bending-plane frame (origin at the segment
        base, z along the base tangent, x toward the bending side).
    length_mm : float
        Segment length L, mm.
    psi, eta : Basis
        Arclength basis (in s / L) and joint basis (in q, mm).
    initial : array, shape (psi.size, eta.size), optional
        Starting value of A; default: the linear fit to the chord angles.
    quadrature_order : int
        Gauss-Legendre nodes per integral.

    Returns
    -------
    CalibrationResult
        With ``residual_rms_mm`` (root mean square point distance) set.

    Raises
    ------
    ValueError
        On shape mismatch, non-finite data, arclengths not increasing inside (0, L], or samples
        that cannot determine A.
    RuntimeError
        If the nonlinear least-squares refinement does not converge.
    """
    length = _check_length(length_mm)
    s = _check_arclengths(arclength_mm, length)
    if s[0] <= 0.0 or np.any(np.diff(s) <= 0.0):
        raise ValueError("arclength_mm must be strictly increasing and > 0 for point data")
    q = _check_vector(q_mm, "q_mm")
    points = np.asarray(points_mm, dtype=float)
    if points.shape != (q.size, s.size, 2):
        raise ValueError(
            f"points_mm must have shape (n_q, n_s, 2) = ({q.size}, {s.size}, 2), got {points.shape}"
        )
    if not np.all(np.isfinite(points)):
        raise ValueError("points_mm contains non-finite values (NaN or inf)")
    if quadrature_order < 2:
        raise ValueError(f"quadrature_order must be >= 2, got {quadrature_order}")
    shape_A = (psi.size, eta.size)
    if initial is None:
        s_mid, theta = chord_angles(s, points)
        A0 = _solve_angles(s_mid / length, q, theta, psi, eta, s)[0]
    else:
        A0 = np.asarray(initial, dtype=float)
        if A0.shape != shape_A:
            raise ValueError(f"initial A has shape {A0.shape}, expected {shape_A}")
        if not np.all(np.isfinite(A0)):
            raise ValueError("initial A contains non-finite values")
        # The initial guess skips the linear fit, so check identifiability here.
        _check_determined(psi.values(s / length), psi.size, s, "arclength")
        _check_determined(eta.values(q), eta.size, q, "joint")

    quad = SegmentQuadrature.build(
        ModalSegment(length_mm=length, A=np.zeros(shape_A), psi=psi, eta=eta), s, quadrature_order
    )
    Eta = eta.values(q)  # (n_q, n_eta)
    psi_nodes, weights = quad.psi_nodes, quad.weights  # (n_nodes, n_psi), (n_nodes, n_s)

    def unpack(x: Array) -> Array:
        return x.reshape(shape_A, order="F")

    def angles(x: Array) -> Array:
        return Eta @ unpack(x).T @ psi_nodes.T  # (n_q, n_nodes)

    def residuals(x: Array) -> Array:
        th = angles(x)
        model = np.stack([np.cos(th) @ weights, np.sin(th) @ weights], -1)
        return (model - points).ravel()

    def jacobian(x: Array) -> Array:
        th = angles(x)
        # d p_k / d A_ab = sum_n w_nk [-sin, cos](theta_n) psi_a(s_n) eta_b(q_j)
        dx = np.einsum("jn,nk,na,jb->jkba", -np.sin(th), weights, psi_nodes, Eta, optimize=True)
        dz = np.einsum("jn,nk,na,jb->jkba", np.cos(th), weights, psi_nodes, Eta, optimize=True)
        # Column index b * n_psi + a matches vec(A) in column-major order.
        return np.stack([dx, dz], axis=2).reshape(q.size * s.size * 2, -1)

    solution = least_squares(
        residuals,
        A0.ravel(order="F"),
        jac=jacobian,
        method="lm",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=200 * A0.size,
    )
    if not solution.success:
        raise RuntimeError(f"point calibration did not converge: {solution.message}")
    r = solution.fun.reshape(q.size, s.size, 2)
    singular = np.linalg.svd(solution.jac, compute_uv=False)
    tol = singular[0] * max(solution.jac.shape) * np.finfo(float).eps
    rank = int(np.sum(singular > tol))
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    if rank < A0.size:
        raise ValueError(
            f"the point samples cannot determine A: residual Jacobian has rank {rank} < {A0.size}"
        )
    return CalibrationResult(
        A=unpack(solution.x),
        residual_rms_rad=None,
        residual_rms_mm=float(np.sqrt(np.mean(np.sum(r**2, axis=-1)))),
        n_samples=q.size * s.size,
        rank=rank,
        condition_number=condition,
        length_mm=length,
        psi=psi,
        eta=eta,
    )
