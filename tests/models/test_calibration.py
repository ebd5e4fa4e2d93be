"""Calibration of the modal matrix A: exact recovery, unbiasedness under noise, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from models.calibration import (
    CalibrationResult,
    chord_angles,
    fit_modal_matrix_from_angles,
    fit_modal_matrix_from_points,
)
from models.catheter import default_catheter
from models.modal import ModalSegment, PowerBasis

SEGMENTS = ("proximal", "distal")
Q_GRID_MM = np.linspace(-1.0, 1.0, 9)


def _segment(name: str) -> ModalSegment:
    return getattr(default_catheter(), name)


def _angle_grid(segment: ModalSegment) -> tuple[np.ndarray, np.ndarray]:
    s = np.linspace(0.0, segment.length_mm, 11)
    return s, segment.theta(s[None, :], Q_GRID_MM[:, None])


def _point_arclengths(segment: ModalSegment) -> np.ndarray:
    return np.linspace(segment.length_mm / 8, segment.length_mm, 8)


def _points_from_catheter(name: str, s_mm: np.ndarray, q_mm: np.ndarray) -> np.ndarray:
    """In-plane (x, z) points of one segment, taken from the catheter's backbone.

    This is an independent route to the data: the catheter's own direct kinematics, then the
    inverse of the segment's frame, not the calibration module's integrator.
    """
    catheter = default_catheter()
    L1 = catheter.proximal.length_mm
    if name == "proximal":
        q = np.stack([np.zeros_like(q_mm), q_mm, np.full_like(q_mm, 0.4)], -1)
        points_b = catheter.backbone(q, 0.0, s_mm)  # delta_1 = 0: the x-z plane
    else:
        q = np.stack([np.zeros_like(q_mm), np.full_like(q_mm, 0.4), q_mm], -1)
        frames = catheter.frames(q)
        points_b = catheter.backbone(q, 0.0, L1 + s_mm)
        # p_2 = R_b_2^T (o_b - o_2_b), delta_2 = 0 so the distal plane is the x-z plane of {2}.
        points_b = np.einsum("jba,jkb->jka", frames.R_b_2, points_b - frames.o_2_b[:, None, :])
    np.testing.assert_allclose(points_b[..., 1], 0.0, atol=1e-12)
    return points_b[..., [0, 2]]


# ---------------------------------------------------------------------------- exact recovery
@pytest.mark.parametrize("name", SEGMENTS)
def test_angles_recover_default_A_exactly(name):
    segment = _segment(name)
    s, theta = _angle_grid(segment)
    result = fit_modal_matrix_from_angles(
        s, Q_GRID_MM, theta, segment.length_mm, segment.psi, segment.eta
    )
    np.testing.assert_allclose(result.A, segment.A, rtol=0, atol=1e-9)
    assert result.residual_rms_rad < 1e-12
    assert result.residual_rms_mm is None
    assert result.n_samples == theta.size
    assert result.rank == segment.A.size
    assert 1.0 <= result.condition_number < 1e4


@pytest.mark.parametrize("name", SEGMENTS)
def test_points_recover_default_A_exactly(name):
    segment = _segment(name)
    s = _point_arclengths(segment)
    points = _points_from_catheter(name, s, Q_GRID_MM)
    result = fit_modal_matrix_from_points(
        s, Q_GRID_MM, points, segment.length_mm, segment.psi, segment.eta
    )
    np.testing.assert_allclose(result.A, segment.A, rtol=0, atol=1e-9)
    assert result.residual_rms_mm < 1e-10
    assert result.residual_rms_rad is None
    assert result.n_samples == s.size * Q_GRID_MM.size
    assert result.rank == segment.A.size
    assert np.isfinite(result.condition_number)


def test_non_square_bases_keep_the_orientation_of_A():
    # A square A would hide a transposed vec(A); use psi with 4 terms, eta with 2.
    rng = np.random.default_rng(7)
    A = np.zeros((4, 2))
    A[0, 0] = np.pi / 2
    A[1:, :] = 0.3 * rng.standard_normal((3, 2))
    segment = ModalSegment(length_mm=10.0, A=A, psi=PowerBasis(4), eta=PowerBasis(2))
    s = np.linspace(1.0, 10.0, 10)
    q = np.linspace(-1.0, 1.0, 5)
    theta = segment.theta(s[None, :], q[:, None])
    angles = fit_modal_matrix_from_angles(s, q, theta, 10.0, segment.psi, segment.eta)
    np.testing.assert_allclose(angles.A, A, rtol=0, atol=1e-9)

    x = segment.length_mm * np.linspace(0, 1, 4001)
    th = segment.theta(x[None, :], q[:, None])
    # Independent integration (composite Simpson on a fine grid) of [cos, sin] theta.
    points = np.empty((q.size, s.size, 2))
    for k, s_k in enumerate(s):
        n = int(round(s_k / 10.0 * 4000))
        for c, f in enumerate((np.cos, np.sin)):
            y = f(th[:, : n + 1])
            h = x[1] - x[0]
            points[:, k, c] = (
                h / 3 * (y[:, 0] + y[:, n] + 4 * y[:, 1:n:2].sum(-1) + 2 * y[:, 2:n:2].sum(-1))
            )
    result = fit_modal_matrix_from_points(s, q, points, 10.0, segment.psi, segment.eta)
    np.testing.assert_allclose(result.A, A, rtol=0, atol=1e-9)
    assert result.segment().A.shape == (4, 2)


@pytest.mark.parametrize("name", SEGMENTS)
def test_segment_of_the_result_reproduces_the_angles(name):
    segment = _segment(name)
    s, theta = _angle_grid(segment)
    result = fit_modal_matrix_from_angles(
        s, Q_GRID_MM, theta, segment.length_mm, segment.psi, segment.eta
    )
    fitted = result.segment()
    assert isinstance(fitted, ModalSegment)
    assert fitted.length_mm == segment.length_mm
    np.testing.assert_allclose(fitted.theta(s[None, :], Q_GRID_MM[:, None]), theta, atol=1e-12)
    with pytest.raises(ValueError):
        result.A[0, 0] = 0.0  # read-only


def test_points_with_initial_guess_converge_to_the_same_A():
    segment = _segment("proximal")
    s = _point_arclengths(segment)
    points = _points_from_catheter("proximal", s, Q_GRID_MM)
    initial = segment.A + 0.05 * np.random.default_rng(3).standard_normal(segment.A.shape)
    result = fit_modal_matrix_from_points(
        s, Q_GRID_MM, points, segment.length_mm, segment.psi, segment.eta, initial=initial
    )
    np.testing.assert_allclose(result.A, segment.A, rtol=0, atol=1e-9)


def test_chord_angles_are_the_tangent_at_the_midpoint_to_second_order():
    # Constant curvature: the chord angle equals the midpoint tangent angle exactly.
    kappa = 0.12
    s = np.linspace(0.5, 13.0, 26)
    x, z = (1 - np.cos(kappa * s)) / kappa, np.sin(kappa * s) / kappa
    s_mid, theta = chord_angles(s, np.stack([x, z], -1)[None])
    np.testing.assert_allclose(s_mid, np.concatenate([[0.25], 0.5 * (s[1:] + s[:-1])]))
    np.testing.assert_allclose(theta[0], np.pi / 2 - kappa * s_mid, atol=1e-12)


def test_chord_angles_unwrap_past_pi():
    # Bending by more than 180 degrees (q = -1 on the default model) wraps atan2.
    kappa = -0.3
    s = np.linspace(0.25, 13.0, 52)
    x, z = (1 - np.cos(kappa * s)) / kappa, np.sin(kappa * s) / kappa
    _, theta = chord_angles(s, np.stack([x, z], -1)[None])
    assert theta[0, -1] > np.pi
    assert np.all(np.diff(theta[0]) > 0)


# ---------------------------------------------------------------------------- noise
def _mean_within_three_standard_errors(estimates: np.ndarray, truth: np.ndarray) -> None:
    mean = estimates.mean(axis=0)
    standard_error = estimates.std(axis=0, ddof=1) / np.sqrt(estimates.shape[0])
    assert np.all(standard_error > 0)
    z = np.abs(mean - truth) / standard_error
    assert np.all(z < 3.0), f"bias of {z.max():.2f} standard errors, mean {mean}, truth {truth}"


@pytest.mark.parametrize("name", SEGMENTS)
def test_angle_fit_is_unbiased_under_gaussian_noise(name):
    segment = _segment(name)
    s, theta = _angle_grid(segment)
    rng = np.random.default_rng(20230529)
    sigma_rad = 0.02
    estimates, rms = [], []
    for _ in range(200):
        noisy = theta + sigma_rad * rng.standard_normal(theta.shape)
        result = fit_modal_matrix_from_angles(
            s, Q_GRID_MM, noisy, segment.length_mm, segment.psi, segment.eta
        )
        estimates.append(result.A)
        rms.append(result.residual_rms_rad)
    _mean_within_three_standard_errors(np.array(estimates), segment.A)
    # E[RSS] = sigma^2 (n - p): the residual RMS estimates the noise level.
    expected = sigma_rad * np.sqrt((theta.size - segment.A.size) / theta.size)
    assert np.mean(rms) == pytest.approx(expected, rel=0.02)


@pytest.mark.parametrize("name", SEGMENTS)
def test_point_fit_is_unbiased_under_gaussian_noise(name):
    segment = _segment(name)
    s = _point_arclengths(segment)
    points = _points_from_catheter(name, s, Q_GRID_MM)
    rng = np.random.default_rng(1234)
    sigma_mm = 0.05
    estimates = []
    for _ in range(40):
        noisy = points + sigma_mm * rng.standard_normal(points.shape)
        result = fit_modal_matrix_from_points(
            s, Q_GRID_MM, noisy, segment.length_mm, segment.psi, segment.eta
        )
        estimates.append(result.A)
        assert 0.5 * sigma_mm < result.residual_rms_mm < 2.0 * sigma_mm
    _mean_within_three_standard_errors(np.array(estimates), segment.A)


# ---------------------------------------------------------------------------- bad input
def _valid_angle_args():
    segment = _segment("proximal")
    s, theta = _angle_grid(segment)
    return dict(
        arclength_mm=s,
        q_mm=Q_GRID_MM,
        theta_rad=theta,
        length_mm=segment.length_mm,
        psi=segment.psi,
        eta=segment.eta,
    )


def _valid_point_args():
    segment = _segment("proximal")
    s = _point_arclengths(segment)
    return dict(
        arclength_mm=s,
        q_mm=Q_GRID_MM,
        points_mm=_points_from_catheter("proximal", s, Q_GRID_MM),
        length_mm=segment.length_mm,
        psi=segment.psi,
        eta=segment.eta,
    )


def _with_nan(x):
    x = np.array(x, dtype=float)
    x.flat[1] = np.nan
    return x


ANGLE_FAULTS = {
    "theta shape": (lambda a: {"theta_rad": a["theta_rad"].T}, "theta_rad must have shape"),
    "theta 1-D": (lambda a: {"theta_rad": a["theta_rad"][0]}, "theta_rad must have shape"),
    "theta NaN": (
        lambda a: {"theta_rad": _with_nan(a["theta_rad"])},
        "theta_rad contains non-finite",
    ),
    "q NaN": (lambda a: {"q_mm": _with_nan(a["q_mm"])}, "q_mm contains non-finite"),
    "q 2-D": (lambda a: {"q_mm": a["q_mm"][:, None]}, "q_mm must be a non-empty 1-D"),
    "s inf": (
        lambda a: {"arclength_mm": np.where(np.arange(11) == 3, np.inf, a["arclength_mm"])},
        "arclength_mm contains non-finite",
    ),
    "s outside": (lambda a: {"arclength_mm": a["arclength_mm"] + 1.0}, "must lie in"),
    "s negative": (lambda a: {"arclength_mm": a["arclength_mm"] - 1.0}, "must lie in"),
    "length zero": (lambda a: {"length_mm": 0.0}, "segment length must be positive"),
    "length NaN": (lambda a: {"length_mm": np.nan}, "segment length must be positive"),
    "too few distinct s": (
        lambda a: {
            "arclength_mm": np.array([1.0, 1.0, 2.0, 2.0, 1.0, 2.0, 1.0, 2.0, 1.0, 2.0, 2.0])
        },
        "at least 3 distinct arclength",
    ),
    "too few distinct q": (
        lambda a: {
            "q_mm": np.array([0.5, -0.5, 0.5, -0.5, 0.5, -0.5, 0.5, -0.5, 0.5]),
        },
        "at least 3 distinct joint",
    ),
    "too few q": (
        lambda a: {"q_mm": a["q_mm"][:2], "theta_rad": a["theta_rad"][:2]},
        "at least 3 distinct joint",
    ),
}


@pytest.mark.parametrize("fault", ANGLE_FAULTS)
def test_bad_angle_input_raises(fault):
    args = _valid_angle_args()
    change, message = ANGLE_FAULTS[fault]
    args.update(change(args))
    with pytest.raises(ValueError, match=message):
        fit_modal_matrix_from_angles(**args)


POINT_FAULTS = {
    "points shape": (lambda a: {"points_mm": a["points_mm"][..., :1]}, "points_mm must have shape"),
    "points transposed": (
        lambda a: {"points_mm": a["points_mm"].transpose(1, 0, 2)},
        "points_mm must have shape",
    ),
    "points NaN": (
        lambda a: {"points_mm": _with_nan(a["points_mm"])},
        "points_mm contains non-finite",
    ),
    "s zero": (
        lambda a: {"arclength_mm": np.concatenate([[0.0], a["arclength_mm"][1:]])},
        "strictly increasing and > 0",
    ),
    "s not increasing": (
        lambda a: {"arclength_mm": a["arclength_mm"][::-1]},
        "strictly increasing and > 0",
    ),
    "s outside": (lambda a: {"arclength_mm": a["arclength_mm"] * 1.5}, "must lie in"),
    "too few s": (
        lambda a: {"arclength_mm": a["arclength_mm"][:2], "points_mm": a["points_mm"][:, :2]},
        "at least 3 distinct arclength",
    ),
    "too few distinct q": (
        lambda a: {"q_mm": np.repeat([0.5, -0.5], 5)[:9]},
        "at least 3 distinct joint",
    ),
    "initial shape": (lambda a: {"initial": np.zeros((3, 2))}, "initial A has shape"),
    "initial NaN": (
        lambda a: {"initial": np.full((3, 3), np.nan)},
        "initial A contains non-finite",
    ),
    "initial and too few q": (
        lambda a: {"initial": np.zeros((3, 3)), "q_mm": np.repeat([0.5, -0.5], 5)[:9]},
        "at least 3 distinct joint",
    ),
    "quadrature order": (lambda a: {"quadrature_order": 1}, "quadrature_order must be >= 2"),
}


@pytest.mark.parametrize("fault", POINT_FAULTS)
def test_bad_point_input_raises(fault):
    args = _valid_point_args()
    change, message = POINT_FAULTS[fault]
    args.update(change(args))
    with pytest.raises(ValueError, match=message):
        fit_modal_matrix_from_points(**args)


def test_result_is_a_frozen_value():
    result = fit_modal_matrix_from_angles(**_valid_angle_args())
    assert isinstance(result, CalibrationResult)
    with pytest.raises(AttributeError):
        result.A = np.zeros((3, 3))
