"""The rules of the bending-plane UKF, compiled (numba): what
:class:`~tracker.estimators.ukf_core.FilterBank` does to each of its B filters and their
hypotheses in one frame, written once for the live filter (B = 1) and the trial-batched
studies (docs/design.md, "The UKF" and "Joint consistency and doubtful groups").

A step is a few calls, each one loop over the trials and their hypotheses:

- :func:`begin_step` (with a 3-D frame :func:`begin_frame_3d`): the frame interval, the base
  turn, the process noise, the deviation's prior, the predict of every active hypothesis of
  every running trial, a repair where it is not usable; :func:`prepare_fuse`: which trials
  measured anything and which hypotheses are updated (a wide one beside a narrow one is
  dropped; a trial left with only wide ones restarts from the frame);
- (the update's rules per hypothesis: :mod:`tracker.estimators.ukf_gate`;)
- :func:`apply_update`: each trial's report from its leading hypothesis' update, the run of
  rejected frames, the restart candidates and the adaptive noise scale;
- :func:`normalise_single` and :func:`report`: the weights where a trial has one
  hypothesis, the model-mismatch flag and the moment-matched estimate.

The closed-form start and restart, and the weights and merging of several hypotheses, stay
in Python (:mod:`tracker.estimators.ukf_core`). Flags are passed as integers in the order of
``FLAG_ORDER``.
"""
from __future__ import annotations

import functools
import math

import numba
import numpy as np

from tracker.estimators.linalg_kernels import _JITTER_FLOOR, _cap_row, _wrap
from tracker.estimators.measurement_kernels import horizontal_radius, model_error
from tracker.estimators.ukf_gate import (
    _HELD,
    _MISMATCH,
    _NO_MEASUREMENT,
    _NOT_INITIALISED,
    _OUTLIER,
    _PARTIAL,
    _REPAIRED,
    _UNINFORMATIVE,
    FLAG_ORDER,
    commit_update,
    gate_and_fuse,
    update_3d,
    update_views,
)
from tracker.estimators.ukf_kernels import predict_row


