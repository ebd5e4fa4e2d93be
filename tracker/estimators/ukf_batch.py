"""Many independent bending-plane UKFs at once, batched over trials (for Monte Carlo studies).

:func:`run_ukf_batch` runs ``B`` independent copies of :class:`~BendingPlaneUKF`
(one per trial) over ``T`` frames, with numpy over the trial axis instead of a Python loop of
filter steps: the sensitivity studies step 228 study points x 500 trials x 10 frames, which
trial by trial (about 100 us a step) takes minutes.

It is the same filter, not an approximation of it. For the 1-D state ``[delta_L]``
(``include_rate=False``) and frames of 3-D data (tip, optional markers, optional velocity), every
step follows :meth:`BendingPlaneUKF.step` branch for branch:

- the same sigma points and weights (van der Merwe's, from ``alpha``, ``beta``, ``kappa``; the
  weights are filterpy's own), the same wrapped sigma points, circular mean and wrapped
  residuals, filterpy's predict (sigma points, unscented transform, sigma points redrawn from
  the predicted variance) with the process noise ``(q + gain |q_r_dot|) dt``, the std cap
  ``max_std_rad`` (with the sigma points redrawn from the capped variance);
- the same stacked measurement (tip, markers, then the velocity with its cross-covariance with
  the tip) and the finite-difference velocity rule (``velocity_is_finite_difference``: a
  velocity is fused only when the trial's previous step did not fuse a tip);
- the same update: innovation covariance ``S`` factorised by Cholesky (retried once with the
  documented jitter of :data:`~ukf.COVARIANCE_JITTER`), gain and NIS from solves with
  that factor, the Fisher-information check (``uninformative_std_rad``), the NIS gate, the
  acceptance check of the posterior;
- the same initialisation from the closed form (:func:`models.rotation_fit.fit_rotation_z`) on
  the first informative frame, the re-initialisation above ``reacquire_std_rad``, the
  re-initialisation after ``reacquire_after_rejections`` consecutive gate rejections, and the
  model-mismatch acceptance with its inflation (capped at
  :data:`~ukf.MAX_MISMATCH_SCALE`) and decay (:data:`~ukf.MISMATCH_DECAY`);
- the covariance repair of the predict (last good state, re-initialised variance).

Trials whose velocity is not fused in a frame carry the velocity rows padded with zeros (a
zero measurement of a zero model vector with unit covariance and no cross-covariance): their
innovation, gain, NIS and Fisher information are those of the unpadded measurement, and the NIS
degrees of freedom are counted per trial.

Results agree with :class:`BendingPlaneUKF` to rounding: the sigma-point arithmetic sums in
another order, so estimates differ by about 1e-14 rad (tests/tracker/test_ukf_batch.py
requires 1e-9 rad and identical flags). The closed form needs more than that:
:func:`~models.rotation_fit.fit_rotation_z` keeps the cheapest of several Newton-polished
candidates, two of which can reach the same minimum, one of them still about 1e-8 rad short
after its three steps, with costs equal to rounding; a one-ulp change of its inputs can then
move its answer by 1e-8 rad. The batched filter therefore gives it the UKF's inputs bit for bit
(the model vectors from the single-configuration path of
:meth:`~models.catheter.Catheter.shape_vectors`, with or without rates as the UKF calls it; the
unpadded stack; :func:`~ukf.spd_inverse`), and the fit of a batch is that of each trial.

Not supported (a ValueError says so): ``include_rate``, ``estimate_noise``, single-view
measurements, and missing data (non-finite tips, markers or their covariances; a missing
velocity is NaN and simply not fused). :class:`BendingPlaneUKF` handles those.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints

from models.catheter import Catheter
from models.rotation_fit import fit_rotation_z
from tracker.estimators.ukf import (
    COVARIANCE_JITTER_FLOOR,
    MAX_MISMATCH_SCALE,
    MISMATCH_DECAY,
    CovarianceError,
    UKFSettings,
    gate_threshold,
    spd_inverse,
)
from tracker.estimators.ukf import _cholesky_lower as cholesky_lower_jittered
from tracker.types import Flag

Array = np.ndarray

_TWO_PI = 2.0 * math.pi
# Sigma-point offsets of the 1-D state in units of the square root: x, x + U, x - U.
_UNIT_OFFSETS = np.array([0.0, 1.0, -1.0])
_NOT_INITIALISED = Flag.NOT_INITIALISED.value
_UNINFORMATIVE = Flag.UNINFORMATIVE.value
_OUTLIER_REJECTED = Flag.OUTLIER_REJECTED.value
_HELD = Flag.HELD.value
_COVARIANCE_REPAIRED = Flag.COVARIANCE_REPAIRED.value
_MODEL_MISMATCH = Flag.MODEL_MISMATCH.value
_R_NOT_POSITIVE_DEFINITE = (
    "measurement covariance of the frame is not positive definite (or not finite): check "
    "tip_cov_b, markers_cov_b, velocity_cov_b or velocity_tip_cov_b"
)


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
        Normalised innovation squared of an update or a gate rejection; NaN otherwise.
    nis_dof : array of int, shape (B, T)
        Its degrees of freedom (the measurement dimension); 0 without an innovation.
    rejected_outliers : array of int, shape (B, T)
        Rejections counted so far.
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
    if not (np.isfinite(dt).all() and np.all(dt > 0)):
        raise ValueError("frame intervals must be positive and finite")
    cov = np.asarray(tip_cov_b, dtype=float)
    cov = cov.reshape((1,) * (4 - cov.ndim) + cov.shape)
    # One covariance per frame for every trial when neither the noise nor the times vary.
    n_cov = 1 if cov.shape[0] == 1 and shared_time else n
    cov = _broadcast(cov, (n_cov, frames, 3, 3), "tip_cov_b")
    dt_cov = dt[:n_cov]
    velocity = np.full((n, frames, 3), np.nan)
    velocity[:, 1:] = (tip[:, 1:] - tip[:, :-1]) / dt[..., None]
    cov_v = np.full(cov.shape, np.nan)
    cross = np.full(cov.shape, np.nan)
    cov_v[:, 1:] = (cov[:, 1:] + cov[:, :-1]) / (dt_cov**2)[..., None, None]
    cross[:, 1:] = cov[:, 1:] / dt_cov[..., None, None]
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
    k = 0 .. T-1 (see the module notes for what is not supported). Arguments shared by every
    trial may leave out the trial axis (``time_s`` (T,), ``q`` (T, 3)) or have it of length 1.

    Parameters
    ----------
    catheter : Catheter
    settings : UKFSettings
        ``include_rate`` and ``estimate_noise`` must be False.
    time_s : array, shape (B, T) or (T,)
        Frame times, s, non-decreasing per trial.
    q, q_dot : arrays, shape (B, T, 3) or (T, 3)
        Joint values (rad, mm, mm) and rates (rad/s, mm/s, mm/s); ``q_dot`` may be None or
        contain NaN (no rate: no velocity and no rotation process noise in that frame).
    tip_b_mm : array, shape (B, T, 3)
        Measured tips in {B}, mm.
    tip_cov_b : array, broadcastable to (B, T, 3, 3)
        Their covariances, mm^2.
    markers_b_mm : array, shape (B, T, n_markers, 3), optional
        The catheter's markers, in order, mm.
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
        For unsupported settings or data, frames out of time order, a non-finite time, or a
        measurement covariance that is not positive definite.
    CovarianceError
        If a predicted variance cannot be repaired (as :meth:`BendingPlaneUKF.step`).
    """
    return _BatchFilter(catheter, settings).run(
        time_s,
        q,
        q_dot,
        tip_b_mm,
        tip_cov_b,
        markers_b_mm,
        markers_cov_b,
        velocity_b_mm_s,
        velocity_cov_b,
        velocity_tip_cov_b,
    )


