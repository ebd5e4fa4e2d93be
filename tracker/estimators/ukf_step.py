"""A whole filter step with a frame of 3-D groups, compiled (numba): one call per frame.

:meth:`~tracker.estimators.ukf_core.FilterBank.step` with a 3-D frame runs the stages of
:mod:`tracker.estimators.ukf_rules` and :mod:`tracker.estimators.ukf_gate` in order: the
predict and the frame's terms (:func:`~tracker.estimators.ukf_rules.begin_frame_3d`), the
update of the hypotheses that update (:func:`~tracker.estimators.ukf_gate.update_3d`) and
each trial's report (:func:`~tracker.estimators.ukf_rules.finish_update`). Called one by one
from Python, with the bank's glue between them, they cost a frame about 90 us, most of it
in passing arguments and results across the boundary; :func:`step_3d` makes the same calls
in the same order inside one compiled function, so that a frame crosses it once.

It goes as far as the usual case allows: every trial's hypothesis in slot 0 updates
(``first_only``, a bank of one tracking), and stops after the predict otherwise (stage 1:
the caller goes on with the general path from there, as before). Its results are those of
the stages' own calls, to the last bit: the same kernels, the same arguments.
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from tracker.estimators.ukf_gate import update_3d
from tracker.estimators.ukf_rules import begin_frame_3d, finish_update

# How far step_3d went.
STOPPED_UNUSABLE = 0
"""A measurement covariance of the frame is not usable: nothing updated (the caller raises)."""
STOPPED_AFTER_PREDICT = 1
"""The predict and the frame's terms only: the general path goes on from them."""
FINISHED_UPDATE = 2
"""The update and the report of every trial's slot 0 are done."""