# ------------------------------------------------------------------------------ a step
@numba.njit(cache=True, nogil=True)
def begin_step(
    time_s, q, last_time_s, last_q, partial, x, P, good_x, good_P, active, running,
    process_noise, rotation_gain, joint_error, gain_error, deviation_length, deviation_rate,
    rate_noise, max_variance, initial_rate_variance, deviation, rate, flag,
):  # fmt: skip
    """The process side of one frame for B trials: the predict of the active hypotheses of
    the running trials, in place; a prediction that is not usable (a covariance not positive
    definite or not finite) is repaired from the last good state (:func:`_repair`,
    ``COVARIANCE_REPAIRED``).

    Parameters
    ----------
    time_s : array (B,), q : array (B, 3)
        The frame's times (s) and joint values (rad, mm, mm).
    last_time_s, last_q : arrays (B,), (B, 3)
        The previous frame's (NaN: unknown, no change), overwritten with this frame's.
    partial : bool array (B,)
        Trials whose frame lacks part of its data.
    x, P : arrays (B, H, n), (B, H, n, n)
        The hypotheses, predicted in place.
    good_x, good_P : arrays (B, H, n), (B, H, n, n)
        Their last good states (the repair's).
    active : bool array (B, H); running : bool array (B,)
    process_noise, rotation_gain : float
        Torsion random walk, rad^2/s, and its growth per rad of base turn, rad.
    joint_error, gain_error : float
        The deviation's prior: joint-equivalent std (mm) and relative bending-gain error.
    deviation_length, deviation_rate : float
        The deviation's correlation length in joint travel (mm) and its decay rate (1/s).
    rate_noise, max_variance : float
        The rate's process noise (rad^2/s^3) and the delta_L variance cap (rad^2).
    initial_rate_variance : float
        The rate's least variance after a repair, rad^2/s^2.
    deviation, rate : int
        Indices in the state (-1: none).
    flag : int array
        Flag values in the order of ``FLAG_ORDER``.

    Returns
    -------
    flags : int array (B,)
    dt, turn, Q : arrays (B,)
        Frame interval (s), base turn (rad) and the torsion's process variance (rad^2).
    prior : array (B, 2)
        The deviation's prior variance at the frame's joints, mm^2.
    ok : bool array (B, H)
        Hypotheses whose prediction was usable (False: repaired, with no factor).
    L : array (B, H, n, n)
        Lower Cholesky factors of the predicted covariances (where predicted and ok).
    """
    B, H, n = x.shape
    flags = np.zeros(B, dtype=np.int64)
    dt = np.zeros(B)
    turn = np.zeros(B)
    Q = np.empty(B)
    prior = np.empty((B, 2))
    ok = np.ones((B, H), dtype=np.bool_)
    L = np.zeros((B, H, n, n))
    work = np.empty((n, n))
    for t in range(B):
        known = math.isfinite(last_time_s[t])
        moved = 0.0
        for j in range(3):
            change = 0.0
            # Joint values before the first frame (or after a prior is set) are unknown.
            if known and math.isfinite(last_q[t, j]):
                change = q[t, j] - last_q[t, j]
            if j == 0:
                turn[t] = change
            else:
                moved += abs(change)
            last_q[t, j] = q[t, j]
        if known:
            dt[t] = time_s[t] - last_time_s[t]
        last_time_s[t] = time_s[t]
        Q[t] = process_noise * dt[t] + rotation_gain * abs(turn[t])
        if partial[t]:
            flags[t] = flag[_PARTIAL]
        for j in range(2):
            bend = gain_error * q[t, 1 + j]
            prior[t, j] = joint_error * joint_error + bend * bend
        if not running[t]:
            continue
        decay = math.exp(-abs(moved) / deviation_length - deviation_rate * dt[t])
        for h in range(H):
            if active[t, h]:
                ok[t, h] = predict_row(
                    x[t, h], P[t, h], Q[t], decay, prior[t, 0], prior[t, 1], dt[t], deviation,
                    rate, rate_noise, max_variance, L[t, h], work,
                )  # fmt: skip
                if not ok[t, h]:
                    _repair(x[t, h], P[t, h], good_x[t, h], good_P[t, h], Q[t], max_variance,
                            rate, initial_rate_variance)  # fmt: skip
                    flags[t] |= flag[_REPAIRED]
    return flags, dt, turn, Q, prior, ok, L


@numba.njit(cache=True, nogil=True)
def _repair(x, P, good_x, good_P, Q, max_variance, rate, initial_rate_variance):
    """A hypothesis whose predicted covariance is not usable takes its last good state with a
    re-initialised covariance: the last good variances (their magnitudes; ``max_variance``
    where not finite or zero), delta_L's within [``_JITTER_FLOOR``, ``max_variance``], the
    rate's at least ``initial_rate_variance``; then the frame's process variance ``Q`` and
    the std cap. In place."""
    n = x.shape[0]
    for a in range(n):
        x[a] = good_x[a]
        v = abs(good_P[a, a])
        if not (math.isfinite(v) and v > 0.0):
            v = max_variance
        if a == 0:
            v = min(max(v, _JITTER_FLOOR), max_variance)
        if a == rate:
            v = max(v, initial_rate_variance)
        for c in range(n):
            P[a, c] = v if a == c else 0.0
    P[0, 0] += Q
    _cap_row(P, max_variance)