def _wrap(angle: Array) -> Array:
    return (angle + math.pi) % _TWO_PI - math.pi


def _gates(probability: float, dof: Array) -> Array:
    """NIS gate per trial for integer degrees of freedom (a few distinct values)."""
    values, index = np.unique(dof, return_inverse=True)
    gates = np.array([gate_threshold(probability, int(d)) for d in values])
    return gates[index.reshape(dof.shape)]


def _cholesky(A: Array) -> tuple[Array, Array]:
    """Lower Cholesky factors of a stack (b, m, m) and which succeeded.

    One LAPACK call for the stack; only if some matrix is not positive definite, each is
    factorised on its own with :func:`~ukf._cholesky_lower`'s retry with jitter.
    """
    try:
        return np.linalg.cholesky(A), np.ones(A.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    L = np.zeros_like(A)
    ok = np.zeros(A.shape[0], dtype=bool)
    for i in range(A.shape[0]):
        try:
            L[i] = cholesky_lower_jittered(A[i])
            ok[i] = True
        except CovarianceError:
            pass
    return L, ok


def _measurement_cholesky(R: Array) -> Array:
    """Cholesky factors of measurement covariances; the UKF's ValueError if one is not PD."""
    L, ok = _cholesky(R)
    if not ok.all():
        raise ValueError(_R_NOT_POSITIVE_DEFINITE)
    return L


def _model_vectors(catheter: Catheter, q: Array, q_dot: Array | None) -> tuple:
    """The UKF's model vectors for every frame, shaped like ``q`` (..., 3).

    :meth:`Catheter.shape_vectors` of each distinct configuration through its
    single-configuration path, once without rates (frames whose velocity is not fused) and once
    with them (frames whose velocity is), exactly as :meth:`BendingPlaneUKF.step` calls it: the
    two paths round differently, and the closed form that (re-)initialises the filter resolves
    its minimiser only to about 1e-8 rad (see :func:`_spd_inverses`), so the batched filter
    feeds it bit-identical inputs.

    Returns
    -------
    c_tip, c_markers : arrays (..., 3), (..., n_markers, 3)
        Without rates.
    c_tip_moving, c_markers_moving, u_tip : arrays, the same shapes, or None without ``q_dot``
        With rates (NaN where a rate is not finite).
    """
    lead = q.shape[:-1]
    n_m = len(catheter.marker_arclengths_mm)
    flat = q.reshape(-1, 3)
    distinct, index = _distinct_rows(flat)
    plain = [catheter.shape_vectors(row) for row in distinct]
    c_tip = np.array([s.c_tip_mm for s in plain])[index].reshape(lead + (3,))
    c_markers = np.array([s.c_markers_mm for s in plain]).reshape(-1, n_m, 3)[index]
    c_markers = c_markers.reshape(lead + (n_m, 3))
    if q_dot is None:
        return c_tip, c_markers, None, None, None
    joint = np.concatenate([flat, q_dot.reshape(-1, 3)], axis=1)
    finite = np.isfinite(joint).all(axis=1)
    moving_tip = np.full((flat.shape[0], 3), np.nan)
    moving_markers = np.full((flat.shape[0], n_m, 3), np.nan)
    u_tip = np.full((flat.shape[0], 3), np.nan)
    if finite.any():
        distinct, index = _distinct_rows(joint[finite])
        moving = [catheter.shape_vectors(row[:3], row[3:]) for row in distinct]
        moving_tip[finite] = np.array([s.c_tip_mm for s in moving])[index]
        moving_markers[finite] = np.array([s.c_markers_mm for s in moving]).reshape(-1, n_m, 3)[
            index
        ]
        u_tip[finite] = np.array([s.u_tip_mm_s for s in moving])[index]
    return (
        c_tip,
        c_markers,
        moving_tip.reshape(lead + (3,)),
        moving_markers.reshape(lead + (n_m, 3)),
        u_tip.reshape(lead + (3,)),
    )


def _spd_inverses(R: Array) -> Array:
    """:func:`~ukf.spd_inverse` of every matrix of a stack (b, m, m), once per distinct one.

    The closed form (:func:`models.rotation_fit.fit_rotation_z`) keeps the best of several
    Newton-polished candidates; two of them can reach the same minimum, one not quite converged
    after its three steps, with costs equal to rounding. Its minimiser is therefore resolved to
    about 1e-8 rad, and a one-ulp change of its inputs can move it by that much. The batched
    filter gives it the UKF's inputs bit for bit: the same model vectors, the same unpadded
    stack, and this inverse (LAPACK potrf/potrs through scipy, as the UKF computes it). A study
    shares one covariance between its trials, so this is one factorisation per frame.
    """
    distinct, index = _distinct_rows(R.reshape(R.shape[0], -1))
    inverses = np.empty((distinct.shape[0],) + R.shape[1:])
    for i, A in enumerate(distinct.reshape((-1,) + R.shape[1:])):
        try:
            inverses[i] = spd_inverse(A)
        except CovarianceError:
            raise ValueError(_R_NOT_POSITIVE_DEFINITE) from None
    return inverses[index]


def _distinct_rows(a: Array) -> tuple[Array, Array]:
    """Bit-wise distinct rows of a 2-D float array and, per row, the index of its twin."""
    bits = np.ascontiguousarray(a).view(np.uint64)
    if np.all(bits == bits[:1]):
        return a[:1], np.zeros(a.shape[0], dtype=np.intp)
    rows = bits.view(np.dtype((np.void, bits.dtype.itemsize * bits.shape[1]))).ravel()
    _, first, index = np.unique(rows, return_index=True, return_inverse=True)
    return a[first], index.reshape(-1)


def _broadcast(value, shape: tuple[int, ...], name: str) -> Array:
    array = np.asarray(value, dtype=float)
    try:
        return np.broadcast_to(array, shape)
    except ValueError:
        raise ValueError(f"{name} of shape {array.shape} does not broadcast to {shape}") from None


class _BatchFilter:
    """The state of B filters (one array element per trial) and their step."""

    def __init__(self, catheter: Catheter, settings: UKFSettings) -> None:
        unsupported = [
            name for name in ("include_rate", "estimate_noise") if getattr(settings, name)
        ]
        if unsupported:
            raise ValueError(
                f"run_ukf_batch does not support {' or '.join(unsupported)}; use"
                " BendingPlaneUKF for it"
            )
        self.catheter = catheter
        self.settings = settings
        s = settings
        points = MerweScaledSigmaPoints(1, alpha=s.alpha, beta=s.beta, kappa=s.sigma_kappa)
        self.Wm = np.asarray(points.Wm, dtype=float)
        self.Wc = np.asarray(points.Wc, dtype=float)
        # (lambda + n) of the sigma points, computed as filterpy computes it.
        lambda_ = s.alpha**2 * (1 + s.sigma_kappa) - 1
        self.spread = lambda_ + 1
        self.min_information = s.uninformative_std_rad**-2
        self.max_variance = s.max_std_rad**2
        self.reacquire_variance = s.reacquire_std_rad**2
        self.n_markers = len(catheter.marker_arclengths_mm)

    # ------------------------------------------------------------------ inputs
    def run(
        self,
        time_s,
        q,
        q_dot,
        tip_b_mm,
        tip_cov_b,
        markers_b_mm,
        markers_cov_b,
        velocity_b_mm_s,
        velocity_cov_b,
        velocity_tip_cov_b,
    ) -> UKFBatchResult:
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
        if q_dot is not None:
            q_dot = np.broadcast_to(np.asarray(q_dot, dtype=float), q.shape)
        n_m = self.n_markers
        c_tip, c_markers, c_tip_moving, c_markers_moving, u_tip = _model_vectors(
            self.catheter, q, q_dot
        )
        c_tip = np.broadcast_to(c_tip, (n, frames, 3))
        c_markers = np.broadcast_to(c_markers, (n, frames, n_m, 3))
        q_b = np.broadcast_to(q, (n, frames, 3))
        q_dot_b = None if q_dot is None else np.broadcast_to(q_dot, (n, frames, 3))
        if not np.isfinite(tip).all():
            raise ValueError(
                "run_ukf_batch needs a finite tip in every frame; use BendingPlaneUKF for frames"
                " with missing data"
            )
        tip_cov = _broadcast(tip_cov_b, (n, frames, 3, 3), "tip_cov_b")
        if (markers_b_mm is None) != (markers_cov_b is None):
            raise ValueError("give markers_b_mm and markers_cov_b together")
        if markers_b_mm is None:
            n_m = 0
            markers = np.zeros((n, frames, 0, 3))
            markers_cov = np.zeros((n, frames, 0, 3, 3))
            c_markers = c_markers[:, :, :0]
            c_markers_moving = None if c_markers_moving is None else c_markers_moving[..., :0, :]
        else:
            markers = np.asarray(markers_b_mm, dtype=float)
            if markers.shape != (n, frames, n_m, 3):
                raise ValueError(
                    f"markers_b_mm must have shape {(n, frames, n_m, 3)} (the catheter has {n_m}"
                    f" markers), got {markers.shape}"
                )
            if not np.isfinite(markers).all():
                raise ValueError(
                    "run_ukf_batch needs every marker in every frame; use BendingPlaneUKF for"
                    " frames with missing markers"
                )
            markers_cov = _broadcast(markers_cov_b, (n, frames, n_m, 3, 3), "markers_cov_b")
        if not (np.isfinite(tip_cov).all() and np.isfinite(markers_cov).all()):
            raise ValueError("tip_cov_b and markers_cov_b must be finite")
        velocity = None
        if self.settings.use_velocity and velocity_b_mm_s is not None and q_dot is not None:
            if velocity_cov_b is None:
                raise ValueError("velocity_b_mm_s needs velocity_cov_b")
            velocity = _broadcast(velocity_b_mm_s, (n, frames, 3), "velocity_b_mm_s")
            velocity_cov = _broadcast(velocity_cov_b, (n, frames, 3, 3), "velocity_cov_b")
            if velocity_tip_cov_b is None:
                cross = np.zeros((1, 1, 3, 3))
            else:
                cross = _broadcast(velocity_tip_cov_b, (n, frames, 3, 3), "velocity_tip_cov_b")
                # The UKF uses a cross-covariance only when it is finite.
                cross = np.where(np.isfinite(cross).all(axis=(-2, -1))[..., None, None], cross, 0)
            cross = np.broadcast_to(cross, (n, frames, 3, 3))
            has_velocity = (
                np.isfinite(velocity).all(-1)
                & np.isfinite(velocity_cov).all(axis=(-2, -1))
                & np.isfinite(q_dot_b).all(-1)
            )
            c_tip_moving = np.broadcast_to(c_tip_moving, (n, frames, 3))
            c_markers_moving = np.broadcast_to(c_markers_moving, (n, frames, n_m, 3))
            u_tip = np.broadcast_to(u_tip, (n, frames, 3))
        rows = 1 + n_m + (velocity is not None)
        m = 3 * rows

        self.reset(n)
        out = {
            "delta_L_rad": np.full((n, frames), np.nan),
            "std_rad": np.full((n, frames), np.nan),
            "flags": np.zeros((n, frames), dtype=np.int64),
            "nis": np.full((n, frames), np.nan),
            "nis_dof": np.zeros((n, frames), dtype=np.int64),
            "rejected_outliers": np.zeros((n, frames), dtype=np.int64),
        }
        for k in range(frames):
            # This frame's stacked measurement for every trial (velocity rows padded if unused).
            repeats_fused_tip = self.settings.velocity_is_finite_difference & self.tip_fused
            self.tip_fused = np.zeros(n, dtype=bool)
            y = np.zeros((n, rows, 3))
            C = np.zeros((n, rows, 3))
            R = np.zeros((n, m, m))
            y[:, 0] = tip[:, k]
            C[:, 0] = c_tip[:, k]
            R[:, 0:3, 0:3] = tip_cov[:, k]
            y[:, 1 : 1 + n_m] = markers[:, k]
            C[:, 1 : 1 + n_m] = c_markers[:, k]
            for j in range(n_m):
                R[:, 3 + 3 * j : 6 + 3 * j, 3 + 3 * j : 6 + 3 * j] = markers_cov[:, k, j]
            use_velocity = np.zeros(n, dtype=bool)
            if velocity is not None:
                use_velocity = has_velocity[:, k] & ~repeats_fused_tip
                used = use_velocity[:, None]
                # Catheter.shape_vectors with rates, as the UKF calls it when it fuses a velocity.
                C[:, 0] = np.where(used, c_tip_moving[:, k], C[:, 0])
                C[:, 1 : 1 + n_m] = np.where(
                    used[..., None], c_markers_moving[:, k], C[:, 1 : 1 + n_m]
                )
                y[:, -1] = np.where(used, velocity[:, k], 0.0)
                C[:, -1] = np.where(used, u_tip[:, k], 0.0)
                R[:, -3:, -3:] = np.where(used[..., None], velocity_cov[:, k], np.eye(3))
                R[:, -3:, 0:3] = np.where(used[..., None], cross[:, k], 0.0)
                R[:, 0:3, -3:] = np.swapaxes(R[:, -3:, 0:3], -1, -2)
            dof = 3 * (1 + n_m) + 3 * use_velocity
            rate = None if q_dot is None else q_dot_b[:, k, 0]
            self.step(k, time[:, k], q_b[:, k, 0], rate, y, C, R, dof, out)
        return UKFBatchResult(**out)

    # ------------------------------------------------------------------ state
    def reset(self, n: int) -> None:
        self.x = np.zeros(n)
        self.P = np.full(n, self.max_variance)
        self.initialised = np.zeros(n, dtype=bool)
        self.time_s = np.full(n, np.nan)
        self.rejected = np.zeros(n, dtype=np.int64)
        self.consecutive = np.zeros(n, dtype=np.int64)
        self.mismatch_scale = np.ones(n)
        self.tip_fused = np.zeros(n, dtype=bool)
        self.good_x, self.good_P = self.x.copy(), self.P.copy()
        self.prior_x, self.prior_P = self.x.copy(), self.P.copy()
        self.sigmas = np.zeros((n, 3))

    # ------------------------------------------------------------------ one frame
    def step(self, k, t, q_r, rate, y, C, R, dof, out) -> None:
        self.frame = k
        self.out = out
        self.q_r = q_r
        self.y, self.C, self.R, self.dof = y, C, R, dof
        dt = np.where(np.isnan(self.time_s), 0.0, t - self.time_s)
        self.time_s = t.copy()
        started = self.initialised.copy()

        first = np.flatnonzero(~started)
        if first.size:
            self.try_first(first)
        running = np.flatnonzero(started)
        if running.size:
            flags = self.predict(running, dt[running], None if rate is None else rate[running])
            reacquire = self.P[running] > self.reacquire_variance
            if reacquire.any():
                self.reacquire(running[reacquire], flags[reacquire])
            if not reacquire.all():
                self.update(running[~reacquire], flags[~reacquire])
        out["rejected_outliers"][:, k] = self.rejected

    def estimate(self, idx, flags, nis=None, dof=None) -> None:
        """Record the current state of trials idx as their estimate of this frame."""
        k = self.frame
        self.out["delta_L_rad"][idx, k] = _wrap(self.x[idx])
        self.out["std_rad"][idx, k] = np.sqrt(self.P[idx])
        self.out["flags"][idx, k] = flags
        if nis is not None:
            self.out["nis"][idx, k] = nis
            self.out["nis_dof"][idx, k] = dof

    def held(self, idx, flags) -> None:
        self.estimate(idx, flags | _HELD)

    def invalid(self, idx, flags) -> None:
        self.out["flags"][idx, self.frame] = flags

    def restore_prior(self, idx) -> None:
        self.x[idx] = self.prior_x[idx]
        self.P[idx] = self.prior_P[idx]

    # ------------------------------------------------------------------ process model
    def sigma_points(self, x: Array, P: Array) -> tuple[Array, Array]:
        """Wrapped sigma points (b, 3) and which variances sigma_sqrt accepts (b,)."""
        a = self.spread * P
        ok = np.isfinite(a) & (a >= -COVARIANCE_JITTER_FLOOR)
        # A variance that rounded to zero or just below gets the jitter floor (sigma_sqrt).
        a = np.where(a > 0.0, a, COVARIANCE_JITTER_FLOOR)
        with np.errstate(invalid="ignore"):
            U = np.sqrt(np.where(ok, a, 0.0))
        return _wrap(x[:, None] + _UNIT_OFFSETS * U[:, None]), ok

    def unscented_predict(self, sigmas: Array, Q: Array) -> tuple[Array, Array]:
        """filterpy's predict with the project's UT: circular mean and wrapped residuals."""
        x = np.arctan2(np.sin(sigmas) @ self.Wm, np.cos(sigmas) @ self.Wm)
        residual = _wrap(sigmas - x[:, None])
        return x, np.einsum("bs,s,bs->b", residual, self.Wc, residual) + Q

    def predict_once(self, idx, Q) -> Array:
        """Sigma points, UT, sigma points again; returns which trials factorised both times."""
        sigmas, ok = self.sigma_points(self.x[idx], self.P[idx])
        x, P = self.unscented_predict(sigmas, Q)
        x = np.where(ok, x, self.x[idx])
        P = np.where(ok, P, self.P[idx])
        self.x[idx], self.P[idx] = x, P
        self.sigmas[idx], ok_after = self.sigma_points(x, P)
        return ok & ok_after

    def repair(self, idx) -> None:
        """Restore the last good state with a re-initialised (capped) variance."""
        P = np.abs(self.good_P[idx])
        P = np.where(np.isfinite(P), P, self.max_variance)
        self.P[idx] = np.minimum(np.maximum(P, COVARIANCE_JITTER_FLOOR), self.max_variance)
        self.x[idx] = self.good_x[idx]

    def predict(self, idx, dt, rate) -> Array:
        """Predict trials idx to this frame; returns their flags (COVARIANCE_REPAIRED)."""
        s = self.settings
        intensity = np.full(idx.size, s.process_noise_rad2_s)
        if rate is not None and s.rotation_noise_gain_rad:
            finite = np.isfinite(rate)
            intensity = np.where(
                finite, intensity + s.rotation_noise_gain_rad * np.abs(rate), intensity
            )
        Q = intensity * dt
        flags = np.zeros(idx.size, dtype=np.int64)
        ok = self.predict_once(idx, Q)
        if not ok.all():
            self.repair(idx[~ok])
            if not self.predict_once(idx[~ok], Q[~ok]).all():
                raise CovarianceError("covariance is not positive definite, even after repair")
            flags[~ok] = _COVARIANCE_REPAIRED
        P = self.P[idx]
        capped = P > self.max_variance
        if capped.any():
            f = np.sqrt(self.max_variance / P[capped])
            self.P[idx[capped]] = P[capped] * f * f
            # The update reuses predict's sigma points: draw them again from the capped P.
            self.sigmas[idx[capped]], _ = self.sigma_points(
                self.x[idx[capped]], self.P[idx[capped]]
            )
        broken = ~(np.isfinite(self.x[idx]) & np.isfinite(self.P[idx]))
        if broken.any():
            self.repair(idx[broken])
            if not self.predict_once(idx[broken], Q[broken]).all():
                raise CovarianceError("covariance is not positive definite, even after repair")
            flags[broken] = _COVARIANCE_REPAIRED
        self.prior_x[idx] = self.x[idx]
        self.prior_P[idx] = self.P[idx]
        return flags

    # ------------------------------------------------------------------ closed form
    def closed_form(self, idx) -> tuple[Array, Array, Array, Array]:
        """Global closed-form fit of trials idx: (phi, Fisher std, consistent, misfit).

        Per measurement size (with or without the velocity), on the unpadded stack, so that
        :func:`fit_rotation_z` sees what it sees in the UKF (see :func:`_spd_inverses`).
        """
        phi, std = np.empty(idx.size), np.empty(idx.size)
        consistent, misfit = np.empty(idx.size, dtype=bool), np.empty(idx.size)
        dofs = self.dof[idx]
        for size in np.unique(dofs):
            mine = dofs == size
            j = idx[mine]
            R = self.R[j, :size, :size] * self.mismatch_scale[j, None, None]
            fit = fit_rotation_z(self.y[j, : size // 3], self.C[j, : size // 3], _spd_inverses(R))
            information = fit.fisher_information
            with np.errstate(divide="ignore"):
                std[mine] = np.where(information > 0, 1.0 / np.sqrt(information), np.inf)
            # The minimised cost is chi-square with one degree of freedom fewer than the data.
            dof = max(int(size) - 1, 1)
            consistent[mine] = fit.cost <= gate_threshold(self.settings.gate_probability, dof)
            misfit[mine] = np.sqrt(np.maximum(1.0, fit.cost / dof))
            phi[mine] = fit.phi_rad
        return phi, std, consistent, misfit

    def start(self, idx, phi, std, flags) -> None:
        """Re-initialise trials idx from a closed-form solution (BendingPlaneUKF._restart)."""
        if self.settings.initial_std_rad is not None:
            std = np.maximum(std, self.settings.initial_std_rad)
        x = _wrap(_wrap(phi - self.q_r[idx]))
        P = np.minimum(std**2, self.max_variance)
        self.x[idx] = self.good_x[idx] = self.prior_x[idx] = x
        self.P[idx] = self.good_P[idx] = self.prior_P[idx] = P
        self.initialised[idx] = True
        self.consecutive[idx] = 0
        self.tip_fused[idx] = True
        self.estimate(idx, flags)

    def accept_mismatch(self, idx, phi, std, misfit, flags) -> None:
        """Restart with std and measurement noise inflated by the misfit (MODEL_MISMATCH)."""
        self.mismatch_scale[idx] = np.minimum(
            self.mismatch_scale[idx] * misfit**2, MAX_MISMATCH_SCALE
        )
        self.start(idx, phi, std * misfit, flags | _MODEL_MISMATCH)

    def from_closed_form(self, idx, refuse, start_flags, refuse_flags) -> None:
        """BendingPlaneUKF._try_first and _reacquire: restart, accept a mismatch or refuse.

        ``refuse(trials, flags)`` records a refusal (uninformative, or inconsistent data);
        a restart carries ``start_flags``.
        """
        s = self.settings
        phi, std, consistent, misfit = self.closed_form(idx)
        uninformative = ~(std < s.uninformative_std_rad)
        refuse(idx[uninformative], refuse_flags[uninformative] | _UNINFORMATIVE)
        inconsistent = ~uninformative & ~consistent
        self.consecutive[idx[inconsistent]] += 1
        persistent = (
            inconsistent
            & bool(s.reacquire_after_rejections)
            & (self.consecutive[idx] >= s.reacquire_after_rejections)
            & (std * misfit < s.uninformative_std_rad)
        )
        if persistent.any():
            self.accept_mismatch(
                idx[persistent], phi[persistent], std[persistent], misfit[persistent],
                start_flags[persistent],
            )  # fmt: skip
        refused = inconsistent & ~persistent
        self.rejected[idx[refused]] += 1
        refuse(idx[refused], refuse_flags[refused] | _OUTLIER_REJECTED)
        good = ~uninformative & consistent
        if good.any():
            self.start(idx[good], phi[good], std[good], start_flags[good])

    def try_first(self, idx) -> None:
        """No estimate yet: start from the closed form of an informative, consistent frame."""
        # A start drops NOT_INITIALISED (and would keep PARTIAL, which 3-D data never are).
        none = np.zeros(idx.size, dtype=np.int64)
        self.from_closed_form(idx, self.invalid, none, none | _NOT_INITIALISED)

    def reacquire(self, idx, flags) -> None:
        """The predicted std is too wide for a sigma-point update: restart from the closed form."""
        self.from_closed_form(idx, self.held, flags, flags)

    # ------------------------------------------------------------------ update
    def update(self, idx, flags) -> None:
        """filterpy's update (vectorised over trials), the information check and the gate."""
        s = self.settings
        R = self.R[idx] * self.mismatch_scale[idx, None, None]
        sigmas = self.sigmas[idx]
        x_prior = self.x[idx]
        C = self.C[idx]
        b, rows = C.shape[:2]
        m = 3 * rows
        # Measurement sigma points Rz(q_r + sigma) C: a complex multiplication of C_x + i C_y.
        turn = np.exp(1j * (self.q_r[idx, None] + sigmas))
        rotated = turn[:, :, None] * (C[:, None, :, 0] + 1j * C[:, None, :, 1])
        h = np.empty((b, 3, rows, 3))
        h[..., 0] = rotated.real
        h[..., 1] = rotated.imag
        h[..., 2] = C[:, None, :, 2]
        h = h.reshape(b, 3, m)
        zp = np.einsum("s,bsm->bm", self.Wm, h)
        dz = h - zp[:, None, :]
        S = np.einsum("bsi,s,bsj->bij", dz, self.Wc, dz) + R
        dx = _wrap(sigmas - x_prior[:, None])
        Pxz = np.einsum("bs,s,bsm->bm", dx, self.Wc, dz)
        innovation = self.y[idx].reshape(b, m) - zp
        L_S, factorised = _cholesky(S)
        L_R = _measurement_cholesky(R)
        if not factorised.all():
            # The UKF restores the prior and reports the repair (filterpy's update raised).
            broken = ~factorised
            self.held(idx[broken], flags[broken] | _COVARIANCE_REPAIRED)
            keep = factorised
            idx, flags, L_S, L_R, x_prior = (
                idx[keep],
                flags[keep],
                L_S[keep],
                L_R[keep],
                x_prior[keep],
            )
            Pxz, innovation, h = Pxz[keep], innovation[keep], h[keep]
            b = idx.size
            if b == 0:
                return
        # With S = L L^T: gain K = Pxz S^-1, K y = (L^-1 Pxz)^T (L^-1 y), K Pxz^T = |L^-1 Pxz|^2,
        # NIS = |L^-1 y|^2 (the same solves as the UKF's Cholesky solve of S).
        solved = np.linalg.solve(L_S, np.stack([Pxz, innovation], axis=-1))
        gain_side, innovation_side = solved[..., 0], solved[..., 1]
        nis = np.einsum("bm,bm->b", innovation_side, innovation_side)
        x_post = _wrap(x_prior + np.einsum("bm,bm->b", gain_side, innovation_side))
        P_post = self.P[idx] - np.einsum("bm,bm->b", gain_side, gain_side)
        # Fisher information at the prior mean; the first measurement sigma point is h(mean).
        slope = np.zeros((b, m // 3, 3))
        first = h[:, 0].reshape(b, m // 3, 3)
        slope[..., 0] = -first[..., 1]
        slope[..., 1] = first[..., 0]
        w = np.linalg.solve(L_R, slope.reshape(b, m, 1))[..., 0]
        information = np.einsum("bm,bm->b", w, w)
        uninformative = ~(information > self.min_information)
        if uninformative.any():
            self.held(idx[uninformative], flags[uninformative] | _UNINFORMATIVE)
        informative = ~uninformative
        dof = self.dof[idx]
        gate = _gates(s.gate_probability, dof)
        rejected = informative & ~(nis <= gate)
        if rejected.any():
            self.reject(idx[rejected], flags[rejected], nis[rejected], dof[rejected])
        accepted = informative & (nis <= gate)
        if not accepted.any():
            return
        i = idx[accepted]
        flags = flags[accepted]
        self.consecutive[i] = 0
        # A model-mismatch inflation fades once the data fit again (about 1 % per frame).
        self.mismatch_scale[i] = 1.0 + MISMATCH_DECAY * (self.mismatch_scale[i] - 1.0)
        x, P = x_post[accepted], P_post[accepted]
        good = np.isfinite(x) & np.isfinite(P) & (P > 0)
        self.x[i[good]] = self.good_x[i[good]] = x[good]
        self.P[i[good]] = self.good_P[i[good]] = P[good]
        self.tip_fused[i[good]] = True
        flags = np.where(good, flags, flags | _COVARIANCE_REPAIRED | _HELD)
        self.estimate(i, flags, nis[accepted], dof[accepted])

    def reject(self, idx, flags, nis, dof) -> None:
        """Gate rejection: hold the prior; re-initialise after too many in a row."""
        s = self.settings
        self.consecutive[idx] += 1
        limit = s.reacquire_after_rejections
        handled = np.zeros(idx.size, dtype=bool)
        if limit:
            due = self.consecutive[idx] >= limit
            if due.any():
                j = np.flatnonzero(due)
                phi, std, consistent, misfit = self.closed_form(idx[j])
                jump = consistent & (std < s.uninformative_std_rad)
                mismatch = ~jump & (std * misfit < s.uninformative_std_rad)
                if jump.any():
                    self.start(idx[j[jump]], phi[jump], std[jump], flags[j[jump]])
                if mismatch.any():
                    self.accept_mismatch(
                        idx[j[mismatch]], phi[mismatch], std[mismatch], misfit[mismatch],
                        flags[j[mismatch]],
                    )  # fmt: skip
                handled[j[jump | mismatch]] = True
        held = ~handled
        self.rejected[idx[held]] += 1
        self.estimate(idx[held], flags[held] | _OUTLIER_REJECTED | _HELD, nis[held], dof[held])


__all__ = ["UKFBatchResult", "finite_difference_velocity", "run_ukf_batch"]
