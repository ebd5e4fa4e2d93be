"""A filter's steps through a sequence of 3-D frames, compiled (numba): one call per run.

:meth:`~tracker.estimators.ukf.BendingPlaneUKF.run` replays a recording's observations. Each
frame through :meth:`~tracker.estimators.ukf.BendingPlaneUKF.step` pays its crossings into
compiled code (the measurement groups, then :func:`~tracker.estimators.ukf_step.step_3d`)
and the Python around them; :func:`run_3d` loops over frames whose groups were assembled
beforehand for all of them at once, and calls :func:`~tracker.estimators.ukf_step.step_3d`
for each, as the bank's step would, with the same arguments.

It stops at the first frame that needs more than the usual step (a frame the caller marked
irregular, nothing measured, a time out of order, a step that
:func:`~tracker.estimators.ukf_step.step_3d` does not finish): that frame's state is put back
as it was before it, and the caller steps it through the general path, then calls again from
the next frame. The estimates are the live filter's, to the last bit (tested). It is
compiled (or loaded from numba's cache) at its first call in a process.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import literal_unroll

from tracker.estimators.ukf_step import FINISHED_UPDATE, step_3d


@numba.njit(cache=True, nogil=True)
def _keep(kept):
    """Copy each state array of ``kept`` ((array, copy) pairs) into its copy."""
    for pair in literal_unroll(kept):
        pair[1][...] = pair[0]


@numba.njit(cache=True, nogil=True)
def _put_back(kept):
    """Copy each copy of ``kept`` ((array, copy) pairs) back into its state array."""
    for pair in literal_unroll(kept):
        pair[0][...] = pair[1]


@numba.njit(cache=True, nogil=True)
def run_3d(
    start, regular, times, qs, partial, y_all, c_all, R_bar_all, JK_all, present_all, u_all,
    has_velocity_all, n_positions, last_time_s, last_q, x, P, good_x, good_P, active,
    initialised, log_weight, mismatch_scale, noise_scale, rejected, bad_run, tip_fused,
    first_only, single, factor_ok, factor, process_noise, rotation_gain, joint_error,
    gain_error, deviation_length, deviation_rate, rate_noise, max_variance,
    initial_rate_variance, deviation, rate, flag, reacquire_variance, white_mm,
    relative_error, every, slot_0, mismatch_decay, spread, Wm, Wc, outlier_probability,
    outlier_scale, threshold, doubt, gates_positions, gates_all, min_information, adapt,
    table_positions, table_all, forgetting, low, high, offer_velocity, offer_after_tip,
    out_mean, out_std, out_flags, out_nis, out_dof, out_radius, out_rejected, out_innovation,
    out_shown,
):  # fmt: skip
    """The steps of a bank of one from frame ``start`` on, while they are usual ones.

    Frames (N of them): ``regular`` (N,) marks those this loop may take; ``times``,
    ``qs``, ``partial`` are each frame's time, joint values and partial mark; the groups
    ``y_all``, ``c_all`` (N, G, 3), ``R_bar_all`` (N, G, 3, 3), ``JK_all`` (N, G, 3, 5),
    ``present_all`` (N, G) and ``u_all`` (N,) hold the positions' groups and, last (G =
    ``n_positions`` + 1), the velocity's; ``has_velocity_all`` (N,) says which frames have a
    velocity (when it is not offered, or absent, a frame's groups are its positions' alone,
    as :func:`~tracker.estimators.ukf.observation_groups` makes them).

    The bank's arrays (``last_time_s`` to ``bad_run``) are updated in place, the settings
    and rules are the bank's (``gates_*`` and ``table_*`` for the positions alone and with
    the velocity). The estimates go to ``out_*`` (N,); ``out_innovation`` (N, 3 G) with
    ``out_shown`` (N,) its length, -1 where none is shown.

    Returns ``(stop, tip_fused, first_only, single, factor_ok, factor)``: the first frame not
    stepped (N when all were) and the bank's values after the last frame stepped.
    """
    N = times.shape[0]
    B, H, n = x.shape
    G_all = y_all.shape[1]
    # The bank's state, each array with a copy of itself: put back as it was before a frame
    # that needs the general path.
    kept = (
        (last_time_s, last_time_s.copy()), (last_q, last_q.copy()), (x, x.copy()),
        (P, P.copy()), (good_x, good_x.copy()), (good_P, good_P.copy()),
        (active, active.copy()), (initialised, initialised.copy()),
        (log_weight, log_weight.copy()), (mismatch_scale, mismatch_scale.copy()),
        (noise_scale, noise_scale.copy()), (rejected, rejected.copy()),
        (bad_run, bad_run.copy()),
    )  # fmt: skip
    for k in range(start, N):
        if not regular[k]:
            return k, tip_fused, first_only, single, factor_ok, factor
        t = times[k]
        if math.isnan(t) or t < last_time_s[0]:
            return k, tip_fused, first_only, single, factor_ok, factor
        offered = offer_velocity and (not offer_after_tip or not tip_fused[0])
        with_velocity = offered and has_velocity_all[k]
        G = G_all if with_velocity else n_positions
        present = present_all[k : k + 1, :G].copy()
        if not present.any():
            return k, tip_fused, first_only, single, factor_ok, factor
        _keep(kept)
        u = np.zeros(1)
        if with_velocity:
            u[0] = u_all[k]
        fused_tip = np.zeros(1, dtype=np.bool_)
        scale = noise_scale * mismatch_scale
        gates, table = gates_positions, table_positions
        if with_velocity:
            gates, table = gates_all, table_all
        result = step_3d(
            times[k : k + 1].copy(), qs[k : k + 1].copy(), last_time_s, last_q,
            partial[k : k + 1].copy(), x, P, good_x, good_P, active, initialised.copy(),
            process_noise, rotation_gain, joint_error, gain_error, deviation_length,
            deviation_rate, rate_noise, max_variance, initial_rate_variance, deviation, rate,
            flag, R_bar_all[k : k + 1, :G].copy(), present, reacquire_variance,
            c_all[k : k + 1, :G].copy(), n_positions, JK_all[k : k + 1, :G].copy(),
            with_velocity, u, white_mm, relative_error, first_only, every, slot_0, log_weight,
            mismatch_scale, mismatch_decay, scale, spread, y_all[k : k + 1, :G].copy(),
            qs[k : k + 1].copy(), Wm, Wc, outlier_probability, outlier_scale, threshold, doubt,
            gates, min_information, rejected, bad_run, fused_tip, noise_scale, adapt, table,
            forgetting, low, high, initialised,
        )  # fmt: skip
        if result[0] != FINISHED_UPDATE or not result[27]:
            _put_back(kept)
            return k, tip_fused, first_only, single, factor_ok, factor
        # The report, as the bank's step gives it (ukf_core.FilterBank._finish_fused).
        flags, radius, shown, row = result[1], result[12], result[19], result[23]
        factor_ok, factor = result[6], result[7]
        first_only, single = result[25], result[26]
        tip_fused = fused_tip
        out_mean[k] = result[28][0]
        out_std[k] = result[29][0]
        out_flags[k] = flags[0]
        out_nis[k] = result[30][0]
        out_dof[k] = result[31][0]
        out_radius[k] = radius[0]
        out_rejected[k] = rejected[0]
        out_shown[k] = -1
        if row[0] >= 0 and shown[row[0]]:
            innovation = result[32]
            out_shown[k] = innovation.shape[0]
            out_innovation[k, : innovation.shape[0]] = innovation
    return N, tip_fused, first_only, single, factor_ok, factor


__all__ = ["run_3d"]