@numba.njit(cache=True, nogil=True)
def prepare_fuse(noise, present, running, active, P, reacquire_variance, flags, flag):
    """Which hypotheses a frame updates (B trials, H slots).

    Returns ``(usable, measured, all_wide, updating)``: whether every present group's noise
    has positive variances (if not, nothing is changed: the caller raises); the trials that
    measured anything (the others get ``NO_MEASUREMENT`` and ``HELD`` or
    ``NOT_INITIALISED``); the running trials whose hypotheses are all too wide to update
    (delta_L variance beyond ``reacquire_variance``: restarted from the frame); and the
    hypotheses updated (B, H). A wide hypothesis beside a narrow one is dropped (``active``
    changed in place).
    """
    B, G, d = noise.shape[0], noise.shape[1], noise.shape[2]
    H = active.shape[1]
    measured = np.zeros(B, dtype=np.bool_)
    all_wide = np.zeros(B, dtype=np.bool_)
    updating = np.zeros((B, H), dtype=np.bool_)
    for t in range(B):
        for g in range(G):
            if present[t, g]:
                for a in range(d):
                    if not noise[t, g, a, a] > 0.0:
                        return False, measured, all_wide, updating
    for t in range(B):
        for g in range(G):
            measured[t] = measured[t] or present[t, g]
        if not measured[t]:
            flags[t] |= flag[_NO_MEASUREMENT]
            flags[t] |= flag[_HELD] if running[t] else flag[_NOT_INITIALISED]
        if not running[t]:
            continue
        narrow = False
        for h in range(H):
            if active[t, h] and not P[t, h, 0, 0] > reacquire_variance:
                narrow = True
        some = False
        for h in range(H):
            if not active[t, h]:
                continue
            if P[t, h, 0, 0] > reacquire_variance:
                if narrow:
                    active[t, h] = False
            else:
                updating[t, h] = measured[t]
            some = some or active[t, h]
        all_wide[t] = some and not narrow and measured[t]
    return True, measured, all_wide, updating


@numba.njit(cache=True, nogil=True)
def begin_frame_3d(
    time_s, q, last_time_s, last_q, partial, x, P, good_x, good_P, active, running,
    process_noise, rotation_gain, joint_error, gain_error, deviation_length, deviation_rate,
    rate_noise, max_variance, initial_rate_variance, deviation, rate, flag, R_bar, present,
    reacquire_variance, c, n_positions, JK, has_velocity, u_norm, white_mm, relative_error,
):  # fmt: skip
    """:func:`begin_step` for a frame of 3-D groups, then what the update needs of it:
    :func:`prepare_fuse`, the frame's radius and its model-error covariance
    (:mod:`tracker.estimators.measurement_kernels`; the torsion change over the interval
    enters the velocity's model error unless the state carries the rate).

    Returns ``begin_step``'s ``(flags, dt, turn, Q, prior, ok, L)``, then ``prepare_fuse``'s
    ``(usable, measured, all_wide, updating)``, the radius (B,), mm, and M (B, G, 3, 3).
    """
    flags, dt, turn, Q, prior, ok, L = begin_step(
        time_s, q, last_time_s, last_q, partial, x, P, good_x, good_P, active, running,
        process_noise, rotation_gain, joint_error, gain_error, deviation_length,
        deviation_rate, rate_noise, max_variance, initial_rate_variance, deviation, rate, flag,
    )  # fmt: skip
    usable, measured, all_wide, updating = prepare_fuse(
        R_bar, present, running, active, P, reacquire_variance, flags, flag
    )
    radius = horizontal_radius(c, present, n_positions)
    process_var = Q if rate < 0 else np.zeros_like(Q)
    M = model_error(JK, white_mm, has_velocity, c, u_norm, relative_error, process_var, dt)
    return (flags, dt, turn, Q, prior, ok, L, usable, measured, all_wide, updating, radius, M)


@numba.njit(cache=True, nogil=True)
def leading(active, log_weight):
    """Each trial's heaviest active hypothesis (the first of equals; 0 if none)."""
    B, H = active.shape
    lead = np.zeros(B, dtype=np.intp)
    for t in range(B):
        best = -math.inf
        for h in range(H):
            w = log_weight[t, h] if active[t, h] else -math.inf
            if w > best:
                best, lead[t] = w, h
    return lead


