"""Many independent bending-plane UKFs at once, batched over trials (for Monte Carlo studies).

:func:`run_ukf_batch` runs ``B`` independent copies of
:class:`~tracker.estimators.ukf.BendingPlaneUKF` (one per trial) over ``T`` frames with numpy
over the trial axis instead of a Python loop of filter steps: the sensitivity studies step
hundreds of study points x hundreds of trials x tens of frames.

It is the same filter, not an approximation of it: both step a
:class:`~tracker.estimators.ukf_core.FilterBank`, where the rules (gate, restart, mismatch,
repair) are written once, and both build each frame's measurement groups with
:func:`~tracker.estimators.measurement.assemble_expanded` from the same
:class:`~tracker.estimators.deviation.ShapeExpansion`. Only the order of floating-point
sums over the trial axis can differ (tests/tracker/test_ukf_batch.py requires 1e-9 rad and
identical flags). Missing data are NaN (a tip, a marker, a velocity); single-view
measurements are the live filter's only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.catheter import Catheter
from tracker.estimators.deviation import ShapeExpansion
from tracker.estimators.measurement import assemble_expanded
from tracker.estimators.ukf_core import FilterBank
from tracker.estimators.ukf_settings import UKFSettings
from tracker.types import Flag, velocity_from_positions

Array = np.ndarray


@dataclass(frozen=True)
class UKFBatchResult:
    """Every trial's estimate after every frame, as :class:`tracker.types.Estimate` says it.

    Attributes
    ----------
    delta_L_rad, std_rad : array, shape (B, T)
        Estimate of delta_L and its std, rad; NaN before the filter of the trial has started.
    flags : array of int, shape (B, T)
        :class:`tracker.types.Flag` values (``Flag(int(flags[b, t]))``).
    nis : array, shape (B, T)
        Normalised innovation squared of an update; NaN otherwise.
    nis_dof : array of int, shape (B, T)
        Its degrees of freedom (the fused measurement dimension); 0 without an innovation.
    rejected_outliers : array of int, shape (B, T)
        Rejected measurement groups counted so far.
    """

    delta_L_rad: Array
    std_rad: Array
    flags: Array
    nis: Array
    nis_dof: Array
    rejected_outliers: Array

    @property
    def valid(self) -> Array:
        """Boolean (B, T): the step gave an estimate (finite delta_L and std)."""
        return np.isfinite(self.delta_L_rad) & np.isfinite(self.std_rad)

    def flag(self, trial: int, frame: int) -> Flag:
        """The flags of one step as a :class:`~tracker.types.Flag`."""
        return Flag(int(self.flags[trial, frame]))


def finite_difference_velocity(
    time_s: Array, tip_b_mm: Array, tip_cov_b: Array
) -> tuple[Array, Array, Array]:
    """Every frame's finite-difference tip velocity, as the Reconstructor makes it.

    Frame k > 0 gets :func:`tracker.types.velocity_from_positions` of the tips of frames
    k and k - 1; frame 0 has none (NaN).

    Parameters
    ----------
    time_s : array, shape (T,) or (B, T)
        Frame times, s (strictly increasing).
    tip_b_mm : array, shape (B, T, 3)
        Measured tips in {B}, mm.
    tip_cov_b : array, broadcastable to (B, T, 3, 3)
        Their covariances, mm^2.

    Returns
    -------
    velocity_b_mm_s : array, shape (B, T, 3)
        mm/s.
    velocity_cov_b, velocity_tip_cov_b : arrays, shape (B', T, 3, 3)
        Covariance of the velocity (mm^2/s^2) and cross-covariance with the tip of the same
        frame (mm^2/s); ``B'`` is 1 when ``tip_cov_b`` is the same for every trial.
    """
    tip = np.asarray(tip_b_mm, dtype=float)
    if tip.ndim != 3 or tip.shape[-1] != 3:
        raise ValueError(f"tip_b_mm must have shape (B, T, 3), got {tip.shape}")
    n, frames = tip.shape[:2]
    time = np.asarray(time_s, dtype=float)
    shared_time = time.ndim == 1 or time.shape[0] == 1
    dt = np.diff(_broadcast(time, (n, frames), "time_s"), axis=1)
    cov = np.asarray(tip_cov_b, dtype=float)
    cov = cov.reshape((1,) * (4 - cov.ndim) + cov.shape)
    # One covariance per frame for every trial when neither the noise nor the times vary.
    n_cov = 1 if cov.shape[0] == 1 and shared_time else n
    cov = _broadcast(cov, (n_cov, frames, 3, 3), "tip_cov_b")
    velocity = np.full((n, frames, 3), np.nan)
    cov_v = np.full(cov.shape, np.nan)
    cross = np.full(cov.shape, np.nan)
    # With one covariance for every trial the times are shared too: dt[:1] is every trial's.
    velocity[:, 1:], cov_v[:, 1:], cross[:, 1:] = velocity_from_positions(
        tip[:, 1:], cov[:, 1:], tip[:, :-1], cov[:, :-1], dt[:n_cov]
    )
    return velocity, cov_v, cross


def run_ukf_batch(
    catheter: Catheter,
    settings: UKFSettings,
    time_s: Array,
    q: Array,
    q_dot: Array | None,
    tip_b_mm: Array,
    tip_cov_b: Array,
    markers_b_mm: Array | None = None,
    markers_cov_b: Array | None = None,
    velocity_b_mm_s: Array | None = None,
    velocity_cov_b: Array | None = None,
    velocity_tip_cov_b: Array | None = None,
) -> UKFBatchResult:
    """Run B independent UKFs, each from its reset state, over T frames of 3-D data.

    Trial b gives the estimates ``BendingPlaneUKF(catheter, settings)`` gives for the
    observations ``Observation(time_s[b, k], q[b, k], q_dot[b, k], tip_b_mm[b, k], ...)``,
    k = 0 .. T-1. Arguments shared by every trial may leave out the trial axis (``time_s``
    (T,), ``q`` (T, 3)) or have it of length 1.

    Parameters
    ----------
    catheter : Catheter
    settings : UKFSettings
    time_s : array, shape (B, T) or (T,)
        Frame times, s, non-decreasing per trial.
    q, q_dot : arrays, shape (B, T, 3) or (T, 3)
        Joint values (rad, mm, mm) and rates (rad/s, mm/s, mm/s); ``q_dot`` may be None or
        contain NaN (no rates: no velocity in that frame).
    tip_b_mm : array, shape (B, T, 3)
        Measured tips in {B}, mm; NaN: not measured.
    tip_cov_b : array, broadcastable to (B, T, 3, 3)
        Their covariances, mm^2.
    markers_b_mm : array, shape (B, T, n_markers, 3), optional
        The catheter's markers, in order, mm; NaN rows: not found.
    markers_cov_b : array, broadcastable to (B, T, n_markers, 3, 3), optional
        Per-marker covariances, mm^2.
    velocity_b_mm_s : array, shape (B, T, 3), optional
        Tip velocities, mm/s; a non-finite row is a frame without velocity.
    velocity_cov_b, velocity_tip_cov_b : arrays, broadcastable to (B, T, 3, 3), optional
        Covariance of the velocity (mm^2/s^2) and its cross-covariance with the tip (mm^2/s;
        non-finite or None: none).

    Returns
    -------
    UKFBatchResult
        Per trial and frame.

    Raises
    ------
    ValueError
        For data of the wrong shape, frames out of time order, a non-finite time or joint
        value, or a measurement covariance that is not positive definite.
    """
    tip = np.asarray(tip_b_mm, dtype=float)
    if tip.ndim != 3 or tip.shape[-1] != 3:
        raise ValueError(f"tip_b_mm must have shape (B, T, 3), got {tip.shape}")
    n, frames = tip.shape[:2]
    time = _broadcast(time_s, (n, frames), "time_s")
    if not np.isfinite(time).all():
        raise ValueError("observation times must be finite")
    if np.any(np.diff(time, axis=1) < 0):
        raise ValueError("observations must arrive in time order")
    q = np.asarray(q, dtype=float)
    if q.shape[-1:] != (3,) or q.ndim not in (2, 3):
        raise ValueError(f"q must have shape (B, T, 3) or (T, 3), got {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError("joint values must be finite")
    n_m = len(catheter.marker_arclengths_mm)
    q_all = np.broadcast_to(q, (n, frames, 3))
    expansion = ShapeExpansion(catheter)
    q_dot_all = None
    if q_dot is not None:
        q_dot_all = _broadcast(q_dot, (n, frames, 3), "q_dot")
    tip_cov = _broadcast(tip_cov_b, (n, frames, 3, 3), "tip_cov_b")
    if (markers_b_mm is None) != (markers_cov_b is None):
        raise ValueError("give markers_b_mm and markers_cov_b together")
    markers = markers_cov = None
    if markers_b_mm is not None:
        markers = np.asarray(markers_b_mm, dtype=float)
        if markers.shape != (n, frames, n_m, 3):
            raise ValueError(
                f"markers_b_mm must have shape {(n, frames, n_m, 3)} (the catheter has {n_m}"
                f" markers), got {markers.shape}"
            )
        markers_cov = _broadcast(markers_cov_b, (n, frames, n_m, 3, 3), "markers_cov_b")
    velocity = velocity_cov = cross = None
    if velocity_b_mm_s is not None:
        if velocity_cov_b is None:
            raise ValueError("velocity_b_mm_s needs velocity_cov_b")
        velocity = _broadcast(velocity_b_mm_s, (n, frames, 3), "velocity_b_mm_s")
        velocity_cov = _broadcast(velocity_cov_b, (n, frames, 3, 3), "velocity_cov_b")
        if velocity_tip_cov_b is not None:
            cross = _broadcast(velocity_tip_cov_b, (n, frames, 3, 3), "velocity_tip_cov_b")
    bank = FilterBank(settings, n)
    out = {
        "delta_L_rad": np.full((n, frames), np.nan),
        "std_rad": np.full((n, frames), np.nan),
        "flags": np.zeros((n, frames), dtype=np.int64),
        "nis": np.full((n, frames), np.nan),
        "nis_dof": np.zeros((n, frames), dtype=np.int64),
        "rejected_outliers": np.zeros((n, frames), dtype=np.int64),
    }
    for k in range(frames):
        if q.ndim == 2 or k == 0 or not np.array_equal(q_all[:, k], q_all[:, k - 1]):
            shape = expansion.expanded(q_all[:, k] if q.ndim == 3 else q_all[:1, k])
            c, JK = (np.broadcast_to(a, (n,) + a.shape[1:]) for a in shape)
        groups = assemble_expanded(
            q_all[:, k], None if q_dot_all is None else q_dot_all[:, k], c, JK, tip[:, k],
            tip_cov[:, k],
            None if markers is None else markers[:, k],
            None if markers_cov is None else markers_cov[:, k],
            None if velocity is None else velocity[:, k],
            None if velocity_cov is None else velocity_cov[:, k],
            None if cross is None else cross[:, k],
        )  # fmt: skip
        P = groups.n_positions
        given = np.ones(P, dtype=bool)
        given[1:] = markers is not None
        partial = np.any(given & ~groups.present[:, :P], axis=1)
        step = bank.step(time[:, k], q_all[:, k], groups, partial)
        out["delta_L_rad"][:, k] = step.delta_L_rad
        out["std_rad"][:, k] = step.std_rad
        out["flags"][:, k] = step.flags
        out["nis"][:, k] = step.nis
        out["nis_dof"][:, k] = step.nis_dof
        out["rejected_outliers"][:, k] = step.rejected
    return UKFBatchResult(**out)


def _broadcast(value, shape: tuple[int, ...], name: str) -> Array:
    array = np.asarray(value, dtype=float)
    try:
        return np.broadcast_to(array, shape)
    except ValueError:
        raise ValueError(f"{name} of shape {array.shape} does not broadcast to {shape}") from None


__all__ = ["UKFBatchResult", "finite_difference_velocity", "run_ukf_batch"]
