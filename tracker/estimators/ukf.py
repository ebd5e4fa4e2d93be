"""Unscented Kalman filter of the torsional loss angle delta_L (DESIGN.md section 5).

The state is ``[delta_L]`` (rad) or, with ``include_rate``, ``[delta_L, delta_L_dot]``
(rad, rad/s). Process model: a random walk whose intensity grows with the commanded base
rotation speed ``|q_r_dot|`` (torsion builds up while the base turns). Measurement model
(DESIGN.md section 3): every fused vector is ``Rz(q_r + delta_L) c`` for a delta_L-independent
``c`` from :meth:`models.catheter.Catheter.shape_vectors` -- the tip, each segmented marker and
the tip velocity are stacked into one update whose covariance is the joint one, including the
cross-covariance between the velocity and the tip. When the views are not synchronised, each
:class:`~tracker.types.ViewMeasurement` is used through its own projection
``view.project(R_w_b @ Rz(q_r + delta_L) c + o_b_w)``.

A finite-difference velocity ``(tip_t - tip_{t-1}) / dt`` shares its noise with *both* tips.
The cross-covariance covers the current one; the previous one was already fused in the last
update, and nothing in an observation can express that correlation, so such a velocity is
fused only when the previous step did not fuse a tip (``velocity_is_finite_difference``).
Fused every frame it counts each tip twice: in simulation +10 to +30 % mean-square error and
an overconfident std, whereas a velocity with independent noise lowers the error.

The filter object is filterpy's :class:`~filterpy.kalman.UnscentedKalmanFilter` (its
``predict``, ``x`` and ``P``; the update is its equations with the per-sigma-point loops
vectorised, see :class:`_AngleUKF`); this module wraps it so that nothing else touches its
mutable attributes, and every step returns an :class:`~tracker.types.Estimate` value.

Numerical notes
---------------
- Angles: sigma points, the state mean (weighted circular mean), the state residual and the
  state addition all wrap delta_L to ``[-pi, pi)``. A wrapped residual is only unambiguous
  while the sigma-point spread ``sqrt(alpha^2 (n + kappa)) * std`` stays below pi, so the
  predicted std is capped below that (``max_std_rad``, 1.8 rad by default): a wrapped normal
  with std 1.8 rad is already close to uniform (mean resultant length 0.2), so the cap loses
  nothing. The default sigma points (alpha = 1, beta = 2, kappa = 3 - n) have positive
  weights, which keeps the weighted circular mean from flipping by pi for wide spreads.
- filterpy 2.0 re-draws the sigma points from ``P`` at the end of ``predict`` and draws them
  again at the start of the next ``predict``; both factorise ``P`` and raise ``LinAlgError``
  when it is not positive definite. The square root given to the sigma points symmetrises and
  retries once with a documented jitter (``COVARIANCE_JITTER`` times the mean variance); if
  that fails too, the step restores the last good state, re-initialises the covariance and
  reports ``Flag.COVARIANCE_REPAIRED``. The innovation covariance is applied by Cholesky
  solves (LAPACK ``potrf``/``potrs``, same jitter rule), never inverted. ``P`` is symmetrised
  after each step; no step returns NaN once the filter is initialised.
- Global (re-)initialisation: the first informative frame (closed-form Fisher std below
  ``uninformative_std_rad``) initialises the filter with the exact global closed-form minimiser
  (:func:`models.rotation_fit.fit_rotation_z`) of all its 3-D data and that minimiser's Fisher
  variance. The same closed form re-initialises the filter when its predicted std has grown
  beyond ``reacquire_std_rad`` (the prior carries almost nothing, and a sigma-point update of a
  nearly uniform prior would be a poor approximation), and after ``reacquire_after_rejections``
  consecutive gate rejections whose data are self-consistent (a torsion jump, not a bad
  segmentation: a wrong segmentation shows up as a large closed-form cost and is not used).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.linalg import lapack
from scipy.stats import chi2

from models.catheter import Catheter, ShapeVectors
from models.rotation_fit import fit_rotation_z
from tracker.estimators.per_frame import UNINFORMATIVE_STD_RAD
from tracker.types import Estimate, Flag, Observation, ViewMeasurement

Array = np.ndarray

# Relative jitter added (times the mean variance) before a second Cholesky attempt.
COVARIANCE_JITTER = 1e-9
# Absolute floor of that jitter, rad^2 (or the squared measurement unit for S).
COVARIANCE_JITTER_FLOOR = 1e-15
# Step for the numerical derivative of a projection with respect to delta_L, rad.
_VIEW_DERIVATIVE_STEP_RAD = 1e-6
_TWO_PI = 2.0 * math.pi
# Per accepted update, the excess of the model-mismatch noise inflation is multiplied by this.
MISMATCH_DECAY = 0.99
# The model-mismatch inflation of the measurement covariance never exceeds this factor.
MAX_MISMATCH_SCALE = 1e4
# Sigma-point offsets of a 1-D state in units of the square root: x, x + U, x - U.
_UNIT_OFFSETS = np.array([[0.0], [1.0], [-1.0]])


class CovarianceError(np.linalg.LinAlgError):
    """A covariance stayed non-positive-definite after symmetrisation and jitter."""


@dataclass(frozen=True)
class UKFSettings:
    """Settings of :class:`BendingPlaneUKF` (validated on construction).

    Parameters
    ----------
    process_noise_rad2_s : float
        Random-walk intensity of delta_L, rad^2/s: a frame interval dt adds this times dt to
        the variance.
    rotation_noise_gain_rad : float
        Extra random-walk intensity per rad/s of commanded base rotation speed |q_r_dot|, so the
        intensity is ``process_noise_rad2_s + rotation_noise_gain_rad * |q_r_dot|`` (rad^2/s).
        The default 0.05 rad gave 2-sigma coverage of 96-97 % in the demo's simulated torsion
        wind-up (60 degrees of play, base turning at up to 1 rad/s); 0.01 gave 64 %.
    use_velocity : bool
        Fuse the tip velocity when the observation has one (see the next setting).
    velocity_is_finite_difference : bool
        The velocity is ``(tip_t - tip_{t-1}) / dt`` of this frame's and the previous frame's
        tips (:func:`tracker.types.velocity_from_positions`). Its noise then repeats the
        previous tip's noise, which the filter has already fused if its previous step updated
        with that tip; the cross-covariance with the current tip cannot express this, and such
        a velocity carries no information beyond the two positions. Fusing it anyway counts the
        previous tip twice (measured: +10 to +30 % mean-square error and an overconfident std),
        so it is fused only when the previous step did not fuse a tip. Set False for a velocity
        whose noise is independent of earlier frames (correlated at most with this frame's tip,
        through ``velocity_tip_cov_b``): it is then fused whenever present.
    include_rate : bool
        State ``[delta_L, delta_L_dot]`` instead of ``[delta_L]``; the rate is a random walk of
        intensity ``rate_process_noise_rad2_s3`` and enters the velocity model.
    rate_process_noise_rad2_s3 : float
        Random-walk intensity of delta_L_dot, rad^2/s^3 (only with ``include_rate``).
    initial_rate_std_rad_s : float
        Initial std of delta_L_dot, rad/s (only with ``include_rate``).
    gate_probability : float
        Chi-square quantile (on the measurement dimension) of the NIS gate, in (0, 1]; 1 turns
        the gate off.
    uninformative_std_rad : float
        A frame whose closed-form Fisher std exceeds this is uninformative (near straight):
        the filter only predicts.
    initial_std_rad : float or None
        Std to start with at the first informative frame; None takes that frame's Fisher std,
        so the first estimate is exactly the per-frame closed-form one. A larger value is a more
        conservative start; a value below the Fisher std is raised to it.
    max_std_rad : float
        Cap on the predicted std of delta_L, rad. ``max_std_rad * sqrt(alpha^2 (n + kappa))``
        must stay below pi so that wrapped sigma-point residuals are unambiguous.
    reacquire_std_rad : float
        Above this predicted std an informative frame re-initialises the filter from its
        closed-form solution instead of updating it.
    reacquire_after_rejections : int
        After this many consecutive NIS-gate rejections, a frame whose closed-form fit is
        consistent re-initialises the filter (a real torsion jump); 0 never re-initialises.
    alpha, beta, kappa : float
        Van der Merwe's sigma-point parameters; ``kappa=None`` means ``3 - n``.
    estimate_noise : bool
        Estimate a scale of the measurement covariances online from the innovations (forgetting
        factor ``noise_forgetting``), for a segmentation noise that is not known well.
    noise_forgetting : float
        Forgetting factor of that estimate, in (0, 1).
    noise_scale_bounds : tuple of float
        Limits of the estimated scale.
    """

    process_noise_rad2_s: float = 1e-4
    rotation_noise_gain_rad: float = 0.05
    use_velocity: bool = True
    velocity_is_finite_difference: bool = True
    include_rate: bool = False
    rate_process_noise_rad2_s3: float = 1e-3
    initial_rate_std_rad_s: float = 0.1
    gate_probability: float = 0.9999
    uninformative_std_rad: float = UNINFORMATIVE_STD_RAD
    initial_std_rad: float | None = None
    max_std_rad: float = 1.8
    reacquire_std_rad: float = 0.5
    reacquire_after_rejections: int = 3
    alpha: float = 1.0
    beta: float = 2.0
    kappa: float | None = None
    estimate_noise: bool = False
    noise_forgetting: float = 0.98
    noise_scale_bounds: tuple[float, float] = (1e-3, 1e3)

    def __post_init__(self) -> None:
        def positive(name: str, value: float, allow_zero: bool = False) -> None:
            ok = math.isfinite(value) and (value >= 0 if allow_zero else value > 0)
            if not ok:
                bound = ">= 0" if allow_zero else "> 0"
                raise ValueError(f"UKFSettings.{name} must be finite and {bound}, got {value}")

        positive("process_noise_rad2_s", self.process_noise_rad2_s, allow_zero=True)
        positive("rotation_noise_gain_rad", self.rotation_noise_gain_rad, allow_zero=True)
        positive("rate_process_noise_rad2_s3", self.rate_process_noise_rad2_s3, allow_zero=True)
        positive("initial_rate_std_rad_s", self.initial_rate_std_rad_s)
        positive("uninformative_std_rad", self.uninformative_std_rad)
        positive("max_std_rad", self.max_std_rad)
        positive("reacquire_std_rad", self.reacquire_std_rad)
        positive("alpha", self.alpha)
        positive("beta", self.beta, allow_zero=True)
        if self.initial_std_rad is not None:
            positive("initial_std_rad", self.initial_std_rad)
        if not (0.0 < self.gate_probability <= 1.0):
            raise ValueError(
                f"UKFSettings.gate_probability must lie in (0, 1], got {self.gate_probability}"
            )
        if int(self.reacquire_after_rejections) != self.reacquire_after_rejections or (
            self.reacquire_after_rejections < 0
        ):
            raise ValueError(
                "UKFSettings.reacquire_after_rejections must be an integer >= 0, got "
                f"{self.reacquire_after_rejections}"
            )
        if not (0.0 < self.noise_forgetting < 1.0):
            raise ValueError(
                f"UKFSettings.noise_forgetting must lie in (0, 1), got {self.noise_forgetting}"
            )
        object.__setattr__(self, "noise_scale_bounds", tuple(self.noise_scale_bounds))
        if len(self.noise_scale_bounds) != 2:
            bounds = self.noise_scale_bounds
            raise ValueError(f"UKFSettings.noise_scale_bounds must be (low, high), got {bounds}")
        low, high = self.noise_scale_bounds
        if not (0.0 < low <= 1.0 <= high < math.inf):
            raise ValueError(
                "UKFSettings.noise_scale_bounds must satisfy 0 < low <= 1 <= high < inf, got "
                f"{self.noise_scale_bounds}"
            )
        if self.uninformative_std_rad > self.max_std_rad:
            raise ValueError(
                f"UKFSettings.uninformative_std_rad ({self.uninformative_std_rad}) must not exceed"
                f" max_std_rad ({self.max_std_rad})"
            )
        if self.reacquire_std_rad > self.max_std_rad:
            raise ValueError(
                f"UKFSettings.reacquire_std_rad ({self.reacquire_std_rad}) must not exceed"
                f" max_std_rad ({self.max_std_rad})"
            )
        n = self.state_dim
        kappa = self.sigma_kappa
        if self.alpha**2 * (n + kappa) <= 0:
            raise ValueError(
                f"UKFSettings: alpha^2 (n + kappa) must be > 0, got alpha={self.alpha}, "
                f"kappa={kappa}, n={n}"
            )
        scale = math.sqrt(self.alpha**2 * (n + kappa))
        if self.max_std_rad * scale >= math.pi:
            raise ValueError(
                f"UKFSettings.max_std_rad={self.max_std_rad} puts sigma points "
                f"{self.max_std_rad * scale:.3f} rad from the mean, beyond pi, where a wrapped "
                f"residual is ambiguous; use max_std_rad < {math.pi / scale:.3f}"
            )

    @property
    def state_dim(self) -> int:
        """Dimension of the filter state: 1, or 2 with ``include_rate``."""
        return 2 if self.include_rate else 1

    @property
    def sigma_kappa(self) -> float:
        """The kappa actually used (``3 - n`` when ``kappa`` is None)."""
        return float(3 - self.state_dim) if self.kappa is None else float(self.kappa)


@lru_cache(maxsize=256)
def gate_threshold(probability: float, dof: int) -> float:
    """Chi-square quantile of the NIS gate (inf when the gate is off)."""
    if probability >= 1.0:
        return math.inf
    return float(chi2.ppf(probability, dof))


def _wrap_scalar(angle: float) -> float:
    return (angle + math.pi) % _TWO_PI - math.pi


def _residual_x(a: Array, b: Array) -> Array:
    """State difference a - b with the angle wrapped to [-pi, pi) (one state or rows of them)."""
    y = np.subtract(a, b)
    if y.ndim == 1:
        y[0] = (float(y[0]) + math.pi) % _TWO_PI - math.pi
    else:
        y[:, 0] = (y[:, 0] + math.pi) % _TWO_PI - math.pi
    return y


def _state_add(x: Array, dx: Array) -> Array:
    """x + dx with the angle wrapped to [-pi, pi)."""
    y = np.add(x, dx)
    y[0] = (float(y[0]) + math.pi) % _TWO_PI - math.pi
    return y


def _state_mean(sigmas: Array, weights: Array) -> Array:
    """Weighted mean of sigma points: circular for the angle, arithmetic for the rate."""
    mean = weights @ sigmas
    mean[0] = math.atan2(weights @ np.sin(sigmas[:, 0]), weights @ np.cos(sigmas[:, 0]))
    return mean


def _state_transform(sigmas, Wm, Wc, noise_cov, mean_fn=None, residual_fn=None):
    """Vectorised unscented transform of the state sigma points (filterpy's ``UT`` hook)."""
    x = _state_mean(sigmas, Wm)
    y = _residual_x(sigmas, x)
    P = (y.T * Wc) @ y
    if noise_cov is not None:
        P += noise_cov
    return x, P


def _jittered(A: Array) -> Array:
    A = 0.5 * (A + A.T)
    scale = max(float(np.trace(A)) / A.shape[0], 0.0)
    return A + max(COVARIANCE_JITTER * scale, COVARIANCE_JITTER_FLOOR) * np.eye(A.shape[0])


def _cholesky_lower(A: Array) -> Array:
    """Lower Cholesky factor, retried once with jitter; CovarianceError if it still fails."""
    if not np.isfinite(A).all():
        raise CovarianceError("covariance contains non-finite values")
    c, info = lapack.dpotrf(A, lower=1, clean=1)
    if info != 0:
        c, info = lapack.dpotrf(_jittered(A), lower=1, clean=1)
        if info != 0:
            raise CovarianceError("covariance is not positive definite, even after jitter")
    return c


def sigma_sqrt(A: Array) -> Array:
    """Upper-triangular square root U (U^T U = A) for the sigma points, with jitter.

    Raises CovarianceError (a LinAlgError) when ``A`` is not positive definite even after the
    documented jitter.
    """
    if A.shape == (1, 1):
        a = float(A[0, 0])
        if not math.isfinite(a):
            raise CovarianceError("covariance contains non-finite values")
        if a <= 0.0:
            # A variance that rounded to zero or just below gets the jitter floor.
            if a < -COVARIANCE_JITTER_FLOOR:
                raise CovarianceError(f"variance {a} is negative")
            a = COVARIANCE_JITTER_FLOOR
        return np.array([[math.sqrt(a)]])
    return _cholesky_lower(A).T


def spd_inverse(A: Array) -> Array:
    """Inverse of a symmetric positive-definite matrix by Cholesky solves against I.

    (LAPACK ``potrs``; the explicit ``potri`` of scipy's OpenBLAS was measured to stall for
    tens of milliseconds now and then, where ``potrs`` takes microseconds.)
    """
    inverse, info = lapack.dpotrs(_cholesky_lower(A), np.eye(A.shape[0]), lower=1)
    if info != 0:
        raise CovarianceError("covariance could not be inverted")
    return 0.5 * (inverse + inverse.T)


class _WrappedSigmaPoints(MerweScaledSigmaPoints):
    """Van der Merwe's sigma points, vectorised, with delta_L wrapped to [-pi, pi).

    Same points and weights as the parent class (rows x, x + U_k, x - U_k for the upper square
    root U of (lambda + n) P); only the per-row Python loop is replaced by array operations.
    """

    def sigma_points(self, x: Array, P: Array) -> Array:
        lambda_ = self.alpha**2 * (self.n + self.kappa) - self.n
        U = self.sqrt((lambda_ + self.n) * P)
        if self.n == 1:
            sigmas = x + _UNIT_OFFSETS * U[0, 0]
        else:
            sigmas = np.vstack((x, x + U, x - U))
        sigmas[:, 0] = (sigmas[:, 0] + math.pi) % _TWO_PI - math.pi
        return sigmas


class _AngleUKF(UnscentedKalmanFilter):
    """filterpy's UKF with the per-sigma-point Python loops replaced by array operations.

    ``compute_process_sigmas`` (called by filterpy's ``predict``) passes all sigma points to
    ``fx`` at once, and :meth:`update_sigmas` is filterpy's ``update`` with all measurement
    sigma points from one call. Per frame that Python overhead costs more than the arithmetic
    of a 1- or 2-state filter; the equations are filterpy's.
    """

    def compute_process_sigmas(self, dt, fx=None, **fx_args):
        if fx is None:
            fx = self.fx
        self.sigmas_f = fx(self.points_fn.sigma_points(self.x, self.P), dt, **fx_args)

    def update_sigmas(self, z: Array, R: Array, hx_sigmas: Callable[[Array], Array]) -> float:
        """filterpy's ``update`` with vectorised measurement sigma points; returns the NIS.

        Same equations as ``UnscentedKalmanFilter.update``: unscented transform of the sigma
        points drawn at the end of ``predict``, cross-covariance with ``residual_x``, gain
        ``K = Pxz S^-1``, ``x = state_add(x, K y)``, ``P = P - K S K^T`` (written as
        ``P - K Pxz^T``, the same matrix). ``S^-1`` is applied by Cholesky solves (with the
        documented jitter) rather than formed, so ``SI`` is not set; ``sigmas_h``, ``S``,
        ``K``, ``y``, ``z``, ``x``, ``P``, ``x_post`` and ``P_post`` are.

        Parameters
        ----------
        z : array, shape (m,)
        R : array, shape (m, m)
        hx_sigmas : callable
            Maps the sigma points (k, dim_x) to the measurement sigma points (k, m).
        """
        sigmas_h = hx_sigmas(self.sigmas_f)
        zp = self.Wm @ sigmas_h
        dz = sigmas_h - zp
        S = (dz.T * self.Wc) @ dz + R
        dx = self.residual_x(self.sigmas_f, self.x)
        Pxz = (dx.T * self.Wc) @ dz
        y = z - zp
        n = Pxz.shape[0]
        rhs = np.empty((y.size, n + 1))
        rhs[:, :n] = Pxz.T
        rhs[:, n] = y
        solved, info = lapack.dpotrs(_cholesky_lower(S), rhs, lower=1)
        if info != 0:
            raise CovarianceError("innovation covariance could not be factorised")
        K = solved[:, :n].T
        self.sigmas_h, self.S, self.K, self.y, self.z = sigmas_h, S, K, y, z
        self.x = self.state_add(self.x, K @ y)
        self.P = self.P - K @ Pxz.T
        self.x_post = self.x.copy()
        self.P_post = self.P.copy()
        self._log_likelihood = None
        self._likelihood = None
        self._mahalanobis = None
        return float(y @ solved[:, n])


def _is_finite(a) -> bool:
    return a is not None and bool(np.isfinite(a).all())


class _Measurement:
    """One frame's stacked measurement z = h(x) + noise with covariance R."""

    __slots__ = (
        "z",
        "R",
        "hx",
        "slope",
        "partial",
        "radius_mm",
        "y_vectors",
        "c_vectors",
        "has_tip",
    )

    def __init__(
        self, z, R, hx, slope, partial, radius_mm, y_vectors=None, c_vectors=None, has_tip=False
    ):
        self.z = z  # (m,)
        self.R = R  # (m, m)
        self.hx = hx  # sigma points (k, n) -> measurement sigma points (k, m)
        self.slope = slope  # state -> dh/d delta_L (m,), or None: e_z x h(x) for 3-D data
        self.partial = partial
        self.radius_mm = radius_mm
        # 3-D data only (for the closed form): measured and model vectors, (k, 3) each; the
        # closed form assumes delta_L_dot = 0 in the velocity.
        self.y_vectors = y_vectors
        self.c_vectors = c_vectors
        self.has_tip = has_tip  # the 3-D tip is part of z


def _rotation_hx(cxy: Array, cz: Array, D: Array | None, q_r: float) -> Callable:
    """Measurement sigma points Rz(q_r + x0) (C + x1 D), stacked, for sigma points (k, n).

    ``cxy = C_x + i C_y`` and ``cz = C_z`` for the model vectors C (rows), since a rotation
    about z of the xy components is a complex multiplication by exp(i angle).
    """
    n = cxy.shape[0]
    dxy = None if D is None else D[:, 0] + 1j * D[:, 1]

    def hx_sigmas(sigmas: Array) -> Array:
        turn = np.exp(1j * (q_r + sigmas[:, 0]))[:, None]
        rotated = turn * (cxy if dxy is None else cxy + sigmas[:, 1:2] * dxy)
        out = np.empty((sigmas.shape[0], n, 3))
        out[:, :, 0] = rotated.real
        out[:, :, 1] = rotated.imag
        out[:, :, 2] = cz
        return out.reshape(sigmas.shape[0], 3 * n)

    return hx_sigmas


def _rotation_slope(h: Array) -> Array:
    """d h / d delta_L = e_z x h for stacked rotated vectors h (3k,)."""
    p = h.reshape(-1, 3)
    out = np.zeros_like(p)
    out[:, 0] = -p[:, 1]
    out[:, 1] = p[:, 0]
    return out.ravel()


def _view_hx(views: list[tuple[ViewMeasurement, Array]], q_r: float) -> tuple[Callable, Callable]:
    """Projections of R_w_b Rz(q_r + x0) c + o_b_w in each view, and dh/dx0 at a state."""
    frames = [
        (v.view, C, np.asarray(v.R_w_b, dtype=float), np.asarray(v.o_b_w_mm, dtype=float))
        for v, C in views
    ]

    def hx_sigmas(sigmas: Array) -> Array:
        angle = q_r + sigmas[:, 0]
        c, s = np.cos(angle), np.sin(angle)
        zero, one = np.zeros_like(c), np.ones_like(c)
        # Rz(a)^T for every sigma point, so that points (k, p, 3) = C @ Rz^T.
        Rz_T = np.stack(
            [
                np.stack([c, s, zero], -1),
                np.stack([-s, c, zero], -1),
                np.stack([zero, zero, one], -1),
            ],
            -2,
        )
        parts = [
            np.asarray(view.project(C @ Rz_T @ R_w_b.T + o_b_w), dtype=float).reshape(len(c), -1)
            for view, C, R_w_b, o_b_w in frames
        ]
        return np.concatenate(parts, axis=1)

    def slope(x: Array) -> Array:
        # Any view with a project() will do, so the derivative is a central difference.
        step = np.zeros_like(x)
        step[0] = _VIEW_DERIVATIVE_STEP_RAD
        h = hx_sigmas(np.vstack((x + step, x - step)))
        return (h[0] - h[1]) / (2.0 * _VIEW_DERIVATIVE_STEP_RAD)

    return hx_sigmas, slope


class BendingPlaneUKF:
    """Online estimator of delta_L: filterpy's UKF with the project's measurement models.

    Parameters
    ----------
    catheter : Catheter
        Kinematic model (its markers are the rows of ``Observation.markers_b_mm``).
    settings : UKFSettings, optional
    name : str
        Name reported by the estimator interface.

    Notes
    -----
    The tip and the markers are fused as independent measurements (``Observation`` has no
    cross-covariance between them); a source that reports one segmented point both as the tip
    and as a marker must leave one of them out.
    """

    def __init__(
        self, catheter: Catheter, settings: UKFSettings | None = None, name: str = "ukf"
    ) -> None:
        self.catheter = catheter
        self.settings = UKFSettings() if settings is None else settings
        self.name = name
        s = self.settings
        n = s.state_dim
        self._n_markers = len(catheter.marker_arclengths_mm)
        points = _WrappedSigmaPoints(
            n, alpha=s.alpha, beta=s.beta, kappa=s.sigma_kappa, sqrt_method=sigma_sqrt
        )
        self._kf = _AngleUKF(
            dim_x=n,
            dim_z=3,
            dt=0.0,
            hx=None,
            fx=_fx_rate if s.include_rate else _fx_angle,
            points=points,
            sqrt_fn=sigma_sqrt,
            x_mean_fn=_state_mean,
            residual_x=_residual_x,
            state_add=_state_add,
        )
        self._min_information = s.uninformative_std_rad**-2
        self._max_variance = s.max_std_rad**2
        self.reset()

    # ------------------------------------------------------------------ public interface
    def reset(self) -> None:
        """Forget everything: the next informative frame initialises the filter again."""
        n = self.settings.state_dim
        self._kf.x = np.zeros(n)
        self._kf.P = np.eye(n) * self._max_variance
        self._initialised = False
        self._time_s: float | None = None
        self._rejected = 0
        self._consecutive_rejections = 0
        self._noise_scale = 1.0
        self._mismatch_scale = 1.0
        self._tip_fused_last_step = False
        self._good_x = self._kf.x.copy()
        self._good_P = self._kf.P.copy()
        self._prior_x = self._good_x.copy()
        self._prior_P = self._good_P.copy()

    @property
    def initialised(self) -> bool:
        """Whether the filter has a state (after its first informative frame)."""
        return self._initialised

    @property
    def state(self) -> Array:
        """Copy of the state: [delta_L] or [delta_L, delta_L_dot] (rad, rad/s)."""
        return self._kf.x.copy()

    @property
    def covariance(self) -> Array:
        """Copy of the state covariance."""
        return self._kf.P.copy()

    @property
    def noise_scale(self) -> float:
        """Current scale of the measurement covariances (1 unless ``estimate_noise``)."""
        return self._noise_scale

    def initialise(self, delta_L_rad: float, std_rad: float, time_s: float | None = None) -> None:
        """Start from a given prior instead of waiting for the first informative frame.

        Parameters
        ----------
        delta_L_rad, std_rad : float
            Prior mean and std of delta_L, rad (the std is capped at ``max_std_rad``).
        time_s : float, optional
            Time of the prior, s; the next step predicts from it.
        """
        if not (math.isfinite(delta_L_rad) and math.isfinite(std_rad) and std_rad > 0):
            raise ValueError(
                f"a prior needs a finite delta_L and a positive finite std, got {delta_L_rad},"
                f" {std_rad}"
            )
        self._start(float(delta_L_rad), float(std_rad))
        if time_s is not None:
            self._time_s = float(time_s)

    def step(self, observation: Observation) -> Estimate:
        """Consume one frame: predict to its time, then fuse what it measured.

        Raises
        ------
        ValueError
            For frames out of time order, non-finite time or joint values, marker arrays that
            do not match the catheter, or a measurement covariance that is not positive
            definite.
        """
        t = float(observation.time_s)
        if not math.isfinite(t):
            raise ValueError(f"observation time must be finite, got {observation.time_s}")
        if self._time_s is not None and t < self._time_s:
            raise ValueError(
                f"observations must arrive in time order: {t} s after {self._time_s} s"
            )
        q = np.asarray(observation.q, dtype=float)
        if q.shape != (3,):
            raise ValueError(f"observation.q must have shape (3,), got {q.shape}")
        q_dot = observation.q_dot
        # A finite difference whose other end the filter has just fused repeats that tip.
        repeats_fused_tip = (
            self.settings.velocity_is_finite_difference and self._tip_fused_last_step
        )
        self._tip_fused_last_step = False
        use_velocity = (
            self.settings.use_velocity
            and not repeats_fused_tip
            and observation.velocity_b_mm_s is not None
            and observation.velocity_cov_b is not None
            and _is_finite(q_dot)
            and _is_finite(observation.velocity_b_mm_s)
            and _is_finite(observation.velocity_cov_b)
        )
        # Catheter.shape_vectors validates q (finite, shape) with a clear ValueError.
        shape = self.catheter.shape_vectors(q, q_dot if use_velocity else None)
        dt = 0.0 if self._time_s is None else t - self._time_s
        self._time_s = t
        q_r = float(q[0])
        measurement = self._measurement(observation, shape, use_velocity)

        if not self._initialised:
            return self._try_first(t, q_r, measurement)

        flags = Flag.COVARIANCE_REPAIRED if self._predict(dt, q_dot) else Flag.NONE
        if measurement is None:
            return self._held(t, q_r, flags | Flag.NO_MEASUREMENT, _tip_radius(shape))
        if measurement.partial:
            flags |= Flag.PARTIAL
        if measurement.c_vectors is not None and (
            self._kf.P[0, 0] > self.settings.reacquire_std_rad**2
        ):
            return self._reacquire(t, q_r, measurement, flags)
        return self._update(t, q_r, measurement, flags)

    # ------------------------------------------------------------------ process model
    def _process_noise(self, dt: float, q_dot: Array | None) -> Array:
        s = self.settings
        intensity = s.process_noise_rad2_s
        if q_dot is not None and s.rotation_noise_gain_rad:
            rate = float(q_dot[0])
            if math.isfinite(rate):
                intensity += s.rotation_noise_gain_rad * abs(rate)
        if not s.include_rate:
            return np.array([[intensity * dt]])
        qa = s.rate_process_noise_rad2_s3
        return np.array(
            [
                [intensity * dt + qa * dt**3 / 3.0, qa * dt**2 / 2.0],
                [qa * dt**2 / 2.0, qa * dt],
            ]
        )

    def _predict(self, dt: float, q_dot: Array | None) -> bool:
        """filterpy's predict, then the std cap; True if the covariance had to be repaired."""
        kf = self._kf
        kf.Q = self._process_noise(dt, q_dot)
        repaired = False
        try:
            kf.predict(dt=dt, UT=_state_transform)
        except np.linalg.LinAlgError:
            # filterpy factorises P twice in predict (sigma points before and after).
            self._repair()
            kf.predict(dt=dt, UT=_state_transform)
            repaired = True
        P = kf.P
        if P.shape[0] > 1:
            P = kf.P = 0.5 * (P + P.T)
        if P[0, 0] > self._max_variance:
            f = math.sqrt(self._max_variance / P[0, 0])
            P[0, :] *= f
            P[:, 0] *= f
            # The update reuses predict's sigma points: draw them again from the capped P.
            kf.compute_process_sigmas(0.0)
        if not (math.isfinite(kf.x.sum()) and math.isfinite(P.sum())):
            self._repair()
            kf.predict(dt=0.0, UT=_state_transform)
            repaired = True
        self._prior_x = kf.x.copy()
        self._prior_P = kf.P.copy()
        return repaired

    def _repair(self) -> None:
        """Restore the last good state with a re-initialised (diagonal, capped) covariance."""
        diag = np.abs(np.diag(self._good_P))
        diag = np.where(np.isfinite(diag), diag, self._max_variance)
        diag[0] = min(max(diag[0], COVARIANCE_JITTER_FLOOR), self._max_variance)
        if diag.size > 1:
            diag[1:] = np.maximum(diag[1:], self.settings.initial_rate_std_rad_s**2)
        self._kf.x = self._good_x.copy()
        self._kf.P = np.diag(diag)

    # ------------------------------------------------------------------ measurements
    def _measurement(
        self, observation: Observation, shape: ShapeVectors, use_velocity: bool
    ) -> _Measurement | None:
        """Stack the usable 3-D data (or, without 3-D positions, the single views).

        The common case (everything given is finite) fills the stacked arrays directly; any
        missing or non-finite part goes through :meth:`_measurement_parts`.
        """
        tip = observation.tip_b_mm
        tip_cov = observation.tip_cov_b
        markers = observation.markers_b_mm
        markers_cov = observation.markers_cov_b
        if tip is None or tip_cov is None or (markers is None) != (markers_cov is None):
            return self._measurement_parts(observation, shape, use_velocity)
        n = 0
        if markers is not None:
            markers = np.asarray(markers, dtype=float)
            markers_cov = np.asarray(markers_cov, dtype=float)
            n = markers.shape[0]
            if markers.shape != (self._n_markers, 3) or markers_cov.shape not in (
                (n, 3, 3),
                (3 * n, 3 * n),
            ):
                return self._measurement_parts(observation, shape, use_velocity)
        rows = 1 + n + use_velocity
        y = np.empty((rows, 3))
        C = np.empty((rows, 3))
        R = np.zeros((3 * rows, 3 * rows))
        y[0] = tip
        C[0] = shape.c_tip_mm
        R[0:3, 0:3] = tip_cov
        if n:
            y[1 : 1 + n] = markers
            C[1 : 1 + n] = shape.c_markers_mm
            if markers_cov.ndim == 2:
                R[3 : 3 + 3 * n, 3 : 3 + 3 * n] = markers_cov
            else:
                for k in range(n):
                    R[3 + 3 * k : 6 + 3 * k, 3 + 3 * k : 6 + 3 * k] = markers_cov[k]
        if use_velocity:
            y[-1] = observation.velocity_b_mm_s
            C[-1] = shape.u_tip_mm_s
            R[-3:, -3:] = observation.velocity_cov_b
            if observation.velocity_tip_cov_b is not None:
                # cov(velocity, tip) fills the block below the tip's, and its transpose.
                R[-3:, 0:3] = observation.velocity_tip_cov_b
                R[0:3, -3:] = R[-3:, 0:3].T
        if not (np.isfinite(y).all() and np.isfinite(R).all()):
            return self._measurement_parts(observation, shape, use_velocity)
        return self._stacked(y, C, R, 1 + n, use_velocity, shape, partial=False, has_tip=True)

    def _stacked(self, y, C, R, positions, use_velocity, shape, partial, has_tip) -> _Measurement:
        """The measurement of stacked vectors y = Rz(q_r + delta_L) C (+ noise R)."""
        D = None
        if self.settings.include_rate and use_velocity:
            # A torsion rate turns the tip about z_b as well: v += delta_L_dot e_z x o_4_b.
            D = np.zeros_like(C)
            D[-1, 0] = -shape.c_tip_mm[1]
            D[-1, 1] = shape.c_tip_mm[0]
        cxy = C[:, 0] + 1j * C[:, 1]
        if positions:
            radius = math.sqrt(float(np.vdot(cxy[:positions], cxy[:positions]).real))
        else:
            radius = _tip_radius(shape)
        return _Measurement(
            z=y.ravel(),
            R=R,
            hx=_rotation_hx(cxy, C[:, 2], D, float(shape.q_r_rad)),
            slope=None,
            partial=partial,
            radius_mm=radius,
            y_vectors=y,
            c_vectors=C,
            has_tip=has_tip,
        )

    def _measurement_parts(
        self, observation: Observation, shape: ShapeVectors, use_velocity: bool
    ) -> _Measurement | None:
        """Stack what is usable when something is missing, NaN or given in another layout."""
        ys, cs, blocks = [], [], []
        partial = False
        has_tip = False
        tip = observation.tip_b_mm
        if tip is not None:
            tip = np.asarray(tip, dtype=float)
            tip_cov = observation.tip_cov_b
            if _is_finite(tip) and _is_finite(tip_cov):
                has_tip = True
                ys.append(tip.reshape(1, 3))
                cs.append(shape.c_tip_mm.reshape(1, 3))
                blocks.append(np.asarray(tip_cov, dtype=float))
            else:
                partial = True
        markers = observation.markers_b_mm
        if markers is not None and observation.markers_cov_b is not None:
            markers = np.asarray(markers, dtype=float)
            if markers.shape != (self._n_markers, 3):
                raise ValueError(
                    f"observation has markers of shape {markers.shape}, the catheter model has "
                    f"{self._n_markers} markers"
                )
            joint = observation.markers_joint_covariance()
            mask = np.isfinite(markers).all(axis=1)
            idx = np.repeat(mask, 3)
            cov = joint[np.ix_(idx, idx)]
            if mask.any() and np.isfinite(cov).all():
                ys.append(markers[mask])
                cs.append(shape.c_markers_mm[mask])
                blocks.append(cov)
            partial |= not (mask.all() and np.isfinite(cov).all())
        positions = sum(len(y) for y in ys)
        if positions == 0 and observation.views:
            return self._view_measurement(observation, shape)
        if use_velocity:
            ys.append(np.asarray(observation.velocity_b_mm_s, dtype=float).reshape(1, 3))
            cs.append(shape.u_tip_mm_s.reshape(1, 3))
            blocks.append(np.asarray(observation.velocity_cov_b, dtype=float))
        if not ys:
            return None
        y = np.concatenate(ys)
        C = np.concatenate(cs)
        R = _block_diagonal(blocks)
        if use_velocity and has_tip and observation.velocity_tip_cov_b is not None:
            cross = np.asarray(observation.velocity_tip_cov_b, dtype=float)
            if cross.shape != (3, 3):
                raise ValueError(
                    f"velocity_tip_cov_b must have shape (3, 3), got shape {cross.shape}"
                )
            if np.isfinite(cross).all():
                R[-3:, 0:3] = cross
                R[0:3, -3:] = cross.T
        return self._stacked(y, C, R, positions, use_velocity, shape, partial, has_tip)

    def _view_measurement(
        self, observation: Observation, shape: ShapeVectors
    ) -> _Measurement | None:
        views, zs, blocks = [], [], []
        partial = False
        radius_sq = 0.0
        for view in observation.views:
            uv = np.asarray(view.uv, dtype=float).reshape(-1, 2)
            cov = np.asarray(view.cov, dtype=float).reshape(-1, 2, 2)
            index = np.asarray(view.point_index, dtype=int).reshape(-1)
            if not (uv.shape[0] == cov.shape[0] == index.shape[0]):
                raise ValueError(
                    f"view measurement has {uv.shape[0]} points, {cov.shape[0]} covariances and "
                    f"{index.shape[0]} point indices"
                )
            if np.any(index < -1) or np.any(index >= self._n_markers):
                raise ValueError(
                    f"view point_index must be -1 (tip) or a marker in [0, {self._n_markers}),"
                    f" got {index.tolist()}"
                )
            ok = np.isfinite(uv).all(axis=1) & np.isfinite(cov).all(axis=(1, 2))
            partial |= not ok.all()
            if not ok.any():
                continue
            C = np.where((index[ok] < 0)[:, None], shape.c_tip_mm, shape.c_markers_mm[index[ok]])
            views.append((view, C))
            zs.append(uv[ok].ravel())
            blocks.extend(cov[ok])
            radius_sq += float(np.sum(C[:, :2] ** 2))
        if not views:
            return None
        hx, slope = _view_hx(views, float(shape.q_r_rad))
        return _Measurement(
            z=np.concatenate(zs),
            R=_block_diagonal(blocks),
            hx=hx,
            slope=slope,
            partial=partial,
            radius_mm=math.sqrt(radius_sq),
        )

    # ------------------------------------------------------------------ update and estimates
    def _update(self, t: float, q_r: float, measurement: _Measurement, flags: Flag) -> Estimate:
        """filterpy's update, then the informativeness check and the NIS gate."""
        kf = self._kf
        scale = self._noise_scale * self._mismatch_scale
        R = measurement.R if scale == 1.0 else measurement.R * scale
        try:
            nis = kf.update_sigmas(measurement.z, R, measurement.hx)
        except np.linalg.LinAlgError:
            self._restore_prior()
            _check_measurement_covariance(R)
            return self._held(t, q_r, flags | Flag.COVARIANCE_REPAIRED, measurement.radius_mm)
        # Fisher information of the frame at the prior mean; the first measurement sigma point
        # is h(prior mean), so the 3-D slope e_z x h costs no trigonometry.
        if measurement.slope is None:
            slope = _rotation_slope(kf.sigmas_h[0])
        else:
            slope = measurement.slope(self._prior_x)
        try:
            information = _fisher_information(slope, R)
        except CovarianceError:
            self._restore_prior()
            _check_measurement_covariance(R)
            raise
        if not information > self._min_information:
            self._restore_prior()
            return self._held(t, q_r, flags | Flag.UNINFORMATIVE, measurement.radius_mm)
        innovation = kf.y
        dof = innovation.size
        gate = gate_threshold(self.settings.gate_probability, dof)
        if self.settings.estimate_noise and math.isfinite(nis):
            self._adapt_noise(nis, dof, gate)
        if not nis <= gate:
            return self._reject(t, q_r, measurement, flags, innovation.copy(), nis, dof)
        self._consecutive_rejections = 0
        # A model-mismatch inflation fades once the data fit again (about 1 % per frame).
        self._mismatch_scale = 1.0 + MISMATCH_DECAY * (self._mismatch_scale - 1.0)
        P = kf.P
        if P.shape[0] > 1:
            P = kf.P = 0.5 * (P + P.T)
        if math.isfinite(kf.x.sum()) and math.isfinite(P.sum()) and P[0, 0] > 0:
            self._good_x = kf.x.copy()
            self._good_P = P.copy()
            self._tip_fused_last_step = measurement.has_tip
        else:
            self._restore_prior()
            flags |= Flag.COVARIANCE_REPAIRED | Flag.HELD
        return self._estimate(t, q_r, flags, measurement.radius_mm, innovation.copy(), nis, dof)

    def _reject(self, t, q_r, measurement, flags, innovation, nis, dof) -> Estimate:
        """Gate rejection: hold the prior; re-initialise after too many in a row."""
        self._restore_prior()
        self._consecutive_rejections += 1
        limit = self.settings.reacquire_after_rejections
        if limit and self._consecutive_rejections >= limit and measurement.c_vectors is not None:
            phi, std, consistent, misfit = self._closed_form(measurement)
            if consistent and std < self.settings.uninformative_std_rad:
                # The data agree with the model, only not with the prior: a torsion jump.
                return self._restart(t, q_r, phi, std, measurement, flags)
            if std * misfit < self.settings.uninformative_std_rad:
                return self._accept_mismatch(t, q_r, phi, std, misfit, measurement, flags)
        self._rejected += 1
        flags |= Flag.OUTLIER_REJECTED | Flag.HELD
        return self._estimate(t, q_r, flags, measurement.radius_mm, innovation, nis, dof)

    def _adapt_noise(self, nis: float, dof: int, gate: float) -> None:
        # NIS / dof estimates the ratio of the true to the assumed noise scale; clipping it at
        # the gate keeps one outlier from inflating the scale by more than a few percent, and
        # using rejected frames too lets a badly underestimated noise recover.
        ratio = min(nis, gate, 10.0 * dof) / dof
        lam = self.settings.noise_forgetting
        low, high = self.settings.noise_scale_bounds
        self._noise_scale = min(max(self._noise_scale * (lam + (1 - lam) * ratio), low), high)

    def _restore_prior(self) -> None:
        self._kf.x = self._prior_x.copy()
        self._kf.P = self._prior_P.copy()

    def _closed_form(self, measurement: _Measurement) -> tuple[float, float, bool, float]:
        """Global closed-form fit of the 3-D data: (phi, Fisher std, consistent, misfit).

        ``misfit`` is sqrt(cost / dof) clipped below at 1: the factor by which the noise would
        have to be larger for the data to fit the model.
        """
        R = measurement.R * (self._noise_scale * self._mismatch_scale)
        _check_measurement_covariance(R)
        W = spd_inverse(R)
        fit = fit_rotation_z(measurement.y_vectors, measurement.c_vectors, W)
        information = float(fit.fisher_information)
        std = 1.0 / math.sqrt(information) if information > 0 else math.inf
        # The minimised cost is chi-square with one degree of freedom fewer than the data.
        dof = max(measurement.z.size - 1, 1)
        cost = float(fit.cost)
        consistent = cost <= gate_threshold(self.settings.gate_probability, dof)
        return float(fit.phi_rad), std, consistent, math.sqrt(max(1.0, cost / dof))

    def _persistent_mismatch(self) -> bool:
        """True once ``reacquire_after_rejections`` frames in a row were inconsistent."""
        limit = self.settings.reacquire_after_rejections
        return bool(limit) and self._consecutive_rejections >= limit

    def _accept_mismatch(self, t, q_r, phi, std, misfit, measurement, flags) -> Estimate:
        """Data that stay inconsistent with the model frame after frame (contact deflection,
        a miscalibrated model) are not a passing outlier: restart from their closed form with
        the std inflated by the misfit, inflate the measurement noise by the same factor for
        the frames that follow, and say so, rather than refuse to answer."""
        self._mismatch_scale = min(self._mismatch_scale * misfit**2, MAX_MISMATCH_SCALE)
        return self._restart(
            t, q_r, phi, std * misfit, measurement, flags | Flag.MODEL_MISMATCH
        )

    def _try_first(self, t: float, q_r: float, measurement: _Measurement | None) -> Estimate:
        flags = Flag.NOT_INITIALISED
        if measurement is None:
            return self._invalid(t, q_r, flags | Flag.NO_MEASUREMENT, 0.0)
        if measurement.c_vectors is None:
            # A single view leaves a mirror ambiguity: it updates a filter, never starts one.
            return self._invalid(t, q_r, flags | Flag.UNINFORMATIVE, measurement.radius_mm)
        phi, std, consistent, misfit = self._closed_form(measurement)
        if not std < self.settings.uninformative_std_rad:
            return self._invalid(t, q_r, flags | Flag.UNINFORMATIVE, measurement.radius_mm)
        partial = Flag.PARTIAL if measurement.partial else Flag.NONE
        if not consistent:
            self._consecutive_rejections += 1
            if self._persistent_mismatch() and std * misfit < self.settings.uninformative_std_rad:
                return self._accept_mismatch(t, q_r, phi, std, misfit, measurement, partial)
            self._rejected += 1
            return self._invalid(t, q_r, flags | Flag.OUTLIER_REJECTED, measurement.radius_mm)
        return self._restart(t, q_r, phi, std, measurement, partial)

    def _reacquire(self, t: float, q_r: float, measurement: _Measurement, flags: Flag) -> Estimate:
        """Re-initialise from the closed form when the prior carries (almost) nothing."""
        phi, std, consistent, misfit = self._closed_form(measurement)
        if not std < self.settings.uninformative_std_rad:
            return self._held(t, q_r, flags | Flag.UNINFORMATIVE, measurement.radius_mm)
        if not consistent:
            self._consecutive_rejections += 1
            if self._persistent_mismatch() and std * misfit < self.settings.uninformative_std_rad:
                return self._accept_mismatch(t, q_r, phi, std, misfit, measurement, flags)
            self._rejected += 1
            return self._held(t, q_r, flags | Flag.OUTLIER_REJECTED, measurement.radius_mm)
        return self._restart(t, q_r, phi, std, measurement, flags)

    def _restart(self, t, q_r, phi, std, measurement: _Measurement, flags: Flag) -> Estimate:
        if self.settings.initial_std_rad is not None:
            std = max(std, self.settings.initial_std_rad)
        self._start(_wrap_scalar(phi - q_r), std)
        self._consecutive_rejections = 0
        self._tip_fused_last_step = measurement.has_tip
        return self._estimate(t, q_r, flags, measurement.radius_mm, None, None, 0)

    def _start(self, delta_L_rad: float, std_rad: float) -> None:
        s = self.settings
        n = s.state_dim
        x = np.zeros(n)
        x[0] = _wrap_scalar(delta_L_rad)
        P = np.zeros((n, n))
        P[0, 0] = min(std_rad**2, self._max_variance)
        if n > 1:
            P[1, 1] = s.initial_rate_std_rad_s**2
        self._kf.x = x
        self._kf.P = P
        self._good_x, self._good_P = x.copy(), P.copy()
        self._prior_x, self._prior_P = x.copy(), P.copy()
        self._initialised = True

    def _held(self, t: float, q_r: float, flags: Flag, radius_mm: float) -> Estimate:
        return self._estimate(t, q_r, flags | Flag.HELD, radius_mm, None, None, 0)

    def _estimate(self, t, q_r, flags, radius_mm, innovation, nis, dof) -> Estimate:
        return Estimate(
            time_s=t,
            delta_L_rad=_wrap_scalar(float(self._kf.x[0])),
            std_rad=math.sqrt(float(self._kf.P[0, 0])),
            q_r_rad=q_r,
            flags=flags,
            informative_radius_mm=radius_mm,
            innovation=innovation,
            nis=nis,
            nis_dof=dof,
            rejected_outliers=self._rejected,
        )

    def _invalid(self, t: float, q_r: float, flags: Flag, radius_mm: float) -> Estimate:
        return Estimate(
            time_s=t,
            delta_L_rad=math.nan,
            std_rad=math.nan,
            q_r_rad=q_r,
            flags=flags,
            informative_radius_mm=radius_mm,
            rejected_outliers=self._rejected,
        )


def _fx_angle(sigmas: Array, dt: float) -> Array:
    """Random walk: the sigma points stay, the process noise widens them. (k, 1) -> (k, 1)."""
    return sigmas


def _fx_rate(sigmas: Array, dt: float) -> Array:
    """delta_L integrates its rate; the rate is a random walk. (k, 2) -> (k, 2)."""
    out = sigmas.copy()
    out[:, 0] = (sigmas[:, 0] + dt * sigmas[:, 1] + math.pi) % _TWO_PI - math.pi
    return out


def _tip_radius(shape: ShapeVectors) -> float:
    return math.hypot(float(shape.c_tip_mm[0]), float(shape.c_tip_mm[1]))


def _block_diagonal(blocks: list[Array]) -> Array:
    if len(blocks) == 1:
        return np.array(blocks[0], dtype=float)
    sizes = [b.shape[0] for b in blocks]
    out = np.zeros((sum(sizes), sum(sizes)))
    i = 0
    for b, k in zip(blocks, sizes, strict=True):
        out[i : i + k, i : i + k] = b
        i += k
    return out


def _check_measurement_covariance(R: Array) -> None:
    """ValueError naming the problem if a frame's measurement covariance is not usable."""
    try:
        _cholesky_lower(R)
    except CovarianceError as exc:
        raise ValueError(
            "measurement covariance of the frame is not positive definite (or not finite): "
            "check tip_cov_b, markers_cov_b, velocity_cov_b, velocity_tip_cov_b or the view "
            "covariances"
        ) from exc


def _fisher_information(slope: Array, R: Array) -> float:
    """slope^T R^-1 slope by a Cholesky solve (CovarianceError if R is not PD)."""
    c = _cholesky_lower(R)
    w, info = lapack.dpotrs(c, slope, lower=1)
    if info != 0:
        raise CovarianceError("measurement covariance could not be factorised")
    return float(slope @ w)


__all__ = [
    "BendingPlaneUKF",
    "CovarianceError",
    "UKFSettings",
    "gate_threshold",
]