@numba.njit(cache=True, nogil=True)
def apply_update(
    b, h, status, nis, dof, rejected_groups, tip_fused_rows, active, log_weight, running,
    all_wide, measured, three_d, flags, out_nis, out_dof, rejected, bad_run, tip_fused,
    noise_scale, adapt, gates, forgetting, low, high, flag,
):  # fmt: skip
    """Each trial's report from its leading hypothesis' update (rows ``b``, ``h``) and what
    follows from it, in place: the flags, NIS and its dof, the rejected groups, the run of
    frames rejected as a whole (reset by any other), whether the frame's tip was fused, and
    with ``adapt`` the noise scale (a forgetting average of NIS/dof, each ratio capped at
    its gate ``gates[dof]`` and at 10, within ``[low, high]``).

    Returns ``(spawn, first, row, closed_form)``: the trials whose leading hypothesis
    rejected data (3-D frames: a hypothesis from the frame alone is weighed against it), the
    trials the frame may start (not running, measured; 3-D frames), the update's row of each
    trial (-1: none reported), and whether any trial needs the frame's closed form (to
    start, restart or spawn: 3-D frames).
    """
    B = active.shape[0]
    lead = leading(active, log_weight)
    row = np.full(B, -1, dtype=np.intp)
    for i in range(b.shape[0]):
        t = b[i]
        if h[i] == lead[t] and running[t] and not all_wide[t]:
            row[t] = i
    spawn = np.zeros(B, dtype=np.bool_)
    first = np.zeros(B, dtype=np.bool_)
    held_rejected = flag[_OUTLIER] | flag[_HELD]
    for t in range(B):
        if three_d:
            first[t] = measured[t] and not running[t]
        elif measured[t] and not running[t]:
            # A single view leaves a mirror ambiguity: it updates a filter, never starts one.
            flags[t] |= flag[_NOT_INITIALISED] | flag[_UNINFORMATIVE]
        if not three_d and all_wide[t]:
            flags[t] |= flag[_UNINFORMATIVE] | flag[_HELD]
        i = row[t]
        if i < 0:
            continue
        st = status[i]
        flags[t] |= st
        out_nis[t] = nis[i]
        out_dof[t] = dof[i] if math.isfinite(nis[i]) else 0
        rejected[t] += rejected_groups[i]
        if (st & held_rejected) != held_rejected:
            bad_run[t] = 0
        tip_fused[t] = tip_fused[t] or tip_fused_rows[i]
        spawn[t] = three_d and (st & flag[_OUTLIER]) != 0
        if adapt and math.isfinite(nis[i]) and dof[i] > 0:
            k = dof[i]
            ratio = min(min(nis[i], gates[k]), 10.0 * k) / k
            value = noise_scale[t] * (forgetting + (1.0 - forgetting) * ratio)
            noise_scale[t] = min(max(value, low), high)
    closed_form = False
    for t in range(B):
        closed_form = closed_form or first[t] or spawn[t] or (three_d and all_wide[t])
    return spawn, first, row, closed_form


@numba.njit(cache=True, nogil=True)
def normalise_single(active, log_weight):
    """Whether every trial has its hypotheses in slot 0 only (``first_only``) and at most
    one (``single``); with ``single`` the weights become 0 (log) where active, -inf
    elsewhere, in place."""
    B, H = active.shape
    first_only = True
    single = True
    for t in range(B):
        count = 0
        for h in range(H):
            if active[t, h]:
                count += 1
                if h > 0:
                    first_only = False
        if count > 1:
            single = False
    if single:
        for t in range(B):
            for h in range(H):
                log_weight[t, h] = 0.0 if active[t, h] else -math.inf
    return first_only, single


