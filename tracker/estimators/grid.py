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

The per-cell arithmetic (each group's d^2 on every cell, the likelihood, the posterior and its
moments, the predict's end and the deviation's update) is compiled
(:mod:`tracker.estimators.grid_kernels`, loaded or compiled when a filter is made); the FFTs
and the exponentials stay in scipy and numpy.

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

from models.catheter import Catheter
from tracker.estimators import grid_kernels, measurement_kernels
from tracker.estimators._linalg import cholesky, spd_inverse
from tracker.estimators.deviation import ShapeExpansion, deviation_decay, deviation_prior
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
from tracker.estimators.per_frame import Estimator
from tracker.estimators.ukf import check_observation, observation_groups
from tracker.estimators.ukf_settings import UKFSettings
from tracker.types import Estimate, Flag, Observation

Array = np.ndarray
DEFAULT_CELLS = 2048
_TWO_PI = 2.0 * math.pi


class GridFilter(Estimator):
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
        # The fixed rows of every cell's basis [cos, sin, 1, expansion_basis(mu)].
        self._cos = np.cos(self.angles)
        self._sin = np.sin(self.angles)
        self.mu = np.zeros((2, self.cells))
        # What the prediction convolves: p and, moment matching the means, p mu.
        self._stack = np.empty((3, self.cells))
        self._expansion = ShapeExpansion(catheter)
        grid_kernels.warm_up()
        measurement_kernels.warm_up()
        self.reset()

    def prepare(self, q: Array) -> None:
        """Get ready for a frame at joint values q (3,) (:meth:`BendingPlaneUKF.prepare`)."""
        self._expansion.prepare(q)

    def reset(self) -> None:
        """Forget everything: uniform posterior, not initialised."""
        s = self.settings
        self.p = np.full(self.cells, 1.0 / self.cells)
        self._deviation = s.estimates_deviation
        self._mixture = {
            dim: _mixture_constants(dim, s.outlier_probability, s.outlier_scale) for dim in (2, 3)
        }
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
            mean, var = grid_kernels.circular_moments(
                self.p, self._cos, self._sin, self.angles, self.cell_rad
            )
            self._moments = (float(wrap(mean)), math.sqrt(var + self.cell_rad**2 / 12.0))
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
                d2, update = self._likelihood_3d(groups, Q, dt, present, joints[0])
            else:
                d2, update = self._squared_residuals_views(groups), None
            self._multiply(d2, groups.dim)
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

    def _multiply(self, d2: Array, dim: int) -> None:
        """Posterior = prior x the frame's likelihood, normalised, from the groups' d^2 (G,
        N) of dimension ``dim``."""
        shrink, scale2, ratio, mixture = self._mixture[dim]
        factors = grid_kernels.exponents(d2, shrink, scale2, mixture)
        p, ok = grid_kernels.posterior(self.p, np.exp(factors, out=factors), ratio, mixture)
        if not ok:
            # The likelihood's peak lies where the prior has (numerically) no mass: in logs.
            s = self.settings
            log_lik = np.add.reduce(
                mixture_log_likelihood(d2, dim, s.outlier_probability, s.outlier_scale), axis=0
            )
            log_post = np.log(np.maximum(self.p, 1e-300)) + (log_lik - log_lik.max())
            p = np.exp(log_post - log_post.max())
            p /= float(p.sum())
        self.p = p
        self._moments = None

    def _predict(self, variance: float, jump: float) -> None:
        """The posterior after a random walk of ``variance`` and a jump of probability
        ``jump``."""
        # A variance much below a cell's only blurs within it: it accumulates until it shows.
        variance += self._pending_variance
        self._pending_variance = 0.0
        p, means, blurred = self.p, self.mu, False
        blur_means = False
        if variance > 0.01 * self.cell_rad**2:
            # The wrapped normal's Fourier coefficients at the integer frequencies of the grid.
            # Those below exp(-650) (about 1e-282) are not computed (the inverse transform pads with
            # zeros): what they add is far below what a sum of the posterior's order can
            # hold, and near exp(-708) they and their products turn subnormal, each
            # operation on which costs a hundred ordinary ones.
            used = min(self._k2.size, int(math.sqrt(1300.0 / variance)) + 1)
            # The deviation means follow by moment matching (convolving p mu with p), unless
            # the blur stays within a few cells.
            blur_means = self._deviation and variance > (2 * self.cell_rad) ** 2
            stack = self._stack[: 3 if blur_means else 1]
            stack[0] = p
            if blur_means:
                np.multiply(p, self.mu, out=stack[1:])
            spectrum = scipy.fft.rfft(stack)[:, :used]
            grid_kernels.attenuate(spectrum, variance, self._k2)
            convolved = scipy.fft.irfft(spectrum, self.cells, overwrite_x=True)
            p, blurred = convolved[0], True
            if blur_means:
                means = convolved[1:]
        else:
            self._pending_variance = variance
        # Clipped where the truncated series rings below zero, normalised and mixed with the
        # uniform density of a jump, the deviation means moment matched.
        self.p = grid_kernels.mix_in_jump(p, means, blur_means, self.mu, jump, blurred)
        self._moments = None

    def _likelihood_3d(self, groups: FrameGroups, Q: float, dt: float, present: Array, q_r: float):
        """Per present group and cell d^2 (G', N), and the Kalman update of the deviation
        means given which of the present groups are inliers (None without a deviation)."""
        s = self.settings
        M = model_error_covariance(
            groups, s.joint_error_white_mm, s.velocity_relative_error, np.array([Q]),
            np.array([dt]),
        )[0]  # fmt: skip
        # The kernels take C-contiguous arrays (one compiled version); y is a view.
        C, A, J, noise, S, ok = grid_kernels.group_terms(
            np.ascontiguousarray(groups.y[0]), np.ascontiguousarray(groups.c[0]),
            np.ascontiguousarray(groups.JK[0]), np.ascontiguousarray(groups.R_bar[0]),
            np.ascontiguousarray(M),
            np.ascontiguousarray(present), q_r, self.Sigma, self.p, self.mu, self._deviation,
        )  # fmt: skip
        if not ok:
            # A covariance that is not positive definite: the documented jitter of cholesky.
            A = np.linalg.inv(cholesky(S)[0]) @ C
        d2 = grid_kernels.squared_residuals(A, self._cos, self._sin, self.mu)
        if not self._deviation:
            return d2, None

        def update(inlier: Array) -> None:
            self.Sigma = grid_kernels.update_deviation(
                J, noise, inlier, C, self.Sigma, self._cos, self._sin, self.mu
            )

        return d2, update

    def _squared_residuals_views(self, groups) -> Array:
        """Per point and cell d^2 (G, N), single views."""
        W = spd_inverse(groups.R[0])
        predicted = groups.predict(np.array([0]), self.angles[None, :, None])[0]
        residual = groups.z[0][None] - predicted  # (N, G, 2)
        d2 = np.einsum("ngi,gij,ngj->gn", residual, W, residual)
        return np.ascontiguousarray(d2)


def _mixture_constants(
    dim: int, outlier_probability: float, outlier_scale: float
) -> tuple[float, float, float, bool]:
    """What :func:`grid_kernels.exponents` and :func:`grid_kernels.posterior` take for the
    heavy-tailed likelihood of a group of dimension ``dim``
    (:func:`~tracker.estimators.measurement.mixture_log_likelihood`): ``1 - s^-2``,
    ``s^2``, the inlier component's weight over the outlier's ``(1 - p) / (p s^-dim)`` and
    whether there is an outlier component at all (the Gaussian without)."""
    if outlier_probability <= 0.0:
        return 0.0, 1.0, 0.0, False
    log_outlier = math.log(outlier_probability) - dim * math.log(outlier_scale)
    ratio = (1.0 - outlier_probability) / math.exp(log_outlier)
    return 1.0 - outlier_scale**-2, outlier_scale**2, ratio, True


__all__ = ["DEFAULT_CELLS", "GridFilter"]
