"""Point-mass (grid) filter of delta_L: the exact Bayesian reference for the UKF.

delta_L is one angle, so its posterior can be held on a grid of cells over the circle and
computed on the grid. :class:`GridFilter` does so with the UKF's process and measurement
models (:mod:`tracker.estimators.measurement`, :mod:`tracker.estimators.deviation`, the same
:class:`~tracker.estimators.ukf_settings.UKFSettings`); the approximations are the
deviation's (below):

- the joint-equivalent deviation dq of the shape is Rao-Blackwellised: every cell carries
  the Gaussian of dq given that cell's angle, one mean per cell (its residuals use the
  second-order shape) and one covariance for all (the deviation's Jacobian does not depend
  on the angle; it is taken at the deviation of the most probable cell), updated by a Kalman
  filter;
- predict: the random walk is a convolution of the grid with a wrapped normal, applied
  exactly as a product of Fourier coefficients ``exp(-k^2 var / 2)`` (one real FFT each
  way; the per-cell dq means follow by moment matching); a torsion jump mixes in the
  uniform density with the jump probability;
- update: every group's residual in the model frame is affine in (cos, sin) of the cell's
  angle and in dq, so the heavy-tailed likelihood of a frame on all cells costs a few
  element-wise operations on (cells, groups, 3) arrays; the groups enter as independent
  given the cell (their common dq uncertainty enters each group's covariance); single-view
  points are projected on every cell;
- the estimate is the circular mean of the posterior and its std the root of the posterior
  variance (plus a cell's own ``h^2 / 12``); 2,048 cells by default (0.18 degree cells).

It carries no gate, restart or mismatch rule: a multimodal posterior (a nearly straight
catheter, a torsion jump) is simply represented. It starts reporting once the posterior std
first falls below ``uninformative_std_rad``. Not used from the settings: the UKF's
sigma-point, hypothesis and restart settings, ``include_rate`` (the grid is over delta_L
alone) and ``estimate_noise``.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

from models.catheter import Catheter
from tracker.estimators._linalg import cholesky, spd_inverse
from tracker.estimators.deviation import (
    ShapeExpansion,
    deviation_decay,
    deviation_jacobian,
    deviation_prior,
    quadratic_moments,
)
from tracker.estimators.measurement import (
    FrameGroups,
    jump_probability,
    mixture_log_likelihood,
    model_error_covariance,
    offered_velocity,
    outlier_threshold,
    process_variance,
    velocity_offered,
    wrap,
)
from tracker.estimators.ukf import check_observation, observation_groups
from tracker.estimators.ukf_settings import UKFSettings
from tracker.types import Estimate, Flag, Observation

Array = np.ndarray
DEFAULT_CELLS = 2048
_LOG_2PI = math.log(2.0 * math.pi)
_TWO_PI = 2.0 * math.pi


class GridFilter:
    """Point-mass filter of delta_L on ``cells`` cells over [-pi, pi).

    Parameters
    ----------
    catheter : Catheter
    settings : UKFSettings, optional
        Its process and measurement models (see the module notes for what is not used).
    cells : int
        Number of grid cells, >= 64. The default 2,048 (0.18 degree cells) resolves a
        posterior down to a std of about a cell; the grid's std includes a cell's own
        ``h^2 / 12``, so a narrower posterior is reported as wide as a cell.
    name : str
    """

    def __init__(
        self,
        catheter: Catheter,
        settings: UKFSettings | None = None,
        cells: int = DEFAULT_CELLS,
        name: str = "grid",
    ) -> None:
        if int(cells) != cells or cells < 64:
            raise ValueError(f"a grid filter needs an integer number of cells >= 64, got {cells}")
        self.catheter = catheter
        self.settings = UKFSettings() if settings is None else settings
        self.name = name
        self.cells = int(cells)
        self.cell_rad = 2 * math.pi / self.cells
        self.angles = -math.pi + self.cell_rad * np.arange(self.cells)
        self._turn = np.exp(1j * self.angles)
        self._k2 = np.arange(self.cells // 2 + 1, dtype=float) ** 2
        # Rows [cos, sin, 1, expansion_basis(mu)] of every cell for the likelihood (row 2
        # stays 1), and the stack the prediction convolves.
        self._basis = np.ones((8, self.cells))
        self._stack = np.empty((3, self.cells))
        self._expansion = ShapeExpansion(catheter)
        self.reset()

    def reset(self) -> None:
        """Forget everything: uniform posterior, not initialised."""
        s = self.settings
        self.p = np.full(self.cells, 1.0 / self.cells)
        self._deviation = s.estimates_deviation
        # The deviation's mean (dq_p, dq_d) given each cell's angle, mm: (2, cells).
        self.mu = np.zeros((2, self.cells))
        self.Sigma = np.diag(deviation_prior(np.zeros((1, 3)), s.joint_error_mm, 0.0)[0])
        self._pending_variance = 0.0
        self._initialised = False
        self._time_s = math.nan
        self._q = np.full(3, np.nan)
        self._tip_fused = np.zeros(1, dtype=bool)
        self._rejected = 0
        self._moments = None

    @property
    def initialised(self) -> bool:
        return self._initialised

    def moments(self) -> tuple[float, float]:
        """Circular mean and std of the posterior, rad."""
        if self._moments is None:
            p = self.p
            z = p @ self._turn
            mean = math.atan2(z.imag, z.real)
            spread = self.angles - mean
            spread -= _TWO_PI * np.rint(spread / _TWO_PI)
            var = float(p @ (spread * spread)) + self.cell_rad**2 / 12.0
            self._moments = (float(wrap(mean)), math.sqrt(var))
        return self._moments

    def _cell(self, angle: float) -> int:
        return int(round((angle + math.pi) / self.cell_rad)) % self.cells

    def step(self, observation: Observation) -> Estimate:
        """Predict the posterior to the frame's time and multiply in the frame's likelihood."""
        s = self.settings
        t, q = check_observation(observation, self._time_s)
        offered = velocity_offered(s, self._tip_fused)
        groups, partial = observation_groups(self._expansion, observation, q, bool(offered[0]))
        known = math.isfinite(self._time_s)
        dt = t - self._time_s if known else 0.0
        turn = float(q[0] - self._q[0]) if known else 0.0
        moved = float(np.sum(np.abs(q[1:] - self._q[1:]))) if known else 0.0
        self._time_s, self._q = t, q.copy()
        Q = float(process_variance(s.process_noise_rad2_s, s.rotation_noise_gain_rad, dt, turn))
        if self._deviation:
            prior = deviation_prior(q[None], s.joint_error_mm, s.gain_error)[0]
            a = float(deviation_decay(moved, s.deviation_length_mm, dt, s.deviation_rate_per_s))
            self.mu *= a
            self.Sigma = a * a * self.Sigma + (1 - a * a) * np.diag(prior)
        if self._initialised:
            jump = float(jump_probability(s.jump_rate_per_s, s.jump_per_rad, dt, turn))
            self._predict(Q, jump)
        flags = Flag.PARTIAL if partial else Flag.NONE
        rejected = 0
        radius = 0.0
        tip_fused = False
        if groups is not None:
            groups = offered_velocity(groups, s, self._tip_fused)
        if groups is None or not groups.present.any():
            flags |= Flag.NO_MEASUREMENT | (Flag.HELD if self._initialised else Flag.NONE)
        else:
            radius = float(groups.radius_mm()[0])
            three_d = isinstance(groups, FrameGroups)
            present = groups.present[0]
            if three_d:
                d2, log_lik, update = self._likelihood_3d(groups, Q, dt, present)
            else:
                d2, log_lik = self._likelihood_views(groups)
            self._multiply(log_lik)
            mean, _ = self.moments()
            inlier = present.copy()
            inlier[present] = d2[self._cell(mean)] <= outlier_threshold(
                groups.dim, s.outlier_probability, s.outlier_scale
            )
            rejected = int(np.sum(present & ~inlier))
            if rejected:
                flags |= Flag.OUTLIER_REJECTED
            tip_fused = bool(three_d and inlier[0])
            if three_d and self._deviation and inlier.any():
                update(inlier[present])
        self._tip_fused[0] = tip_fused
        self._rejected += rejected
        mean, std = self.moments()
        if not self._initialised and std < s.uninformative_std_rad:
            self._initialised = True
        if not self._initialised:
            return Estimate(
                time_s=t, delta_L_rad=math.nan, std_rad=math.nan, q_r_rad=float(q[0]),
                flags=flags | Flag.NOT_INITIALISED, informative_radius_mm=radius,
                rejected_outliers=self._rejected,
            )  # fmt: skip
        if self._deviation:
            prior = deviation_prior(q[None], s.joint_error_mm, s.gain_error)[0]
            if np.any(self.mu[:, self._cell(mean)] ** 2 > 9.0 * prior):
                flags |= Flag.MODEL_MISMATCH
        return Estimate(
            time_s=t, delta_L_rad=mean, std_rad=std, q_r_rad=float(q[0]), flags=flags,
            informative_radius_mm=radius, rejected_outliers=self._rejected,
        )  # fmt: skip

    def _multiply(self, log_lik: Array) -> None:
        """Posterior = prior x likelihood, normalised."""
        p = self.p * np.exp(log_lik - log_lik.max())
        total = p.sum()
        if not (total > 1e-250 and math.isfinite(total)):
            # The likelihood's peak lies where the prior has (numerically) no mass: in logs.
            log_post = np.log(np.maximum(self.p, 1e-300)) + log_lik
            p = np.exp(log_post - log_post.max())
            total = p.sum()
        self.p = p / total
        self._moments = None

    def _predict(self, variance: float, jump: float) -> None:
        # A variance much below a cell's only blurs within it: it accumulates until it shows.
        variance += self._pending_variance
        self._pending_variance = 0.0
        p = self.p
        if variance > 0.01 * self.cell_rad**2:
            # The wrapped normal's Fourier coefficients at the integer frequencies of the grid.
            # Beyond exp(-746) the coefficients are exactly 0.0 in doubles: not computed.
            used = min(self._k2.size, int(math.sqrt(1492.0 / variance)) + 1)
            kernel = np.zeros(self._k2.size)
            np.exp(-0.5 * variance * self._k2[:used], out=kernel[:used])
            if self._deviation and variance > (2 * self.cell_rad) ** 2:
                # The deviation means follow by moment matching: convolve p and p mu at once.
                stack = self._stack
                stack[0] = self.p
                np.multiply(self.p, self.mu, out=stack[1:])
                blurred = scipy.fft.irfft(scipy.fft.rfft(stack) * kernel, self.cells)
                p = np.maximum(blurred[0], 0.0)
                self.mu = blurred[1:] / np.maximum(p, 1e-300)
            else:
                p = np.maximum(scipy.fft.irfft(scipy.fft.rfft(self.p) * kernel, self.cells), 0.0)
            p /= p.sum()
        else:
            self._pending_variance = variance
        if jump > 0:
            mixed = (1.0 - jump) * p + jump / self.cells
            # A jump lands anywhere with the deviation's prior mean (zero).
            self.mu *= (1.0 - jump) * p / mixed
            p = mixed
        self.p = p
        self._moments = None

    def _likelihood_3d(self, groups: FrameGroups, Q: float, dt: float, present: Array):
        """Per cell and present group d^2 (N, G'), the frame's log-likelihood (N,) and the
        Kalman update of the deviation means."""
        s = self.settings
        M = model_error_covariance(
            groups, s.joint_error_white_mm, s.velocity_relative_error, np.array([Q]),
            np.array([dt]),
        )[0][present]  # fmt: skip
        y, c, JK = groups.y[0][present], groups.c[0][present], groups.JK[0][present]
        S = groups.R_bar[0][present] + M
        if self._deviation:
            # The deviation enters with its Jacobian at the most probable cell's deviation, and
            # its quadratic term with the mean and spread of the shared covariance.
            J = deviation_jacobian(JK[..., :2], JK[..., 2:], self.mu[:, int(np.argmax(self.p))])
            bias, spread = quadratic_moments(JK[..., 2:], self.Sigma)
            S = S + J @ self.Sigma @ np.swapaxes(J, -1, -2) + spread
            c = c + bias
        G = y.shape[0]
        # Rz(q_r + delta)^T y - c - JK expansion_basis(mu) = A^T basis for every group and
        # cell, with basis the rows [cos, sin, 1, expansion_basis(mu)] of the cells: (3G, N).
        rows = 8 if self._deviation else 3
        A = np.empty((rows, G, 3))
        A[0, :, 0], A[0, :, 1], A[0, :, 2] = y[:, 0], y[:, 1], 0.0
        A[1, :, 0], A[1, :, 1], A[1, :, 2] = y[:, 1], -y[:, 0], 0.0
        A[2, :, 0], A[2, :, 1], A[2, :, 2] = -c[:, 0], -c[:, 1], y[:, 2] - c[:, 2]
        basis = self._basis[:rows]
        turned = self._turn * complex(math.cos(groups.q_r[0]), math.sin(groups.q_r[0]))
        basis[0], basis[1] = turned.real, turned.imag
        if self._deviation:
            A[3:] = -np.moveaxis(JK, -1, 0)
            mu = self.mu
            basis[3:5] = mu
            np.multiply(mu[0], mu[0], out=basis[5])
            np.multiply(mu[0], mu[1], out=basis[6])
            np.multiply(mu[1], mu[1], out=basis[7])
        A = A.reshape(rows, 3 * G)
        # Whitened by each group's Cholesky factor, d^2 = |L^-1 r|^2, folded into A.
        whitening, logdet = _whitening(S)
        white = (A @ whitening).T @ basis
        white *= white
        d2 = white.reshape(G, 3, -1).sum(1)  # sums of three squares, (G, N)
        terms = mixture_log_likelihood(d2, 3, s.outlier_probability, s.outlier_scale)
        log_lik = terms.sum(0) - 0.5 * (logdet + 3 * G * _LOG_2PI)

        def update(inlier: Array) -> None:
            if self._deviation:
                self._update_deviation(J, S, inlier, basis, A)

        return d2.T, log_lik, update

    def _likelihood_views(self, groups):
        """Per cell and point d^2 (N, G) and the frame's log-likelihood (N,), single views."""
        s = self.settings
        cov = groups.R[0]
        W = spd_inverse(cov)
        logdet = np.linalg.slogdet(cov)[1]
        predicted = groups.predict(np.array([0]), self.angles[None, :, None])[0]
        residual = groups.z[0][None] - predicted  # (N, G, 2)
        d2 = np.einsum("ngi,gij,ngj->ng", residual, W, residual)
        terms = mixture_log_likelihood(d2, 2, s.outlier_probability, s.outlier_scale)
        return d2, terms.sum(axis=1) - 0.5 * float(np.sum(logdet + 2 * _LOG_2PI))

    def _update_deviation(
        self, J: Array, S_g: Array, inlier: Array, basis: Array, A: Array
    ) -> None:
        """Kalman update of every cell's deviation mean with the inlying groups (one gain,
        with the Jacobian J (G, 3, 2) at the deviation of the posterior mean); the model-frame
        residuals of the cells are ``A^T basis`` ((k, 3G) and (k, N))."""
        J_in = J[inlier]
        k = J_in.shape[0]
        noise = S_g[inlier] - J_in @ self.Sigma @ np.swapaxes(J_in, -1, -2)
        R = np.zeros((k, 3, k, 3))
        R[np.arange(k), :, np.arange(k), :] = noise
        H = J_in.reshape(-1, 2)
        S = H @ self.Sigma @ H.T + R.reshape(3 * k, 3 * k)
        gain = np.linalg.solve(S, H @ self.Sigma).T  # (2, m)
        columns = np.repeat(inlier, 3)
        self.mu += (A[:, columns] @ gain.T).T @ basis
        Sigma = self.Sigma - gain @ S @ gain.T
        self.Sigma = 0.5 * (Sigma + Sigma.T)


def _whitening(S: Array) -> tuple[Array, float]:
    """Block-diagonal ``L^-T`` of the Cholesky factors L of G covariances (G, 3, 3), (3G, 3G),
    and the sum of their log determinants.

    The few 3 x 3 factors and inverses are computed in floats (LAPACK's order of operations);
    a covariance that is not positive definite goes through :func:`cholesky` and its jitter.
    """
    G = S.shape[0]
    whitening = np.zeros((3 * G, 3 * G))
    logdet = 0.0
    for g, ((a11, _, _), (a21, a22, _), (a31, a32, a33)) in enumerate(S.tolist()):
        d1 = a11
        if not d1 > 0.0:
            break
        l11 = math.sqrt(d1)
        l21, l31 = a21 / l11, a31 / l11
        d2 = a22 - l21 * l21
        if not d2 > 0.0:
            break
        l22 = math.sqrt(d2)
        l32 = (a32 - l31 * l21) / l22
        d3 = a33 - l31 * l31 - l32 * l32
        if not (d3 > 0.0 and math.isfinite(d3)):
            break
        l33 = math.sqrt(d3)
        m11, m22, m33 = 1.0 / l11, 1.0 / l22, 1.0 / l33
        m21 = -(l21 * m11) * m22
        m32 = -(l32 * m22) * m33
        m31 = -(l31 * m11 + l32 * m21) * m33
        k = 3 * g
        whitening[k : k + 3, k : k + 3] = ((m11, m21, m31), (0.0, m22, m32), (0.0, 0.0, m33))
        logdet += 2.0 * (math.log(l11) + math.log(l22) + math.log(l33))
    else:
        return whitening, logdet
    L, _ = cholesky(S)
    whitening = np.zeros((G, 3, G, 3))
    whitening[np.arange(G), :, np.arange(G), :] = np.swapaxes(np.linalg.inv(L), -1, -2)
    logdet = 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum()
    return whitening.reshape(3 * G, 3 * G), float(logdet)


__all__ = ["DEFAULT_CELLS", "GridFilter"]