@numba.njit(cache=True, nogil=True)
def report(x, P, active, log_weight, initialised, prior, deviation, flags, flag):
    """The estimate of B trials: the moment-matched mean (circular) and std of delta_L over
    their hypotheses (NaN before a start), and ``MODEL_MISMATCH`` where the leading
    hypothesis' deviation is beyond three prior stds (in place in ``flags``)."""
    B, H = active.shape
    mean = np.full(B, np.nan)
    std = np.full(B, np.nan)
    lead = leading(active, log_weight)
    for t in range(B):
        k = lead[t]
        if deviation >= 0 and initialised[t]:
            for j in range(2):
                v = x[t, k, deviation + j]
                if v * v > 9.0 * prior[t, j]:
                    flags[t] |= flag[_MISMATCH]
        count = 0
        top = -math.inf
        for h in range(H):
            if active[t, h]:
                count += 1
                top = max(top, log_weight[t, h])
        if count == 0:
            continue
        if count == 1:
            m, v = x[t, k, 0], P[t, k, 0, 0]
        else:
            if not math.isfinite(top):
                top = 0.0
            total = 0.0
            for h in range(H):
                if active[t, h]:
                    total += math.exp(log_weight[t, h] - top)
            log_total = top + math.log(max(total, 1e-300))
            s, c = 0.0, 0.0
            for h in range(H):
                if active[t, h]:
                    w = math.exp(log_weight[t, h] - log_total)
                    s += w * math.sin(x[t, h, 0])
                    c += w * math.cos(x[t, h, 0])
            m = math.atan2(s, c)
            v = 0.0
            for h in range(H):
                if active[t, h]:
                    w = math.exp(log_weight[t, h] - log_total)
                    spread = _wrap(x[t, h, 0] - m)
                    v += w * (P[t, h, 0, 0] + spread * spread)
            m = _wrap(m)
        if initialised[t] and math.isfinite(m):
            mean[t] = m
            std[t] = math.sqrt(v)
    return mean, std


