"""What an estimator consumes per frame, and what it returns.

An :class:`Observation` holds the joint values at the frame's time and the reconstructed
measurements relative to the catheter base, expressed in {B}, each with its noise covariance
propagated from the segmentation noise (models.imaging). Missing measurements are ``None``;
a marker that was not segmented is a row of NaN in ``markers_b_mm``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from models.bounds import block_diagonal

Array = np.ndarray


class Flag(enum.Flag):
    """What happened in one estimator step."""

    NONE = 0
    NO_MEASUREMENT = enum.auto()  # nothing usable in the frame: predict only / no estimate
    UNINFORMATIVE = enum.auto()  # the configuration is near straight: delta_L not observable
    HELD = enum.auto()  # the estimate was held from before (UKF predict-only)
    OUTLIER_REJECTED = enum.auto()  # the NIS gate rejected the measurement
    PARTIAL = enum.auto()  # some markers or one view missing, the rest was used
    NOT_INITIALISED = enum.auto()  # the UKF has not seen an informative frame yet
    COVARIANCE_REPAIRED = enum.auto()  # a non-positive-definite covariance was repaired
    NOT_CONVERGED = enum.auto()  # the least-squares baseline did not report convergence
    MODEL_MISMATCH = enum.auto()  # data persistently inconsistent with the model (e.g. contact
    # deflection): accepted with its covariance inflated to the observed misfit
    INVALID_INPUT = enum.auto()  # the observation failed the input checks: skipped, the
    # estimate held (tracker.estimators.checks)


@dataclass(frozen=True)
class ViewMeasurement:
    """Points segmented in one view, for updates when the two views are not synchronised.

    Parameters
    ----------
    view : models.imaging.OrthographicPlane or PinholeView
        Anything with ``project(points_w) -> (..., 2)``.
    R_w_b, o_b_w_mm : arrays (3, 3), (3,)
        Registered base pose in the world frame.
    uv : array, shape (n, 2)
        Segmented image points (mm in the plane, or px).
    cov : array, shape (n, 2, 2)
        Their segmentation-noise covariances.
    point_index : array of int, shape (n,)
        Which point each row is: -1 for the tip, k >= 0 for the catheter's marker k.
    """

    view: object
    R_w_b: Array
    o_b_w_mm: Array
    uv: Array
    cov: Array
    point_index: Array


def _all_finite(values) -> bool:
    """Whether every number of a small array is finite (in floats: numpy's reductions cost
    five times as much on a few numbers, every frame)."""
    return all(map(math.isfinite, np.asarray(values, dtype=float).ravel().tolist()))


@dataclass(frozen=True)
class Observation:
    """Measurements of one frame relative to the base, in {B}.

    Parameters
    ----------
    time_s : float
        Frame time, s.
    q : array, shape (3,)
        Joint values (q_r [rad], q_p [mm], q_d [mm]) interpolated to ``time_s``.
    q_dot : array, shape (3,), optional
        Joint rates (rad/s, mm/s, mm/s).
    tip_b_mm, tip_cov_b : arrays (3,), (3, 3), optional
        Reconstructed tip relative to the base and its covariance, mm, mm^2.
    markers_b_mm : array, shape (n, 3), optional
        Reconstructed backbone markers (the catheter's marker arclengths, in order); NaN rows
        for markers that were not found.
    markers_cov_b : array, shape (n, 3, 3) or (3n, 3n), optional
        Per-marker or joint covariance, mm^2.
    velocity_b_mm_s, velocity_cov_b : arrays (3,), (3, 3), optional
        Finite-difference tip velocity and its covariance, mm/s, mm^2/s^2.
    velocity_tip_cov_b : array, shape (3, 3), optional
        Cross-covariance cov(velocity noise, tip noise), mm^2/s: a finite difference
        (p_t - p_{t-1}) / dt is correlated with the p_t it was made from. It also repeats the
        noise of p_{t-1}: a filter that already fused p_{t-1} would count it twice, which is
        why the UKF fuses such a velocity only after a frame whose tip it did not use
        (``UKFSettings.velocity_is_finite_difference``).
    views : tuple of ViewMeasurement
        Single-view measurements (used by the UKF when the views are not synchronised).
    """

    time_s: float
    q: Array
    q_dot: Array | None = None
    tip_b_mm: Array | None = None
    tip_cov_b: Array | None = None
    markers_b_mm: Array | None = None
    markers_cov_b: Array | None = None
    velocity_b_mm_s: Array | None = None
    velocity_cov_b: Array | None = None
    velocity_tip_cov_b: Array | None = None
    views: tuple[ViewMeasurement, ...] = ()

    def has_tip(self) -> bool:
        return (
            self.tip_b_mm is not None
            and self.tip_cov_b is not None
            and _all_finite(self.tip_b_mm)
            and _all_finite(self.tip_cov_b)
        )

    def has_velocity(self) -> bool:
        return (
            self.velocity_b_mm_s is not None
            and self.velocity_cov_b is not None
            and self.q_dot is not None
            and _all_finite(self.velocity_b_mm_s)
            and _all_finite(self.velocity_cov_b)
            and _all_finite(self.q_dot)
        )

    def marker_mask(self) -> Array:
        """Boolean (n,) of markers present (finite position), empty if there are none."""
        if self.markers_b_mm is None or self.markers_cov_b is None:
            return np.zeros(0, dtype=bool)
        markers = np.asarray(self.markers_b_mm, dtype=float)
        if markers.ndim != 2:
            return np.all(np.isfinite(markers), axis=-1)
        # In floats, as _all_finite: a few rows every frame.
        return np.array([all(map(math.isfinite, row)) for row in markers.tolist()], dtype=bool)

    def markers_joint_covariance(self) -> Array:
        """The joint (3n, 3n) covariance of all markers, mm^2."""
        cov = np.asarray(self.markers_cov_b, dtype=float)
        n = np.asarray(self.markers_b_mm).shape[0]
        if cov.shape == (n, 3, 3):
            return block_diagonal(cov)
        if cov.shape == (3 * n, 3 * n):
            return cov
        raise ValueError(
            f"markers_cov_b must have shape ({n}, 3, 3) or ({3 * n}, {3 * n}), got {cov.shape}"
        )


def velocity_from_positions(
    tip_now_b: Array, cov_now: Array, tip_before_b: Array, cov_before: Array, dt_s
) -> tuple[Array, Array, Array]:
    """Finite-difference tip velocity, its covariance, and its cross-covariance with ``tip_now``.

    ``v = (p_t - p_{t-1}) / dt``, ``cov(v) = (S_t + S_{t-1}) / dt^2`` (independent noise in
    the two frames) and ``cov(v, p_t) = S_t / dt``. This is the one finite-difference rule:
    the Reconstructor, the batched UKF (``finite_difference_velocity``) and the studies call
    it, one frame or many at once.

    Parameters
    ----------
    tip_now_b, tip_before_b : arrays, shape (..., 3)
        Tip in {B} at the frame and at the frame before, mm.
    cov_now, cov_before : arrays, shape (..., 3, 3)
        Their covariances, mm^2.
    dt_s : float or array, shape (...)
        Time between the two frames, s; positive and finite.

    Returns
    -------
    velocity_b_mm_s : array, shape (..., 3)
        mm/s.
    velocity_cov_b, velocity_tip_cov_b : arrays, shape (..., 3, 3)
        Covariance of the velocity (mm^2/s^2) and its cross-covariance with ``tip_now_b``
        (mm^2/s).
    """
    dt = np.asarray(dt_s, dtype=float)
    bad = ~(np.isfinite(dt) & (dt > 0))
    if bad.any():
        raise ValueError(f"frame interval must be positive and finite, got {dt[bad].flat[0]} s")
    cov_now = np.asarray(cov_now, dtype=float)
    tip_now_b, tip_before_b = np.asarray(tip_now_b, float), np.asarray(tip_before_b, float)
    v = (tip_now_b - tip_before_b) / dt[..., None]
    cov_v = (cov_now + np.asarray(cov_before, dtype=float)) / (dt**2)[..., None, None]
    return v, cov_v, cov_now / dt[..., None, None]


@dataclass(frozen=True)
class Estimate:
    """One estimator step's result.

    ``delta_L_rad`` and ``std_rad`` are finite whenever ``valid``; an invalid step (no
    measurement and nothing to hold) carries NaN together with a flag saying why.
    """

    time_s: float
    delta_L_rad: float
    std_rad: float
    q_r_rad: float
    flags: Flag = Flag.NONE
    informative_radius_mm: float = 0.0
    innovation: Array | None = None
    nis: float | None = None
    nis_dof: int = 0
    rejected_outliers: int = 0

    @property
    def delta_1_rad(self) -> float:
        """Bending-plane angle q_r + delta_L wrapped to [-pi, pi)."""
        return float(np.mod(self.q_r_rad + self.delta_L_rad + np.pi, 2 * np.pi) - np.pi)

    @property
    def valid(self) -> bool:
        return bool(np.isfinite(self.delta_L_rad) and np.isfinite(self.std_rad))


@dataclass(frozen=True)
class Frame:
    """One synchronised frame of every view of the rig.

    Parameters
    ----------
    time_s : float
        Image time stamp, s.
    q, q_dot : arrays (3,)
        Joint values and rates interpolated to ``time_s``.
    uv : tuple of arrays (1 + n_markers, 2)
        Segmented image points of each view, in the rig's view order (``rig.names``): rows
        ``[tip, marker_0, ...]`` in the catheter's marker order; mm in the plane
        (orthographic) or px (pinhole); NaN rows for points not found.
    cov : tuple of arrays (1 + n_markers, 2, 2)
        Segmentation-noise covariances of those points, one array per view.
    images : tuple of arrays, optional
        The grayscale images of the views, when the source has them.
    delta_L_true_rad : float, optional
        Ground truth, where known (simulation, phantom with a tracker).
    """

    time_s: float
    q: Array
    q_dot: Array | None
    uv: tuple[Array, ...]
    cov: tuple[Array, ...]
    images: tuple[Array, ...] | None = None
    delta_L_true_rad: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.uv, np.ndarray) or isinstance(self.cov, np.ndarray):
            raise TypeError("Frame uv and cov are sequences with one array per view")
        uv, cov = tuple(self.uv), tuple(self.cov)
        if len(uv) != len(cov) or len(uv) < 2:
            raise ValueError(
                f"a frame needs image points and covariances of two or more views, got"
                f" {len(uv)} and {len(cov)}"
            )
        object.__setattr__(self, "uv", uv)
        object.__setattr__(self, "cov", cov)
        if self.images is not None:
            object.__setattr__(self, "images", tuple(self.images))

    @property
    def n_views(self) -> int:
        return len(self.uv)

