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
- update: every group's residual in the model frame is affine in the rows ``[cos, sin, 1,
  expansion_basis(mu)]`` of the cells (the cell's angle, its dq mean), so the heavy-tailed
  likelihood of a frame on all cells is one small matrix product over the grid and a few
  element-wise operations on (groups, cells) arrays; the groups enter as independent given
  the cell (their common dq uncertainty enters each group's covariance); single-view points
  are projected on every cell;
- the estimate is the circular mean of the posterior and its std the root of the posterior
  variance (plus a cell's own ``h^2 / 12``); 2,048 cells by default (0.18 degree cells).

Likelihoods are evaluated up to a constant (the Gaussians' normalisation): the posterior is
normalised over the cells, where it cancels.

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
from scipy.linalg import lapack

from models.catheter import Catheter
from tracker.estimators._linalg import block_index, cholesky, spd_inverse
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

    Attributes
    ----------
    angles : array (cells,)
        The cells' angles, rad.
    p : array (cells,)
        The posterior probability of every cell.
    mu : array (2, cells)
        The deviation's mean (dq_p, dq_d) given each cell's angle, mm (updated in place: set
        it with ``mu[:] = ...``).
    Sigma : array (2, 2)
        The deviation's covariance given the angle (the same for every cell), mm^2.
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
        self._k2 = np.arange(self.cells // 2 + 1, dtype=float) ** 2
        # The rows every group's model-frame residual is affine in, for every cell: cos and sin
        # of its angle and 1 (fixed), its deviation mean (``mu`` is a view of rows 3 and 4,
        # so that the likelihood reads it in place) and the mean's quadratic terms (filled
        # per frame): [cos, sin, 1, expansion_basis(mu)].
        self._basis = np.empty((8, self.cells))
        self._basis[0] = np.cos(self.angles)
        self._basis[1] = np.sin(self.angles)
        self._basis[2] = 1.0
        self.mu = self._basis[3:5]
        # What the prediction convolves: p and, moment matching the means, p mu.
        self._stack = np.empty((3, self.cells))
        self._spread = np.empty(self.cells)
        self._expansion = ShapeExpansion(catheter)
        self.reset()

    def reset(self) -> None:
        """Forget everything: uniform posterior, not initialised."""
        s = self.settings
        self.p = np.full(self.cells, 1.0 / self.cells)
        self._deviation = s.estimates_deviation
        self.mu[:] = 0.0
        self.Sigma = np.diag(deviation_prior(np.zeros((1, 3)), s.joint_error_mm, 0.0)[0])
        self._pending_variance = 0.0
        self._initialised = False
        self._time_s = math.nan
        self._q = [math.nan] * 3
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
            c, s = (self._basis[:2] @ p).tolist()
            mean = math.atan2(s, c)
            # The cells' offsets from the mean, wrapped to [-pi, pi]: only those more than
            # half a turn away wrap, a run at one end of the grid.
            spread = np.subtract(self.angles, mean, out=self._spread)
            if mean >= 0.0:
                spread[: math.ceil(mean / self.cell_rad)] += _TWO_PI
            else:
                spread[math.floor((_TWO_PI + mean) / self.cell_rad) + 1 :] -= _TWO_PI
            var = float(p @ np.square(spread, out=spread)) + self.cell_rad**2 / 12.0
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
        joints = q.tolist()
        known = math.isfinite(self._time_s)
        dt = t - self._time_s if known else 0.0
        turn = joints[0] - self._q[0] if known else 0.0
        moved = abs(joints[1] - self._q[1]) + abs(joints[2] - self._q[2]) if known else 0.0
        self._time_s, self._q = t, joints
        Q = float(process_variance(s.process_noise_rad2_s, s.rotation_noise_gain_rad, dt, turn))
        if self._deviation:
            prior = deviation_prior(q[None], s.joint_error_mm, s.gain_error)[0].tolist()
            a = float(deviation_decay(moved, s.deviation_length_mm, dt, s.deviation_rate_per_s))
            self.mu *= a
            (s00, s01), (s10, s11) = self.Sigma.tolist()
            a2 = a * a
            self.Sigma = np.array(
                [[a2 * s00 + (1 - a2) * prior[0], a2 * s01],
                 [a2 * s10, a2 * s11 + (1 - a2) * prior[1]]]
            )  # fmt: skip
        if self._initialised:
            jump = float(jump_probability(s.jump_rate_per_s, s.jump_per_rad, dt, turn))
            self._predict(Q, jump)
        flags = Flag.PARTIAL if partial else Flag.NONE
        rejected = 0
        radius = 0.0
        tip_fused = False
        if groups is None or not groups.present.any():
            flags |= Flag.NO_MEASUREMENT | (Flag.HELD if self._initialised else Flag.NONE)
        else:
            radius = float(groups.radius_mm()[0])
            three_d = isinstance(groups, FrameGroups)
            present = groups.present[0]
            if three_d:
                d2, log_lik, update = self._likelihood_3d(groups, Q, dt, present, joints[0])
            else:
                d2, log_lik, update = self._likelihood_views(groups)
            self._multiply(log_lik)
            mean, _ = self.moments()
            # Which of the present groups the posterior mean's cell explains (no outliers).
            explained = d2[:, self._cell(mean)] <= outlier_threshold(
                groups.dim, s.outlier_probability, s.outlier_scale
            )
            rejected = explained.size - int(np.count_nonzero(explained))
            if rejected:
                flags |= Flag.OUTLIER_REJECTED
            tip_fused = bool(three_d and present[0] and explained[0])
            if update is not None and rejected < explained.size:
                update(explained)
        self._tip_fused[0] = tip_fused
        self._rejected += rejected
        mean, std = self.moments()
        if not self._initialised and std < s.uninformative_std_rad:
            self._initialised = True
        if not self._initialised:
            return Estimate(
                time_s=t, delta_L_rad=math.nan, std_rad=math.nan, q_r_rad=joints[0],
                flags=flags | Flag.NOT_INITIALISED, informative_radius_mm=radius,
                rejected_outliers=self._rejected,
            )  # fmt: skip
        if self._deviation:
            cell = self._cell(mean)
            dq_p, dq_d = float(self.mu[0, cell]), float(self.mu[1, cell])
            if dq_p * dq_p > 9.0 * prior[0] or dq_d * dq_d > 9.0 * prior[1]:
                flags |= Flag.MODEL_MISMATCH
        return Estimate(
            time_s=t, delta_L_rad=mean, std_rad=std, q_r_rad=joints[0], flags=flags,
            informative_radius_mm=radius, rejected_outliers=self._rejected,
        )  # fmt: skip

    def _multiply(self, log_lik: Array) -> None:
        """Posterior = prior x likelihood, normalised (``log_lik`` up to a constant; shifted
        in place)."""
        log_lik -= log_lik.max()
        p = np.exp(log_lik)
        p *= self.p
        total = float(p.sum())
        if not (total > 1e-250 and math.isfinite(total)):
            # The likelihood's peak lies where the prior has (numerically) no mass: in logs.
            log_post = np.log(np.maximum(self.p, 1e-300)) + log_lik
            p = np.exp(log_post - log_post.max())
            total = float(p.sum())
        p /= total
        self.p = p
        self._moments = None

    def _predict(self, variance: float, jump: float) -> None:
        """The posterior after a random walk of ``variance`` and a jump of probability
        ``jump``."""
        # A variance much below a cell's only blurs within it: it accumulates until it shows.
        variance += self._pending_variance
        self._pending_variance = 0.0
        p, means = self.p, None
        if variance > 0.01 * self.cell_rad**2:
            # The wrapped normal's Fourier coefficients at the integer frequencies of the grid.
            # Beyond exp(-746) the coefficients are exactly 0.0 in doubles: not computed (the
            # inverse transform pads with zeros).
            used = min(self._k2.size, int(math.sqrt(1492.0 / variance)) + 1)
            # The deviation means follow by moment matching (convolving p mu with p), unless
            # the blur stays within a few cells.
            blur_means = self._deviation and variance > (2 * self.cell_rad) ** 2
            stack = self._stack[: 3 if blur_means else 1]
            stack[0] = p
            if blur_means:
                np.multiply(p, self.mu, out=stack[1:])
            spectrum = scipy.fft.rfft(stack)[:, :used]
            spectrum *= np.exp(-0.5 * variance * self._k2[:used])
            blurred = scipy.fft.irfft(spectrum, self.cells, overwrite_x=True)
            p = np.maximum(blurred[0], 0.0, out=blurred[0])
            if blur_means:
                means = blurred[1:]
        else:
            self._pending_variance = variance
        # Normalised and mixed with the uniform density of a jump: p' = scale p + jump / N. A
        # jump lands anywhere with the deviation's prior mean (zero), so the means become
        # ``means`` (p mu, convolved where p is) over p' / scale (the 1e-300 keeps that
        # finite where p is 0 and nothing jumps).
        scale = (1.0 - jump) / float(p.sum())
        if scale == 0.0:  # a certain jump
            self.p = np.full(self.cells, 1.0 / self.cells)
            self.mu[:] = 0.0
        elif means is None and jump == 0.0:
            self.p = p * scale
        else:
            if means is None:
                means = p * self.mu
            weight = p + max(jump / self.cells / scale, 1e-300)
            np.divide(means, weight, out=self.mu)
            self.p = weight * scale
        self._moments = None

    def _likelihood_3d(self, groups: FrameGroups, Q: float, dt: float, present: Array, q_r: float):
        """Per present group and cell d^2 (G', N), the frame's log-likelihood (N,) up to a
        constant, and the Kalman update of the deviation means given which of the present
        groups are inliers (None without a deviation)."""
        s = self.settings
        M = model_error_covariance(
            groups, s.joint_error_white_mm, s.velocity_relative_error, np.array([Q]),
            np.array([dt]),
        )[0]  # fmt: skip
        take = slice(None) if present.all() else present  # views when every group is there
        y, c, JK = groups.y[0, take], groups.c[0, take], groups.JK[0, take]
        S = groups.R_bar[0, take] + M[take]
        G = y.shape[0]
        rows = 8 if self._deviation else 3
        basis = self._basis[:rows]
        if self._deviation:
            # The deviation enters with its Jacobian at the most probable cell's deviation, and
            # its quadratic term with the mean and spread of the shared covariance.
            mu = self.mu
            J = deviation_jacobian(JK[..., :2], JK[..., 2:], mu[:, int(np.argmax(self.p))])
            bias, spread = quadratic_moments(JK[..., 2:], self.Sigma)
            noise = S + spread  # all but the linear deviation term
            S = noise + J @ self.Sigma @ J.mT
            c = c + bias
            np.multiply(mu[0], mu, out=basis[5:7])
            np.multiply(mu[1], mu[1], out=basis[7])
        # The prediction error c + JK expansion_basis(mu) - Rz(q_r + delta)^T y (minus the
        # residual, so that JK enters as it is) of every group and cell is C basis, C (G', 3,
        # rows): with (u_x, u_y) the horizontal part of Rz(q_r)^T y, Rz(delta)^T u is
        # u cos(delta) + (u_y, -u_x) sin(delta).
        cq, sq = math.cos(q_r), math.sin(q_r)
        affine = []
        for (y_x, y_y, y_z), (c_x, c_y, c_z) in zip(y.tolist(), c.tolist(), strict=True):
            u_x, u_y = cq * y_x + sq * y_y, cq * y_y - sq * y_x
            affine += (-u_x, -u_y, c_x, -u_y, u_x, c_y, 0.0, 0.0, c_z - y_z)
        C = np.array(affine).reshape(G, 3, 3)
        if self._deviation:
            C = np.concatenate((C, JK), axis=-1)
        # Whitened by each group's Cholesky factor L, d^2 = |L^-1 C basis|^2.
        white = (_inverse_cholesky(S) @ C).reshape(3 * G, rows) @ basis
        np.square(white, out=white)
        d2 = np.add.reduce(white.reshape(G, 3, -1), axis=1)
        terms = mixture_log_likelihood(d2, 3, s.outlier_probability, s.outlier_scale)
        log_lik = np.add.reduce(terms, axis=0)
        if not self._deviation:
            return d2, log_lik, None

        def update(inlier: Array) -> None:
            self._update_deviation(J, noise, inlier, C, basis)

        return d2, log_lik, update

    def _likelihood_views(self, groups):
        """Per point and cell d^2 (G, N) and the frame's log-likelihood (N,) up to a
        constant, single views (no deviation update: None)."""
        s = self.settings
        W = spd_inverse(groups.R[0])
        predicted = groups.predict(np.array([0]), self.angles[None, :, None])[0]
        residual = groups.z[0][None] - predicted  # (N, G, 2)
        d2 = np.einsum("ngi,gij,ngj->gn", residual, W, residual)
        terms = mixture_log_likelihood(d2, 2, s.outlier_probability, s.outlier_scale)
        return d2, terms.sum(axis=0), None

    def _update_deviation(
        self, J: Array, noise: Array, inlier: Array, C: Array, basis: Array
    ) -> None:
        """Kalman update of every cell's deviation mean with the inlying groups (one gain,
        with the Jacobian J (G', 3, 2) at the most probable cell's deviation; ``noise``: the
        groups' covariances but for that linear deviation term); the prediction errors of
        the cells are ``C basis`` (C (G', 3, k) and basis (k, N))."""
        take = slice(None) if inlier.all() else inlier
        H = J[take].reshape(-1, 2)
        m = H.shape[0]
        HSigma = H @ self.Sigma
        S = HSigma @ H.T
        S.reshape(-1)[block_index(m // 3, 3)] += noise[take].reshape(-1)
        _, _, solution, info = lapack.dgesv(S, HSigma)
        if info != 0:
            raise np.linalg.LinAlgError(f"singular innovation covariance of the deviation ({info})")
        gain = solution.T  # (2, m)
        self.mu -= (gain @ C[take].reshape(m, -1)) @ basis
        (s00, s01), (s10, s11) = (self.Sigma - gain @ HSigma).tolist()
        s01 = 0.5 * (s01 + s10)
        self.Sigma = np.array([[s00, s01], [s01, s11]])


def _inverse_cholesky(S: Array) -> Array:
    """``L^-1`` of the lower Cholesky factors L of G covariances (G, 3, 3): (G, 3, 3).

    The few 3 x 3 factors and inverses are computed in floats (LAPACK's order of operations);
    a covariance that is not positive definite goes through :func:`cholesky` and its jitter.
    """
    inverses = []
    for (a11, _, _), (a21, a22, _), (a31, a32, a33) in S.tolist():
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
        inverses += (m11, 0.0, 0.0, m21, m22, 0.0, m31, m32, m33)
    else:
        return np.array(inverses).reshape(S.shape)
    return np.linalg.inv(cholesky(S)[0])


__all__ = ["DEFAULT_CELLS", "GridFilter"]