@numba.njit(cache=True, nogil=True)
def finish_update(
    b, h, status, nis, dof, rejected_groups, tip_fused_rows, active, log_weight, running,
    all_wide, measured, three_d, flags, out_nis, out_dof, rejected, bad_run, tip_fused,
    noise_scale, adapt, gates, forgetting, low, high, flag, x, P, initialised, prior,
    deviation,
):  # fmt: skip
    """:func:`apply_update`, then, where no closed form is needed and every trial has at most
    one hypothesis, :func:`normalise_single` and :func:`report`.

    Returns ``apply_update``'s ``(spawn, first, row, closed_form)``, then ``(first_only,
    single, finished, mean, std)``: ``finished`` when the estimate (mean, std) is reported
    here; otherwise the caller does the rest (closed form, several hypotheses).
    """
    spawn, first, row, closed_form = apply_update(
        b, h, status, nis, dof, rejected_groups, tip_fused_rows, active, log_weight, running,
        all_wide, measured, three_d, flags, out_nis, out_dof, rejected, bad_run, tip_fused,
        noise_scale, adapt, gates, forgetting, low, high, flag,
    )  # fmt: skip
    B = active.shape[0]
    first_only, single, finished = False, False, False
    mean, std = np.full(B, np.nan), np.full(B, np.nan)
    if not closed_form:
        first_only, single = normalise_single(active, log_weight)
        if single:
            mean, std = report(x, P, active, log_weight, initialised, prior, deviation, flags,
                               flag)  # fmt: skip
            finished = True
    return spawn, first, row, closed_form, first_only, single, finished, mean, std


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module and of
    :mod:`tracker.estimators.ukf_gate` on tiny inputs of the types a run passes (the flag
    values, the gate tables and a bank of one's indices are shared read-only arrays, a type
    of their own), once per process."""

    def shared(a):
        a.flags.writeable = False
        return a

    flag = shared(np.arange(1, 9, dtype=np.int64))
    for n in (1, 3, 4):
        B, H, G = 1, 2, 2
        x = np.zeros((B, H, n))
        P = np.broadcast_to(np.eye(n), (B, H, n, n)).copy()
        active = np.ones((B, H), dtype=bool)
        running = np.ones(B, dtype=bool)
        flags, dt, turn, Q, prior, ok, L = begin_step(
            np.zeros(B), np.zeros((B, 3)), np.full(B, np.nan), np.zeros((B, 3)),
            np.zeros(B, dtype=bool), x, P, x.copy(), P.copy(), active, running, 1.0, 1.0, 1.0,
            1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1 if n > 2 else -1, 1 if n == 4 else -1, flag,
        )  # fmt: skip
        for has_velocity in (True, False):
            c = np.ones((B, G, 3))
            eye = np.broadcast_to(np.eye(3), (B, G, 3, 3)).copy()
            begin_frame_3d(
                np.zeros(B), np.zeros((B, 3)), np.full(B, np.nan), np.zeros((B, 3)),
                np.zeros(B, dtype=bool), x.copy(), P.copy(), x.copy(), P.copy(), active.copy(),
                running, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1 if n > 2 else -1,
                1 if n == 4 else -1, flag, eye, np.ones((B, G), dtype=bool), 1.0, c, G,
                np.zeros((B, G, 3, 5)), has_velocity, np.ones(B), 0.1, 0.1,
            )  # fmt: skip
        for d in (2, 3):
            noise = np.broadcast_to(np.eye(d), (B, G, d, d)).copy()
            present = np.ones((B, G), dtype=bool)
            _, measured, all_wide, updating = prepare_fuse(
                noise, present, running, active, P, 1.0, flags, flag
            )
            m = G * d
            S = np.broadcast_to(np.eye(m), (1, m, m)).copy()
            out = gate_and_fuse(
                S, np.zeros((1, m)), np.zeros((1, n, m)), np.ones((1, G)), present,
                np.ones(1, dtype=bool), x[:, 0], P[:, 0], d, 0.01, 5.0, 10.0, 5.0,
                shared(np.full(G + 1, 20.0)), 1.0, flag,
            )  # fmt: skip
        lw = np.zeros((B, H))
        # The rows as a bank of one passes them (read-only indices) and as gathered.
        for rows in (np.zeros(1, dtype=np.intp), shared(np.zeros(1, dtype=np.intp))):
            args = (
                rows, rows, out[6], out[2], out[3], out[7], np.ones(1, dtype=bool), active, lw,
                running, all_wide, measured, True, flags, np.zeros(B),
                np.zeros(B, dtype=np.int64), np.zeros(B, dtype=np.int64),
                np.zeros(B, dtype=np.int64), np.zeros(B, dtype=bool), np.ones(B), True,
                shared(np.full(8, 10.0)), 0.9, 0.5, 2.0, flag,
            )  # fmt: skip
            apply_update(*args)
            finish_update(*args, x, P, running, prior, 1 if n > 2 else -1)
            # The update's rules (ukf_gate) with the same argument types.
            commit_update(rows, rows, out[8], out[0], out[1], out[4], x, P, x.copy(), P.copy(),
                          lw, np.ones(B), 0.99)  # fmt: skip
            W = np.full(2 * n + 1, 1.0 / (2 * n + 1))
            for has_velocity in (True, False):
                c = np.ones((B, G, 3))
                eye = np.broadcast_to(np.eye(3), (B, G, 3, 3)).copy()
                update_3d(
                    rows, rows, x, P, L, ok, x.copy(), P.copy(), lw, np.ones(B), 0.99, 1.0, c,
                    np.zeros((B, G, 3, 5)), c, np.zeros((B, 3)), eye, np.ones(B), eye,
                    np.ones((B, G), dtype=bool), has_velocity, W, W, 1 if n > 2 else -1,
                    1 if n == 4 else -1, 0.01, 5.0, 10.0, 5.0, shared(np.full(G + 1, 20.0)),
                    1.0, flag,
                )  # fmt: skip
            # Single views (ViewGroups.cameras: the points' model vectors and cameras).
            update_views(
                rows, rows, x, P, L, ok, x.copy(), P.copy(), lw, np.ones(B), 0.99, 1.0, 0.0,
                np.ones((G, 3)), np.broadcast_to(np.eye(3), (G, 3, 3)).copy(), np.ones((G, 3)),
                np.ones((G, 4)), np.zeros((G, 5)), np.ones(G, dtype=bool), np.zeros((B, G, 2)),
                np.broadcast_to(np.eye(2), (B, G, 2, 2)).copy(), np.ones(B),
                np.ones((B, G), dtype=bool), W, W, 0.01, 5.0, 10.0, 5.0,
                shared(np.full(G + 1, 20.0)), 1.0, flag,
            )  # fmt: skip
        normalise_single(active, lw)
        leading(active, lw)
        report(x, P, active, lw, running, prior, 1 if n > 2 else -1, flags, flag)


__all__ = [
    "FLAG_ORDER",
    "apply_update",
    "begin_frame_3d",
    "begin_step",
    "finish_update",
    "leading",
    "normalise_single",
    "prepare_fuse",
    "report",
    "warm_up",
]
