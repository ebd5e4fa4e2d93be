"""The rules of the bending-plane UKF, written once for B independent filters at a time.

:class:`FilterBank` holds B filters (a leading trial axis; the live filter is a bank of one)
and steps all of them through one frame. The same code serves
:class:`~tracker.estimators.ukf.BendingPlaneUKF` (B = 1, any data) and
:func:`~tracker.estimators.ukf_batch.run_ukf_batch` (the Monte Carlo studies).

Each filter carries up to ``max_hypotheses`` Gaussian hypotheses of its state (a Gaussian
sum: the held estimate and a restarted one), each a UKF. Per frame:

1. **Predict** every hypothesis with the process model (linear, so its unscented transform
   is exact: ``F x``, ``F P F^T + Q``), delta_L wrapped, the std capped.
2. **Gate**: per measured group (tip, marker, velocity) the posterior probability that it is
   no gross error, from its residual and its block of the innovation covariance (van der
   Merwe's sigma points, filterpy's weights); groups below one half are rejected, the rest
   fused in one update. Groups that pass alone but contradict each other (the joint NIS
   beyond its gate) are left out one at a time, the least consistent first; a doubtful
   group's update is mixed with the update without it (:mod:`.ukf_update`). The velocity
   has its own gate and model error, offered only after a step that fused no tip.
3. **Restart**: when the leading hypothesis rejects any group of a frame whose closed form is
   informative, unambiguous (not nearly straight relative to noise plus model error) and
   self-consistent, a hypothesis starts there with prior weight ``jump probability`` times
   the frame's marginal likelihood under a uniform angle, against the held hypotheses'
   marginal likelihoods: the following frames keep what they support. The first filter
   state and a state whose std has outgrown ``reacquire_std_rad`` come from the same closed
   form, under the same conditions.
4. **Mismatch**: the joint-equivalent deviation of the shape is part of the state
   (estimated online, ``Flag.MODEL_MISMATCH`` when it is beyond three prior stds); frames
   rejected as a whole ``reacquire_after_rejections`` times in a row with an informative but
   inconsistent closed form restart with the std and the noise inflated by their misfit.
5. **Repair**: a predicted covariance that is not positive definite (or not finite) is
   replaced by the last good state with a re-initialised covariance; an innovation
   covariance that cannot be factorised leaves the hypothesis at its prediction.

The reported estimate is the moment-matched Gaussian of the hypotheses (circular mean), so a
filter torn between two hypotheses says so with a large std; hypotheses that come to agree
are merged.

The per-frame rules are compiled (numba) in :mod:`tracker.estimators.ukf_rules` and
:mod:`tracker.estimators.ukf_gate` (the update's rules per hypothesis), on the
arithmetic of :mod:`tracker.estimators.ukf_kernels` and
:mod:`tracker.estimators.measurement_kernels`: one loop over trials and hypotheses per stage,
for a bank of one as for thousands. This class keeps the order of a step and what happens
rarely: a covariance repair, the closed-form start, restart and added hypothesis, the weights
and merging of several hypotheses, and the single views' projections (numpy).

filterpy's role: its sigma-point weights are used here, and its
:class:`~filterpy.kalman.UnscentedKalmanFilter` is the step-by-step reference of the tests
(heavy tail and model error off: a predict and an update of a bank of one equal filterpy's).
It is not used at run time: it keeps one filter in mutable attributes and fuses whatever it
is given, whereas these rules need per-group statistics before the update, several
hypotheses per filter and a batch axis.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints

from tracker.estimators import (
    measurement_kernels,
    ukf_gate,
    ukf_kernels,
    ukf_rules,
    ukf_run,
    ukf_step,
)
from tracker.estimators._linalg import (
    COVARIANCE_JITTER,
    COVARIANCE_JITTER_FLOOR,
    CovarianceError,
    cholesky,
    sigma_sqrt,
    spd_inverse,
)
from tracker.estimators.deviation import deviation_prior, quadratic_moments
from tracker.estimators.measurement import (
    FrameFit,
    FrameGroups,
    behind_camera,
    check_measurement_covariance,
    fit_frame,
    group_coefficients,
    is_every_trial,
    jump_probability,
    offered_velocity,
    outlier_threshold,
    trig_table,
    velocity_offered,
    wrap,
)
from tracker.estimators.ukf_settings import UKFSettings, gate_threshold
from tracker.estimators.ukf_update import (
    StepResult,
    UpdateResult,
    doubt_threshold,
    joint_gates,
    merge_agreeing,
)
from tracker.types import Flag

Array = np.ndarray

# Per accepted update, the excess of the model-mismatch noise inflation is multiplied by this.
MISMATCH_DECAY = 0.99
# The model-mismatch inflation of the measurement covariance never exceeds this factor.
MAX_MISMATCH_SCALE = 1e4
_LOG_2PI = math.log(2.0 * math.pi)

# The deviation prior given to the predict kernel when the state has no deviation (unused).
_NO_PRIOR = np.zeros((1, 2))


@lru_cache(maxsize=16)
def _no_gates(G: int) -> Array:
    """No joint-consistency gate for any number of groups (read-only, shared)."""
    gates = np.full(G + 1, np.inf)
    gates.flags.writeable = False
    return gates


_F = {name: flag.value for name, flag in Flag.__members__.items()}
# The flag values the compiled rules set, in their order.
_FLAGS = np.array([_F[name] for name in ukf_rules.FLAG_ORDER], dtype=np.int64)
_FLAGS.flags.writeable = False
_NONE = np.zeros(0, dtype=np.intp)
# The update of a frame that updates no hypothesis.
_NO_UPDATE = UpdateResult(
    b=_NONE, h=_NONE, status=np.zeros(0, dtype=np.int64), nis=np.zeros(0),
    dof=np.zeros(0, dtype=np.int64), rejected=np.zeros(0, dtype=np.int64),
    inlier=np.zeros((0, 0), dtype=bool), fused_tip=np.zeros(0, dtype=bool), innovation=None,
)  # fmt: skip


@lru_cache(maxsize=64)
def _gate_table(probability: float, max_dof: int) -> Array:
    """The consistency gate of a NIS of k degrees of freedom, k = 0 .. max_dof (k = 0: of 1;
    read-only, shared)."""
    table = np.array([gate_threshold(probability, max(k, 1)) for k in range(max_dof + 1)])
    table.flags.writeable = False
    return table


class FilterBank:
    """B independent bending-plane UKFs, each a Gaussian sum of up to ``max_hypotheses``.

    The state of a hypothesis is ``[delta_L]``, then ``delta_L_dot`` with ``include_rate``,
    then the joint-equivalent deviation ``(dq_p, dq_d)`` (mm) when the settings estimate it.

    Parameters
    ----------
    settings : UKFSettings
    n_trials : int
    """

    def __init__(self, settings: UKFSettings, n_trials: int = 1) -> None:
        s = self.settings = settings
        n = self.n = s.state_dim
        self.rate = 1 if s.include_rate else None
        self.deviation = 1 + int(s.include_rate) if s.estimates_deviation else None
        points = MerweScaledSigmaPoints(n, alpha=s.alpha, beta=s.beta, kappa=s.sigma_kappa)
        self.Wm = np.asarray(points.Wm, dtype=float)
        self.Wc = np.asarray(points.Wc, dtype=float)
        # (lambda + n) of the sigma points, computed as filterpy computes it.
        self.spread = (s.alpha**2 * (n + s.sigma_kappa) - n) + n
        self.H = s.max_hypotheses
        self.max_variance = s.max_std_rad**2
        self.min_information = s.uninformative_std_rad**-2
        self.reacquire_variance = s.reacquire_std_rad**2
        # The state components the deviation's decay a scales (f = undecayed + a decayed).
        self._decayed = np.zeros(n)
        if self.deviation is not None:
            self._decayed[self.deviation : self.deviation + 2] = 1.0
        self._undecayed = 1.0 - self._decayed
        # The kernels' indices (-1: not in the state).
        self._rate_index = -1 if self.rate is None else self.rate
        self._deviation_index = -1 if self.deviation is None else self.deviation
        self._rules: dict[tuple[int, int], tuple] = {}
        measurement_kernels.warm_up()
        ukf_kernels.warm_up()
        ukf_rules.warm_up()
        ukf_step.warm_up()
        self.reset(n_trials)

    # ------------------------------------------------------------------ state
    def reset(self, n_trials: int | None = None) -> None:
        B = self.B = self.B if n_trials is None else int(n_trials)
        n, H = self.n, self.H
        self.x = np.zeros((B, H, n))
        self.P = np.broadcast_to(np.eye(n) * self.max_variance, (B, H, n, n)).copy()
        self.log_weight = np.full((B, H), -np.inf)
        self.active = np.zeros((B, H), dtype=bool)
        self.initialised = np.zeros(B, dtype=bool)
        self.time_s = np.full(B, np.nan)
        self.q = np.full((B, 3), np.nan)
        self.rejected = np.zeros(B, dtype=np.int64)
        self.bad_run = np.zeros(B, dtype=np.int64)
        self.mismatch_scale = np.ones(B)
        self.noise_scale = np.ones(B)
        self.tip_fused = np.zeros(B, dtype=bool)
        self.good_x, self.good_P = self.x.copy(), self.P.copy()
        # Fast paths: every trial has at most one hypothesis (``_single``), and it is in slot
        # 0 (``_first_only``: then slot 0 of every trial is each one's leading hypothesis).
        # Either may be False when it is true (then the general path runs), never the reverse.
        self._single = self._first_only = True
        # The predict's Cholesky factors of every hypothesis (B, H, n, n), reused by the
        # update's sigma points in the same step where ``_factor_ok`` (B, H).
        self._factor = np.zeros((B, H, n, n))
        self._factor_ok = np.zeros((B, H), dtype=bool)
        self._no_partial = np.zeros(B, dtype=bool)
        self._held_slot = np.zeros(B, dtype=np.intp)
        # Every trial in order, and slot 0 of each: the hypotheses a bank of one marks.
        self._every = np.arange(B)
        self._slot_0 = np.zeros(B, dtype=np.intp)
        for index in (self._every, self._slot_0):
            index.setflags(write=False)

    def deviation_prior(self, q: Array) -> Array:
        """Prior variance of (dq_p, dq_d) at joint values q (B', 3), mm^2."""
        s = self.settings
        return deviation_prior(q, s.joint_error_mm, s.gain_error)

    def start(self, b: Array, delta_L: Array, std: Array, q: Array | None = None) -> None:
        """(Re-)start trials b with one hypothesis N(delta_L, std^2) (deviation: its prior)."""
        self.active[b] = False
        self.log_weight[b] = -np.inf
        self.active[b, 0] = True
        self.log_weight[b, 0] = 0.0
        self._set(b, np.zeros(b.size, dtype=np.intp), delta_L, std, q)
        self.initialised[b] = True
        self.bad_run[b] = 0

    def _set(self, b: Array, h: Array, delta_L: Array, std: Array, q: Array | None) -> None:
        n, s = self.n, self.settings
        x = np.zeros((b.size, n))
        x[:, 0] = wrap(delta_L)
        P = np.zeros((b.size, n, n))
        P[:, 0, 0] = np.minimum(std**2, self.max_variance)
        if self.rate is not None:
            P[:, self.rate, self.rate] = s.initial_rate_std_rad_s**2
        if self.deviation is not None:
            k = self.deviation
            q = self.q[b] if q is None else q
            prior = self.deviation_prior(np.nan_to_num(q))
            P[:, k, k], P[:, k + 1, k + 1] = prior[:, 0], prior[:, 1]
        self.x[b, h], self.P[b, h] = x, P
        self.good_x[b, h], self.good_P[b, h] = x, P

    def velocity_offered(self) -> Array:
        """Which trials would fuse a velocity in their next step (B,)."""
        return velocity_offered(self.settings, self.tip_fused)

    def leading(self) -> Array:
        """Index of each trial's heaviest hypothesis."""
        return ukf_rules.leading(self.active, self.log_weight)

    def weights(self) -> Array:
        """Normalised weights of the hypotheses (B, H), 0 where inactive."""
        return np.where(self.active, np.exp(self.log_weight - self._log_total()[:, None]), 0.0)

    def _log_total(self) -> Array:
        lw = np.where(self.active, self.log_weight, -np.inf)
        top = np.max(lw, axis=1)
        top = np.where(np.isfinite(top), top, 0.0)
        return top + np.log(np.maximum(np.sum(np.exp(lw - top[:, None]), 1), 1e-300))

    # ------------------------------------------------------------------ one frame
    def step(self, time_s: Array, q: Array, frame, partial: Array | None = None) -> StepResult:
        """Predict every filter to its frame and fuse the frame.

        Parameters
        ----------
        time_s : array (B,)
        q : array (B, 3)
            Joint values (the process model sees the base turn and the joints move).
        frame : FrameGroups, ViewGroups or None
            The measurement groups (None: nothing measured).
        partial : array of bool (B,), optional
            Trials whose frame lacks part of its data (reported as ``Flag.PARTIAL``).
        """
        s, B = self.settings, self.B
        running = self.initialised.copy()
        time_s = np.ascontiguousarray(time_s, dtype=float)
        q = np.ascontiguousarray(q, dtype=float)
        partial = self._no_partial if partial is None else np.ascontiguousarray(partial, bool)
        # The process model of the running trials' hypotheses (ukf_rules.begin_step); the
        # predicted covariances' factors are kept for the update's sigma points.
        process = (
            time_s, q, self.time_s, self.q, partial, self.x, self.P, self.good_x, self.good_P,
            self.active, running, s.process_noise_rad2_s, s.rotation_noise_gain_rad,
            s.joint_error_mm, s.gain_error, s.deviation_length_mm, s.deviation_rate_per_s,
            s.rate_process_noise_rad2_s3, self.max_variance, s.initial_rate_std_rad_s**2,
            self._deviation_index, self._rate_index, _FLAGS,
        )  # fmt: skip
        fused_tip = np.zeros(B, dtype=bool)
        reported = None
        measured_frame = frame is not None and frame.present.any()
        terms = None
        if measured_frame and isinstance(frame, FrameGroups):
            frame = offered_velocity(frame, s, self.tip_fused)
            # A 3-D frame: the predict, the frame's terms and, in the usual case, the update
            # and the report in one call (ukf_step).
            c = np.ascontiguousarray
            G = frame.present.shape[1]
            low, high = s.noise_scale_bounds
            scale = self.noise_scale * self.mismatch_scale
            stage, flags, dt, turn, Q, prior, self._factor_ok, self._factor, *rest = (
                ukf_step.step_3d(
                    *process, c(frame.R_bar), c(frame.present), self.reacquire_variance,
                    c(frame.c), frame.n_positions, c(frame.JK), frame.has_velocity_group,
                    c(frame.u_norm_mm_s, dtype=float), s.joint_error_white_mm,
                    s.velocity_relative_error, self._first_only, self._every, self._slot_0,
                    self.log_weight, self.mismatch_scale, MISMATCH_DECAY, scale, self.spread,
                    c(frame.y), c(frame.q), self.Wm, self.Wc, *self._update_rules(G, 3)[:-1],
                    self.rejected, self.bad_run, fused_tip, self.noise_scale, s.estimate_noise,
                    _gate_table(s.gate_probability, 3 * G), s.noise_forgetting, low, high,
                    self.initialised,
                )
            )  # fmt: skip
            terms = rest[:6]
            if stage == ukf_step.FINISHED_UPDATE:
                return self._finish_fused(
                    frame, rest[6:], flags, dt, turn, prior, fused_tip, scale, terms
                )
        else:
            flags, dt, turn, Q, prior, self._factor_ok, self._factor = ukf_rules.begin_step(
                *process
            )
        out = StepResult(
            delta_L_rad=None, std_rad=None, flags=flags, nis=np.full(B, np.nan),
            nis_dof=np.zeros(B, dtype=np.int64), rejected=None, radius_mm=np.zeros(B),
            innovation=[None] * B,
        )  # fmt: skip
        if not measured_frame:
            flags |= _F["NO_MEASUREMENT"]
            flags |= np.where(running, _F["HELD"], _F["NOT_INITIALISED"])
        else:
            if terms is None:
                frame = offered_velocity(frame, s, self.tip_fused)
            reported = self._fuse(frame, running, Q, dt, turn, prior, flags, out, fused_tip,
                                  terms)  # fmt: skip
        self.tip_fused = fused_tip
        if reported is None:
            reported = ukf_rules.report(
                self.x, self.P, self.active, self.log_weight, self.initialised, prior,
                self._deviation_index, flags, _FLAGS,
            )  # fmt: skip
        out.delta_L_rad, out.std_rad = reported
        out.rejected = self.rejected.copy()
        return out

    def run_3d(self, frames, start: int, out: tuple) -> int:
        """Steps of a bank of one through assembled 3-D frames from ``start`` on, while they
        are usual steps (:func:`~tracker.estimators.ukf_run.run_3d`, whose arguments
        ``frames`` carries: ``regular``, ``time_s``, ``q``, ``partial``, ``y``, ``c``,
        ``R_bar``, ``JK``, ``present``, ``u_norm_mm_s``, ``has_velocity``, ``n_positions``);
        the estimates go to ``out`` (its ``out_*`` arrays, in order).

        Returns the first frame not stepped (its state is the one before it): the caller
        steps it with :meth:`step`.
        """
        if not (self.B == 1 and self._first_only and self.initialised[0]):
            return start  # the general path: the start, or several hypotheses
        s = self.settings
        positions, G = frames.n_positions, frames.y.shape[1]
        rules, rules_all = self._update_rules(positions, 3), self._update_rules(G, 3)
        low, high = s.noise_scale_bounds
        (stop, self.tip_fused, self._first_only, self._single, self._factor_ok,
         self._factor) = ukf_run.run_3d(
            start, frames.regular, frames.time_s, frames.q, frames.partial, frames.y,
            frames.c, frames.R_bar, frames.JK, frames.present, frames.u_norm_mm_s,
            frames.has_velocity, positions, self.time_s, self.q, self.x, self.P, self.good_x,
            self.good_P, self.active, self.initialised, self.log_weight, self.mismatch_scale,
            self.noise_scale, self.rejected, self.bad_run, self.tip_fused, self._first_only,
            self._single, self._factor_ok, self._factor, s.process_noise_rad2_s,
            s.rotation_noise_gain_rad, s.joint_error_mm, s.gain_error, s.deviation_length_mm,
            s.deviation_rate_per_s, s.rate_process_noise_rad2_s3, self.max_variance,
            s.initial_rate_std_rad_s**2, self._deviation_index, self._rate_index, _FLAGS,
            self.reacquire_variance, s.joint_error_white_mm, s.velocity_relative_error,
            self._every, self._slot_0, MISMATCH_DECAY, self.spread, self.Wm, self.Wc,
            *rules[:4], rules[4], rules_all[4], rules[5], s.estimate_noise,
            _gate_table(s.gate_probability, 3 * positions), _gate_table(s.gate_probability, 3 * G),
            s.noise_forgetting, low, high, s.use_velocity, s.velocity_is_finite_difference,
            *out,
        )  # fmt: skip
        return int(stop)

    def _finish_fused(self, frame, results, flags, dt, turn, prior, fused_tip, scale, terms
                      ) -> StepResult:  # fmt: skip
        """The rest of a step that :func:`~tracker.estimators.ukf_step.step_3d` updated: the
        innovation shown, and what stays in Python when a trial needs it (the closed form,
        several hypotheses)."""
        # update_3d's (status, nis, dof, rejected) are already in the bank and in the flags.
        (_, _, _, _, _, shown, _, spawn, first, row, closed_form, first_only, single, finished,
         mean, std, nis, nis_dof, innovation) = results  # fmt: skip
        B = self.B
        out = StepResult(
            delta_L_rad=None, std_rad=None, flags=flags, nis=nis, nis_dof=nis_dof,
            rejected=None, radius_mm=terms[4], innovation=[None] * B,
        )  # fmt: skip
        if B == 1 and row[0] >= 0 and shown[row[0]]:
            out.innovation[0] = innovation
        self.tip_fused = fused_tip
        if finished:
            self._first_only, self._single = first_only, single
        else:
            if closed_form:
                jump = jump_probability(self.settings.jump_rate_per_s, self.settings.jump_per_rad,
                                        dt, turn)  # fmt: skip
                self._closed_form(frame, terms[5], scale, first, terms[2], spawn, jump, flags,
                                  fused_tip)  # fmt: skip
            self._normalise()
            mean, std = ukf_rules.report(
                self.x, self.P, self.active, self.log_weight, self.initialised, prior,
                self._deviation_index, flags, _FLAGS,
            )  # fmt: skip
        out.delta_L_rad, out.std_rad = mean, std
        out.rejected = self.rejected.copy()
        return out

    def prepare_rules(self, n_points: int, n_views: int = 2) -> None:
        """Work out now the update's rules and gate tables of every frame that ``n_points``
        points (the tip and the markers) seen in ``n_views`` views can make: 3-D frames of
        those points with and without a velocity, and single-view frames of up to all of
        them in every view. Otherwise the first frame of each kind pays for them (their
        quantiles come from scipy, whose first call alone took about 1 ms): the live loop's
        first frame did."""
        p = self.settings.gate_probability
        groups = [(G, 3) for G in range(1, n_points + 2)]
        groups += [(G, 2) for G in range(1, n_points * n_views + 1)]
        for G, d in groups:
            self._update_rules(G, d)
            _gate_table(p, G * d)

    def _update_rules(self, G: int, d: int) -> tuple:
        """The update's rules for G groups of dimension d: outlier probability and scale,
        the outlier and doubt thresholds, the joint gates, the least information of an
        update and the flag values (cached per bank)."""
        key = (G, d)
        rules = self._rules.get(key)
        if rules is None:
            s = self.settings
            p, k = s.outlier_probability, s.outlier_scale
            threshold = outlier_threshold(d, p, k)
            if math.isfinite(threshold) and G > 1:
                gates = joint_gates(s.gate_probability, d, G)
            else:
                gates = _no_gates(G)
            rules = self._rules[key] = (
                p,
                k,
                threshold,
                doubt_threshold(d, p, k),
                gates,
                self.min_information,
                _FLAGS,
            )
        return rules

    def _marked(self, mask: Array) -> tuple[Array, Array, Array | slice]:
        """The hypotheses marked in ``mask`` (B, H) as indices (b, h), and the trial rows to
        read per hypothesis: ``slice(None)`` when they are the first slot of every trial in
        order (a bank of one's usual case: views instead of gathers), else b."""
        if self._first_only and mask[:, 0].all():
            # mask lies within the active hypotheses, all in slot 0: it is slot 0 of all.
            return self._every, self._slot_0, slice(None)
        # Contiguous copies: np.nonzero's are strided views, a type the kernels would compile
        # again for in the middle of a run.
        b, h = (np.ascontiguousarray(index, dtype=np.intp) for index in np.nonzero(mask))
        every = is_every_trial(b, self.B) and not h.any()
        return b, h, slice(None) if every else b

    # ------------------------------------------------------------------ fuse
    def _fuse(self, frame, running, Q, dt, turn, prior, flags, out, fused_tip, terms):
        """Update with a measured frame. ``terms``: what ``begin_frame_3d`` computed of a 3-D
        frame (usable, measured, all_wide, updating, radius, M); None for single views.

        Returns the estimate (mean, std) where it was reported with the update, else None.
        """
        s = self.settings
        B = self.B
        present = frame.present
        three_d = terms is not None
        if three_d:
            usable, measured, all_wide, updating, out.radius_mm, M = terms
        else:
            usable, measured, all_wide, updating = ukf_rules.prepare_fuse(
                np.ascontiguousarray(frame.noise(slice(None))), present, running, self.active,
                self.P, self.reacquire_variance, flags, _FLAGS,
            )  # fmt: skip
            out.radius_mm, M = frame.radius_mm(), None
        if not usable:
            check_measurement_covariance(frame.noise(slice(None)), present)  # raises, naming it
        scale = self.noise_scale * self.mismatch_scale
        marked = self._marked(updating)
        update = self._update(frame, marked, M, scale) if marked[0].size else _NO_UPDATE
        G, d = present.shape[1], frame.dim
        low, high = s.noise_scale_bounds
        # The report follows each trial's leading hypothesis.
        spawn, first, row, closed_form, first_only, single, finished, mean, std = (
            ukf_rules.finish_update(
                update.b, update.h, update.status, update.nis, update.dof, update.rejected,
                update.fused_tip, self.active, self.log_weight, running, all_wide, measured,
                three_d, flags, out.nis, out.nis_dof, self.rejected, self.bad_run, fused_tip,
                self.noise_scale, s.estimate_noise, _gate_table(s.gate_probability, G * d),
                s.noise_forgetting, low, high, _FLAGS, self.x, self.P, self.initialised,
                prior, self._deviation_index,
            )
        )  # fmt: skip
        if B == 1 and row[0] >= 0:
            out.innovation[0] = update.innovation[row[0]]
        if finished:
            self._first_only, self._single = first_only, single
            return mean, std
        if closed_form:
            # Data the leading hypothesis does not explain, in part or as a whole: weigh a
            # hypothesis started from the frame alone against it.
            jump = jump_probability(s.jump_rate_per_s, s.jump_per_rad, dt, turn)
            self._closed_form(frame, M, scale, first, all_wide, spawn, jump, flags, fused_tip)
        self._normalise()
        return None

    def _closed_form(self, frame, M, scale, first, all_wide, spawn, jump, flags, fused_tip):
        """Start, restart or add a hypothesis from the global fit of the frame alone."""
        s = self.settings
        b = np.flatnonzero(first | all_wide | spawn)
        g = frame.select(b) if b.size < self.B else frame
        # The frame's own information: noise, white model error and the deviation's prior.
        prior = self.deviation_prior(g.q) if s.estimates_deviation else np.zeros((b.size, 2))
        J = g.J
        # The deviation's quadratic term has a mean and a covariance under its prior.
        prior_cov = prior[:, None, :, None] * np.eye(2)
        bias, spread = quadratic_moments(g.K, prior_cov)
        Sigma = g.R_bar * scale[b, None, None, None] + M[b] + spread
        Sigma = Sigma + np.einsum("bgij,bj,bgkj->bgik", J, prior, J)
        present = g.present
        Sigma = np.where(present[..., None, None], Sigma, np.eye(3))
        W = np.linalg.inv(Sigma)
        coefficients = group_coefficients(g.y, g.c + bias, W, g.q_r)
        # The frame's (expected) Fisher information per group: the model's slope e_z x c.
        model = g.c + bias
        slope = np.zeros_like(model)
        slope[..., 0], slope[..., 1] = -model[..., 1], model[..., 0]
        group_information = np.einsum("bgi,bgij,bgj->bg", slope, W, slope)
        fit = self._fit(coefficients, group_information, present)
        dof = fit.dof
        std = fit.std_rad
        if s.initial_std_rad is not None:
            std = np.maximum(std, s.initial_std_rad)
        informative = (fit.std_rad < s.uninformative_std_rad) & (
            fit.sign_evidence >= s.min_sign_evidence
        )
        gates = np.array([gate_threshold(s.gate_probability, max(int(d) - 1, 1)) for d in dof])
        # Consistent: the cost within its chi-square gate, and no group a gross error at the
        # fit (a frame with a wrong point would start the filter off by its error).
        d2 = np.einsum("bgk,kb->bg", coefficients, trig_table(fit.delta_L_rad))
        worst = np.max(np.where(present, d2, 0.0), axis=1)
        consistent = (fit.cost <= gates) & (
            worst <= outlier_threshold(3, s.outlier_probability, s.outlier_scale)
        )
        misfit = np.sqrt(np.maximum(1.0, fit.cost / np.maximum(dof - 1, 1)))
        good = informative & consistent
        bad = informative & ~consistent
        self.bad_run[b[bad]] += 1
        limit = s.reacquire_after_rejections
        mismatch = (
            bad
            & bool(limit)
            & (self.bad_run[b] >= limit)
            & (fit.std_rad * misfit < s.uninformative_std_rad)
        )
        # Restarts of a trial without a usable prior, and mismatch restarts.
        restart = (good & ~spawn[b]) | mismatch
        if restart.any():
            r = b[restart]
            inflate = np.where(mismatch[restart], misfit[restart], 1.0)
            self.mismatch_scale[r] = np.where(
                mismatch[restart],
                np.minimum(self.mismatch_scale[r] * inflate**2, MAX_MISMATCH_SCALE),
                self.mismatch_scale[r],
            )
            self.start(r, fit.delta_L_rad[restart], std[restart] * inflate)
            flags[r] &= ~(_F["HELD"] | _F["OUTLIER_REJECTED"] | _F["NOT_INITIALISED"])
            flags[r] |= np.where(mismatch[restart], _F["MODEL_MISMATCH"], 0)
            fused_tip[r] = present[restart, 0]
        # A jump hypothesis beside the held one(s).
        jumping = good & spawn[b] & ~mismatch
        if jumping.any():
            self._spawn(b[jumping], fit, std, jumping, Sigma[jumping], present[jumping], jump)
            fused_tip[b[jumping]] |= present[jumping, 0]
            # Where the new hypothesis leads, the estimate is no longer held.
            taken = b[jumping][self.leading()[b[jumping]] != self._held_slot[b[jumping]]]
            flags[taken] &= ~_F["HELD"]
        # Frames that could not (re)start the filter.
        idle = ~restart
        start_idle = idle & first[b]
        wide_idle = idle & all_wide[b]
        why = np.where(informative, _F["OUTLIER_REJECTED"], _F["UNINFORMATIVE"])
        self.rejected[b[start_idle & bad & ~mismatch]] += 1
        flags[b[start_idle]] |= _F["NOT_INITIALISED"] | why[start_idle]
        flags[b[wide_idle]] |= _F["HELD"] | why[wide_idle]

    @staticmethod
    def _fit(coefficients: Array, group_information: Array, present: Array) -> FrameFit:
        """The global fit of the present groups."""
        return fit_frame(
            np.einsum("bgk,bg->bk", coefficients, present), 3 * present.sum(axis=1),
            np.sum(group_information * present, axis=1),
        )  # fmt: skip

    def _spawn(self, b, fit, std, chosen, Sigma, present, jump) -> None:
        """Add the closed-form hypothesis of trials b with weight jump x its marginal; the
        held hypotheses keep ``1 - jump`` of theirs."""
        s = self.settings
        logdet = np.linalg.slogdet(Sigma)[1]
        n_groups = present.sum(axis=1)
        # log of the frame's likelihood averaged over a uniform delta_L (Laplace's method).
        log_marginal = (
            n_groups * math.log1p(-s.outlier_probability)
            - 0.5 * np.sum(present * (logdet + 3 * _LOG_2PI), axis=1)
            - 0.5 * fit.cost[chosen]
            + 0.5 * np.log(2 * math.pi / np.maximum(fit.information[chosen], 1e-300))
            - _LOG_2PI
        )
        p = np.minimum(jump[b], 0.5)
        self.log_weight[b] += np.log1p(-p)[:, None]
        log_w = np.log(np.maximum(p, 1e-300)) + log_marginal
        self._held_slot[b] = self.leading()[b]
        # The new hypothesis takes a free slot, or the weakest one if it is heavier.
        lw = np.where(self.active[b], self.log_weight[b], -np.inf)
        slot = np.argmin(lw, axis=1)
        take = log_w > lw[np.arange(b.size), slot]
        b, slot = b[take], slot[take]
        self._single = self._first_only = False
        self.active[b, slot] = True
        self.log_weight[b, slot] = log_w[take]
        self._set(b, slot, fit.delta_L_rad[chosen][take], std[chosen][take], None)

    def _normalise(self) -> None:
        self._first_only, self._single = ukf_rules.normalise_single(self.active, self.log_weight)
        if self._single:
            return
        if self._merge_agreeing():
            self._normalise()
            return
        s = self.settings
        total = self._log_total()
        self.log_weight = np.where(self.active, self.log_weight - total[:, None], -np.inf)
        weak = self.active & (self.log_weight < math.log(max(s.hypothesis_floor, 1e-300)))
        keep = np.zeros_like(weak)
        keep[np.arange(self.B), self.leading()] = True
        drop = weak & ~keep
        if drop.any():
            self.active[drop] = False
            self._normalise()

    def _merge_agreeing(self) -> bool:
        """Merge hypotheses that have come to agree with the leading one
        (:func:`~tracker.estimators.ukf_update.merge_agreeing`); whether any was merged."""
        merged = merge_agreeing(self.x, self.P, self.log_weight, self.active, self.leading())
        if merged.any():
            self.good_x[merged], self.good_P[merged] = self.x[merged], self.P[merged]
        return bool(merged.any())

    # ------------------------------------------------------------------ update
    def _update(self, frame, marked: tuple, M: Array | None, scale: Array) -> UpdateResult:
        """filterpy's UKF update of the ``marked`` hypotheses (:meth:`_marked`), with a gate
        per group.

        3-D data are compared in the model frame at each hypothesis' prior mean (the
        measured vectors turned by ``-(q_r + x_0)``, a fixed rotation of the data), where the
        rotation-invariant noise and the model error need no turning. The innovation
        covariance ``S = sum_s Wc dz dz^T + R``; its diagonal blocks give each group's
        squared residual and so whether it is an outlier; the inlying groups are fused in
        one update (gain ``Pxz S^-1``, ``P - K S K^T``), the others padded with zero rows and
        unit noise.
        """
        b, h, rows = marked
        r = b.size
        G, d = frame.present.shape[1], frame.dim
        rules = self._update_rules(G, d)
        if isinstance(frame, FrameGroups):
            c = np.ascontiguousarray
            status, nis, dof, rejected, inlier, shown, rho = ukf_gate.update_3d(
                b, h, self.x, self.P, self._factor, self._factor_ok, self.good_x, self.good_P,
                self.log_weight, self.mismatch_scale, MISMATCH_DECAY, self.spread, c(frame.c),
                c(frame.JK), c(frame.y), c(frame.q), c(frame.R_bar), scale, M,
                c(frame.present), frame.has_velocity_group, self.Wm, self.Wc,
                self._deviation_index, self._rate_index, *rules,
            )  # fmt: skip
        elif frame.cameras is not None:
            # Single views of known cameras: projected and updated in one call as well.
            status, nis, dof, rejected, inlier, shown, rho, least_depth = (
                ukf_gate.update_views(
                    b, h, self.x, self.P, self._factor, self._factor_ok, self.good_x,
                    self.good_P, self.log_weight, self.mismatch_scale, MISMATCH_DECAY,
                    self.spread, float(frame.q[0, 0]), *frame.cameras, frame.z, frame.R, scale,
                    frame.present, self.Wm, self.Wc, *rules,
                )
            )  # fmt: skip
            if least_depth <= 0.0:
                raise behind_camera(least_depth)
        else:
            # Views of another kind: projected by their own method, the rules the same.
            P, factor, ok_sigma = ukf_kernels.row_factors(
                b, h, self.P, self._factor, self._factor_ok
            )
            x = self.x[b, h]
            S, rho, Pxz, d2, _ = frame.innovation(
                rows, x, factor, self.spread, scale[rows], M, self.Wm, self.Wc,
                self._rate_index, self._deviation_index,
            )  # fmt: skip
            x_post, P_post, nis, dof, log_lik, inlier, status, rejected, done, shown = (
                ukf_gate.gate_and_fuse(
                    S, rho, Pxz, d2, frame.present[rows], ok_sigma, x, P, d, *rules
                )
            )
            ukf_gate.commit_update(
                b, h, done, x_post, P_post, log_lik, self.x, self.P, self.good_x, self.good_P,
                self.log_weight, self.mismatch_scale, MISMATCH_DECAY,
            )  # fmt: skip
        innovation = None
        if self.B == 1:
            # The fused residuals of each shown update (the inlying groups').
            rho_g = rho.reshape(r, G, d)
            if r == 1:
                innovation = [rho_g[0, inlier[0]].ravel() if shown[0] else None]
            else:
                innovation = [rho_g[i, inlier[i]].ravel() if shown[i] else None for i in range(r)]
        return UpdateResult(
            b=b, h=h, status=status, nis=nis, dof=dof, rejected=rejected, inlier=inlier,
            fused_tip=inlier[:, 0] & frame.is_tip_group(0), innovation=innovation,
        )  # fmt: skip


__all__ = [
    "COVARIANCE_JITTER",
    "COVARIANCE_JITTER_FLOOR",
    "CovarianceError",
    "FilterBank",
    "StepResult",
    "check_measurement_covariance",
    "cholesky",
    "sigma_sqrt",
    "spd_inverse",
]