@numba.njit(cache=True, nogil=True)
def step_3d(
    time_s, q, last_time_s, last_q, partial, x, P, good_x, good_P, active, running,
    process_noise, rotation_gain, joint_error, gain_error, deviation_length, deviation_rate,
    rate_noise, max_variance, initial_rate_variance, deviation, rate, flag, R_bar, present,
    reacquire_variance, c, n_positions, JK, has_velocity, u_norm, white_mm, relative_error,
    first_only, every, slot_0, log_weight, mismatch_scale, mismatch_decay, scale, spread, y,
    q_frame, Wm, Wc, outlier_probability, outlier_scale, threshold, doubt, gates,
    min_information, rejected, bad_run, tip_fused, noise_scale, adapt, gate_table, forgetting,
    low, high, initialised,
):  # fmt: skip
    """:func:`begin_frame_3d`, then, where every trial's slot 0 updates, :func:`update_3d` of
    those hypotheses and :func:`finish_update` (the arguments are theirs, in their order;
    ``every`` and ``slot_0`` are the rows; ``scale``, the noise scale times the mismatch
    scale before the step).

    Returns ``(stage, begin_frame_3d's 13 results, update_3d's 7, finish_update's 9, nis,
    nis_dof, innovation)``: the last 19 are empty placeholders unless ``stage`` is
    :data:`FINISHED_UPDATE`; then ``nis`` and ``nis_dof`` (B,) are the step's report and,
    for a bank of one, ``innovation`` the fused residuals of the update shown (the inlying
    groups', in order; empty when none is shown).
    """
    (flags, dt, turn, Q, prior, ok, L, usable, measured, all_wide, updating, radius,
     M) = begin_frame_3d(
        time_s, q, last_time_s, last_q, partial, x, P, good_x, good_P, active, running,
        process_noise, rotation_gain, joint_error, gain_error, deviation_length,
        deviation_rate, rate_noise, max_variance, initial_rate_variance, deviation, rate,
        flag, R_bar, present, reacquire_variance, c, n_positions, JK, has_velocity, u_norm,
        white_mm, relative_error,
    )  # fmt: skip
    B = x.shape[0]
    G = present.shape[1]
    stage = FINISHED_UPDATE
    if not usable:
        stage = STOPPED_UNUSABLE
    elif not first_only or B == 0:
        stage = STOPPED_AFTER_PREDICT
    else:
        for t in range(B):
            if not updating[t, 0]:
                stage = STOPPED_AFTER_PREDICT
                break
    empty_i = np.zeros(0, dtype=np.int64)
    empty_b = np.zeros(0, dtype=np.bool_)
    empty_f = np.zeros(0)
    if stage != FINISHED_UPDATE:
        return (
            stage, flags, dt, turn, Q, prior, ok, L, usable, measured, all_wide, updating,
            radius, M, empty_i, empty_f, empty_i, empty_i, np.zeros((0, G), dtype=np.bool_),
            empty_b, np.zeros((0, 3 * G)), empty_b, empty_b, np.zeros(0, dtype=np.intp), False,
            False, False, False, empty_f, empty_f, empty_f, empty_i, empty_f,
        )  # fmt: skip
    out_nis = np.full(B, np.nan)
    out_dof = np.zeros(B, dtype=np.int64)
    status, nis, dof, rejected_groups, inlier, shown, rho = update_3d(
        every, slot_0, x, P, L, ok, good_x, good_P, log_weight, mismatch_scale,
        mismatch_decay, spread, c, JK, y, q_frame, R_bar, scale, M, present, has_velocity, Wm,
        Wc, deviation, rate, outlier_probability, outlier_scale, threshold, doubt, gates,
        min_information, flag,
    )  # fmt: skip
    # Group 0 of a 3-D frame is the tip.
    tip_rows = inlier[:, 0].copy()
    spawn, first, row, closed_form, single_first, single, finished, mean, std = finish_update(
        every, slot_0, status, nis, dof, rejected_groups, tip_rows, active, log_weight,
        running, all_wide, measured, True, flags, out_nis, out_dof, rejected, bad_run,
        tip_fused, noise_scale, adapt, gate_table, forgetting, low, high, flag, x, P,
        initialised, prior, deviation,
    )  # fmt: skip
    innovation = empty_f
    if B == 1 and row[0] >= 0 and shown[row[0]]:
        i = row[0]
        innovation = np.empty(3 * np.sum(inlier[i]))
        k = 0
        for g in range(G):
            if inlier[i, g]:
                innovation[k : k + 3] = rho[i, 3 * g : 3 * g + 3]
                k += 3
    return (
        stage, flags, dt, turn, Q, prior, ok, L, usable, measured, all_wide, updating, radius,
        M, status, nis, dof, rejected_groups, inlier, shown, rho, spawn, first, row,
        closed_form, single_first, single, finished, mean, std, out_nis, out_dof, innovation,
    )  # fmt: skip


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) :func:`step_3d` once per process, with the argument
    types a bank passes (the flag values, the rows and the gate tables are shared read-only
    arrays, a type of their own)."""

    def shared(a):
        a.flags.writeable = False
        return a

    flag = shared(np.arange(1, 9, dtype=np.int64))
    rows = shared(np.zeros(1, dtype=np.intp))
    for n in (1, 3, 4):
        B, H, G = 1, 2, 2
        deviation, rate = (1 if n > 2 else -1), (1 if n == 4 else -1)
        for has_velocity in (True, False):
            x = np.zeros((B, H, n))
            P = np.broadcast_to(np.eye(n), (B, H, n, n)).copy()
            c = np.ones((B, G, 3))
            eye = np.broadcast_to(np.eye(3), (B, G, 3, 3)).copy()
            W = np.full(2 * n + 1, 1.0 / (2 * n + 1))
            step_3d(
                np.zeros(B), np.zeros((B, 3)), np.full(B, np.nan), np.zeros((B, 3)),
                np.zeros(B, dtype=bool), x, P, x.copy(), P.copy(), np.ones((B, H), dtype=bool),
                np.ones(B, dtype=bool), 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, deviation,
                rate, flag, eye, np.ones((B, G), dtype=bool), 1.0, c, G,
                np.zeros((B, G, 3, 5)), has_velocity, np.ones(B), 0.1, 0.1, True, rows, rows,
                np.zeros((B, H)), np.ones(B), 0.99, np.ones(B), 1.0, c.copy(), np.zeros((B, 3)),
                W, W, 0.01, 5.0, 10.0, 5.0, shared(np.full(G + 1, 20.0)), 1.0,
                np.zeros(B, dtype=np.int64), np.zeros(B, dtype=np.int64),
                np.zeros(B, dtype=bool), np.ones(B), True,
                shared(np.full(3 * G + 1, 10.0)), 0.9, 0.5, 2.0, np.ones(B, dtype=bool),
            )  # fmt: skip


__all__ = [
    "FINISHED_UPDATE",
    "STOPPED_AFTER_PREDICT",
    "STOPPED_UNUSABLE",
    "step_3d",
    "warm_up",
]
