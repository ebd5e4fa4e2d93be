"""Settings of the bending-plane filters (the UKF and the grid filter share the models)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from scipy.stats import chi2

from tracker.estimators.per_frame import UNINFORMATIVE_STD_RAD


@lru_cache(maxsize=256)
def gate_threshold(probability: float, dof: int) -> float:
    """Chi-square quantile of a consistency gate (inf when the gate is off)."""
    if probability >= 1.0:
        return math.inf
    return float(chi2.ppf(probability, dof))


@dataclass(frozen=True)
class UKFSettings:
    """Settings of :class:`~tracker.estimators.ukf.BendingPlaneUKF` (validated on construction).

    The process and measurement settings (the first three groups) are also those of the grid
    filter (:class:`~tracker.estimators.grid.GridFilter`).

    Process model
    -------------
    process_noise_rad2_s : float
        Random-walk intensity of delta_L with the base still, rad^2/s.
    rotation_noise_gain_rad : float
        Extra variance of delta_L per rad the base turns, rad^2/rad (torsion winds up and
        unwinds while the base turns, by up to the turn itself).
    jump_rate_per_s, jump_per_rad : float
        Probability rate of a torsion jump to anywhere on the circle, per second and per rad
        the base turns. A jump hypothesis is only ever weighed against the held estimate
        with this prior: with the base still, torsion does not jump.
    include_rate : bool
        State ``[delta_L, delta_L_dot]`` instead of ``[delta_L]`` (UKF only); the rate is a
        random walk of intensity ``rate_process_noise_rad2_s3`` and enters the velocity model.
    rate_process_noise_rad2_s3, initial_rate_std_rad_s : float
        Its intensity (rad^2/s^3) and initial std (rad/s).

    Measurement model
    -----------------
    outlier_probability : float
        Probability that a measured group (tip, one marker, velocity) is a gross error; such a
        group is drawn from the noise widened ``outlier_scale`` times. 0: Gaussian, no
        rejection.
    outlier_scale : float
        That widening, > 1.
    joint_error_mm : float
        Prior std of the joint-equivalent deviation dq of each bending joint, mm: the shape
        errs as if the joints were off by this much (contact, calibration). dq is part of
        the state (estimated online); 0 together with ``gain_error = 0``: no such state.
    gain_error : float
        Relative error of the bending gain (the modal matrices); adds ``gain_error * q`` to
        the prior std of the deviation of each joint.
    deviation_length_mm : float
        Joint travel over which the deviation decorrelates, mm.
    deviation_rate_per_s : float
        Rate at which it decorrelates while the joints hold, 1/s (a contact made or released).
    joint_error_white_mm : float
        Joint-equivalent model error that changes from frame to frame, mm.
    velocity_relative_error : float
        Relative model error of the tip velocity.
    use_velocity : bool
        Fuse the tip velocity when the observation has one.
    velocity_is_finite_difference : bool
        The velocity is ``(tip_t - tip_{t-1}) / dt``: decorrelated from this frame's tip it
        measures the previous tip, so it is fused only after a step that did not fuse a tip
        (else that tip counts twice). False: a velocity with independent noise, fused
        whenever present.

    Filter rules
    ------------
    gate_probability : float
        Chi-square quantile at which a frame's global closed-form fit counts as consistent
        (for a start, restart or jump hypothesis), in (0, 1]; 1: always consistent.
    uninformative_std_rad : float
        A frame whose information (noise and model error) gives a std above this is
        uninformative: it updates nothing and starts nothing.
    min_sign_evidence : float
        A frame starts or restarts the filter only if its best fit beats every fit on the
        opposite half circle by this much (chi-square units): a nearly straight catheter,
        relative to noise plus model error, cannot tell a plane from its opposite.
    initial_std_rad : float or None
        Std to start with (at least the frame's Fisher std); None: the Fisher std.
    max_std_rad : float
        Cap on the predicted std of delta_L, rad; ``max_std_rad * sqrt(alpha^2 (n + kappa))``
        must stay below pi so that wrapped sigma-point residuals are unambiguous.
    reacquire_std_rad : float
        Above this predicted std the prior carries almost nothing: an informative frame
        restarts the filter from its closed form instead of updating it.
    reacquire_after_rejections : int
        After this many consecutive frames rejected as a whole whose closed form is
        informative but inconsistent, accept the mismatch: restart with the std and the
        noise inflated by the misfit (``Flag.MODEL_MISMATCH``); 0 never does.
    max_hypotheses : int
        Hypotheses carried at once (held and restarted), >= 1.
    hypothesis_floor : float
        A hypothesis whose weight falls below this is dropped.
    alpha, beta, kappa : float
        Van der Merwe's sigma-point parameters; ``kappa=None`` means ``3 - n``.
    estimate_noise : bool
        Estimate a scale of the noise covariances online from the NIS (forgetting factor
        ``noise_forgetting``), for a segmentation noise that is not known well.
    noise_forgetting : float
        Its forgetting factor, in (0, 1).
    noise_scale_bounds : tuple of float
        Limits of the estimated scale.
    """

    process_noise_rad2_s: float = 1e-6
    rotation_noise_gain_rad: float = 0.3
    jump_rate_per_s: float = 1e-3
    jump_per_rad: float = 0.05
    include_rate: bool = False
    rate_process_noise_rad2_s3: float = 1e-3
    initial_rate_std_rad_s: float = 0.1
    outlier_probability: float = 0.02
    outlier_scale: float = 30.0
    joint_error_mm: float = 0.1
    gain_error: float = 0.05
    deviation_length_mm: float = 1.0
    deviation_rate_per_s: float = 0.5
    joint_error_white_mm: float = 0.01
    velocity_relative_error: float = 0.1
    use_velocity: bool = True
    velocity_is_finite_difference: bool = True
    gate_probability: float = 0.9999
    uninformative_std_rad: float = UNINFORMATIVE_STD_RAD
    min_sign_evidence: float = 16.0
    initial_std_rad: float | None = None
    max_std_rad: float = 1.8
    reacquire_std_rad: float = 0.5
    reacquire_after_rejections: int = 3
    max_hypotheses: int = 2
    hypothesis_floor: float = 1e-6
    alpha: float = 1.0
    beta: float = 2.0
    kappa: float | None = None
    estimate_noise: bool = False
    noise_forgetting: float = 0.98
    noise_scale_bounds: tuple[float, float] = (1e-3, 1e3)

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, requirement: str) -> None:
            if not ok:
                value = getattr(self, name)
                raise ValueError(f"UKFSettings.{name} must be {requirement}, got {value}")

        def finite(name: str, low: float = 0.0, allow_low: bool = True) -> None:
            value = getattr(self, name)
            ok = math.isfinite(value) and (value >= low if allow_low else value > low)
            check(name, ok, f"finite and {'>=' if allow_low else '>'} {low}")

        for name in (
            "process_noise_rad2_s", "rotation_noise_gain_rad", "jump_rate_per_s", "jump_per_rad",
            "rate_process_noise_rad2_s3", "joint_error_mm", "gain_error",
            "joint_error_white_mm", "velocity_relative_error", "min_sign_evidence", "beta",
            "deviation_rate_per_s",
        ):  # fmt: skip
            finite(name)
        for name in (
            "initial_rate_std_rad_s", "uninformative_std_rad", "max_std_rad",
            "reacquire_std_rad", "alpha", "deviation_length_mm",
        ):  # fmt: skip
            finite(name, allow_low=False)
        finite("outlier_scale", 1.0, allow_low=False)
        if self.initial_std_rad is not None:
            finite("initial_std_rad", allow_low=False)
        check("outlier_probability", 0.0 <= self.outlier_probability < 1.0, "in [0, 1)")
        check("gate_probability", 0.0 < self.gate_probability <= 1.0, "in (0, 1]")
        check("hypothesis_floor", 0.0 <= self.hypothesis_floor < 1.0, "in [0, 1)")
        check("noise_forgetting", 0.0 < self.noise_forgetting < 1.0, "in (0, 1)")
        for name, low in (("reacquire_after_rejections", 0), ("max_hypotheses", 1)):
            value = getattr(self, name)
            check(name, int(value) == value and value >= low, f"an integer >= {low}")
        object.__setattr__(self, "noise_scale_bounds", tuple(self.noise_scale_bounds))
        check("noise_scale_bounds", len(self.noise_scale_bounds) == 2, "(low, high)")
        low, high = self.noise_scale_bounds
        check("noise_scale_bounds", 0.0 < low <= 1.0 <= high < math.inf,
              "0 < low <= 1 <= high < inf")  # fmt: skip
        for name in ("uninformative_std_rad", "reacquire_std_rad"):
            check(name, getattr(self, name) <= self.max_std_rad,
                  f"<= max_std_rad ({self.max_std_rad})")  # fmt: skip
        n = self.state_dim
        spread = self.alpha**2 * (n + self.sigma_kappa)
        if spread <= 0:
            raise ValueError(
                f"UKFSettings: alpha^2 (n + kappa) must be > 0, got alpha={self.alpha}, "
                f"kappa={self.sigma_kappa}, n={n}"
            )
        scale = math.sqrt(spread)
        if self.max_std_rad * scale >= math.pi:
            raise ValueError(
                f"UKFSettings.max_std_rad={self.max_std_rad} puts sigma points "
                f"{self.max_std_rad * scale:.3f} rad from the mean, beyond pi, where a wrapped "
                f"residual is ambiguous; use max_std_rad < {math.pi / scale:.3f}"
            )

    @property
    def estimates_deviation(self) -> bool:
        """Whether the state carries the joint-equivalent deviation (dq_p, dq_d)."""
        return self.joint_error_mm > 0 or self.gain_error > 0

    @property
    def state_dim(self) -> int:
        """Dimension of the UKF state: delta_L, then the rate (``include_rate``), then the
        deviation (dq_p, dq_d) (``estimates_deviation``)."""
        return 1 + int(self.include_rate) + 2 * int(self.estimates_deviation)

    @property
    def sigma_kappa(self) -> float:
        """The kappa actually used (``3 - n`` when ``kappa`` is None)."""
        return float(3 - self.state_dim) if self.kappa is None else float(self.kappa)


__all__ = ["UKFSettings", "gate_threshold"]
