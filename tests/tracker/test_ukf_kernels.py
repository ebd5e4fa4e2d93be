"""The UKF's compiled arithmetic and rules (tracker/estimators/ukf_kernels.py, ukf_rules.py)
against the textbook formulas written here in plain numpy: the linear predict, the unscented
transform of the 3-D measurement model, the update with only the inlying groups, the
joint-consistency exclusion, the doubtful group's mixture and the frame's likelihood."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tracker.estimators import measurement_kernels as MK
from tracker.estimators import ukf_gate as Gate
from tracker.estimators import ukf_kernels as K
from tracker.estimators import ukf_rules as R

RNG_SEED = 3


def _spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + np.eye(n))


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def _weights(n, alpha=0.3, beta=2.0, kappa=0.0):
    lam = alpha**2 * (n + kappa) - n
    Wm = np.full(2 * n + 1, 0.5 / (n + lam))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = lam / (n + lam) + 1 - alpha**2 + beta
    return Wm, Wc, n + lam


def _predict(x, P, Q, decay, prior, dt, deviation, rate, rate_noise, max_variance):
    """predict_row over rows (x (r, n), P (r, n, n) in place): (ok (r,), L (r, n, n))."""
    r, n = x.shape
    L = np.zeros((r, n, n))
    ok = np.array([
        K.predict_row(x[i], P[i], Q[i], decay[i], prior[i, 0], prior[i, 1], dt[i], deviation,
                      rate, rate_noise, max_variance, L[i], np.empty((n, n)))
        for i in range(r)
    ])  # fmt: skip
    return ok, L


def _factors(P):
    """Fresh sigma-point factors of covariances (r, n, n) (no predict's factor to reuse)."""
    r, n = P.shape[:2]
    rows = np.arange(r)
    none = np.zeros((r, 1), dtype=bool)
    _, L, ok = K.row_factors(rows, np.zeros(r, dtype=np.intp), P[:, None].copy(),
                             np.zeros((r, 1, n, n)), none)  # fmt: skip
    return L, ok


def _fuse(S, rho, Pxz, inlier, d, x, P):
    """fuse_row over rows: (products, logdet, ok, x_post, P_post) as arrays."""
    r, m = rho.shape
    n = Pxz.shape[1]
    products = np.zeros((r, n + 1, n + 1))
    logdet, ok = np.full(r, np.nan), np.zeros(r, dtype=bool)
    x_post, P_post = np.empty((r, n)), np.empty((r, n, n))
    for i in range(r):
        logdet[i], ok[i] = K.fuse_row(
            S[i], rho[i], Pxz[i], inlier[i], d, x[i], P[i], products[i], x_post[i], P_post[i],
            np.empty((m, m)), np.empty((n + 1, m)), np.empty((n + 1, m)), np.empty(m, bool),
        )  # fmt: skip
    return products, logdet, ok, x_post, P_post


# ------------------------------------------------------------------------------ predict
@pytest.mark.parametrize("n, deviation, rate", [(1, -1, -1), (3, 1, -1), (4, 2, 1), (2, -1, 1)])
def test_predict_is_the_linear_process_model(n, deviation, rate):
    rng = np.random.default_rng(RNG_SEED)
    r = 5
    x = rng.normal(size=(r, n))
    x[:, 0] = rng.uniform(-6, 6, r)  # delta_L beyond the circle: the predict wraps it
    P = np.stack([_spd(rng, n, 0.01) for _ in range(r)])
    Q, decay, dt = rng.uniform(0, 0.01, r), rng.uniform(0.2, 1, r), rng.uniform(0.01, 0.1, r)
    prior = rng.uniform(0.001, 0.01, (r, 2))
    qa = 0.3
    expected_x, expected_P = [], []
    for i in range(r):
        F = np.eye(n)
        Qi = np.zeros((n, n))
        Qi[0, 0] = Q[i]
        if deviation >= 0:
            F[deviation, deviation] = F[deviation + 1, deviation + 1] = decay[i]
            Qi[deviation, deviation] = (1 - decay[i] ** 2) * prior[i, 0]
            Qi[deviation + 1, deviation + 1] = (1 - decay[i] ** 2) * prior[i, 1]
        # The random walk's Q is added first, then the deviation decays, then the rate.
        P0 = P[i].copy()
        P0[0, 0] += Q[i]
        Pi = F @ P0 @ F.T + Qi - np.diag([Q[i]] + [0] * (n - 1))
        xi = F @ x[i]
        if rate >= 0:
            T = np.eye(n)
            T[0, rate] = dt[i]
            h = dt[i]
            Qr = np.zeros((n, n))
            Qr[0, 0], Qr[0, rate], Qr[rate, 0] = qa * h**3 / 3, qa * h**2 / 2, qa * h**2 / 2
            Qr[rate, rate] = qa * h
            Pi, xi = T @ Pi @ T.T + Qr, T @ xi
        xi[0] = _wrap(xi[0])
        expected_x.append(xi)
        expected_P.append(Pi)
    ok, L = _predict(x, P, Q, decay, prior, dt, deviation, rate, qa, 10.0)
    assert ok.all()
    np.testing.assert_allclose(x, expected_x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(P, expected_P, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(L @ np.swapaxes(L, 1, 2), P, rtol=1e-12, atol=1e-15)
    assert np.all(np.triu(L, 1) == 0)


def test_predict_caps_the_std_keeping_correlations_and_flags_what_is_not_finite():
    rng = np.random.default_rng(RNG_SEED)
    P = np.stack([_spd(rng, 3) * 4.0, _spd(rng, 3) * 1e-3, _spd(rng, 3)])
    P[2, 1, 2] = np.nan
    x = np.zeros((3, 3))
    before = P.copy()
    ok, L = _predict(
        x, P, np.zeros(3), np.ones(3), np.zeros((3, 2)), np.zeros(3), -1, -1, 0.0, 0.5
    )
    assert ok.tolist() == [True, True, False]
    assert P[0, 0, 0] == pytest.approx(0.5)
    corr = lambda A: A / np.sqrt(np.outer(np.diag(A), np.diag(A)))  # noqa: E731
    np.testing.assert_allclose(corr(P[0]), corr(before[0]), rtol=1e-12)
    np.testing.assert_array_equal(P[1], before[1])


def test_a_covariance_at_the_edge_of_definiteness_factorises_with_the_jitter():
    # Rank one plus nothing: Cholesky fails on it, the documented jitter makes it definite.
    v = np.array([1.0, 2.0, 3.0])
    P = np.outer(v, v)[None]
    L, ok = _factors(P.copy())
    assert ok[0]
    np.testing.assert_allclose(L[0] @ L[0].T, P[0], atol=1e-7)
    L, ok = _factors(-np.eye(3)[None])
    assert not ok[0]


# ------------------------------------------------------------------------------ update
def _frame(rng, r, G, n, deviation, rate, has_velocity):
    c = rng.normal(size=(r, G, 3)) * 5
    JK = rng.normal(size=(r, G, 3, 5))
    y = rng.normal(size=(r, G, 3)) * 5
    noise = np.stack([[_spd(rng, 3, 0.1) for _ in range(G)] for _ in range(r)])
    x = rng.normal(size=(r, n)) * 0.1
    P = np.stack([_spd(rng, n, 0.01) for _ in range(r)])
    q_r = rng.uniform(-3, 3, r)
    return c, JK, y, noise, x, P, q_r


def _model(sigma, c, JK, about, deviation, rate, has_velocity):
    """The 3-D measurement model of one sigma point, as docs/design.md writes it."""
    shape = c.copy()
    if deviation >= 0:
        p, q = sigma[deviation], sigma[deviation + 1]
        shape = shape + JK @ np.array([p, q, p * p, p * q, q * q])
    if rate >= 0 and has_velocity:
        shape[-1] += sigma[rate] * np.cross([0.0, 0.0, 1.0], c[0])
    a = sigma[0] - about
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    return (shape @ Rz.T).ravel()


@pytest.mark.parametrize(
    "n, deviation, rate, has_velocity", [(1, -1, -1, False), (3, 1, -1, True), (4, 2, 1, True)]
)
def test_innovation_is_the_unscented_transform_of_the_3d_model(n, deviation, rate, has_velocity):
    rng = np.random.default_rng(RNG_SEED + n)
    r, G = 3, 4
    c, JK, y, noise, x, P, q_r = _frame(rng, r, G, n, deviation, rate, has_velocity)
    Wm, Wc, spread = _weights(n)
    L = np.linalg.cholesky(P)
    # The noise is the segmentation noise scaled plus the model error.
    scale = rng.uniform(0.5, 2.0, r)
    M = np.stack([[_spd(rng, 3, 0.01) for _ in range(G)] for _ in range(r)])
    S, rho, Pxz, d2, offsets = K.innovation_3d(
        x, L, spread, c, JK, y, q_r, noise, scale, M, Wm, Wc, deviation, rate, has_velocity
    )
    noise = noise * scale[:, None, None, None] + M
    for i in range(r):
        U = np.linalg.cholesky(spread * P[i]).T
        sigmas = np.vstack([x[i], x[i] + U, x[i] - U])
        hs = np.array([_model(s, c[i], JK[i], x[i, 0], deviation, rate, has_velocity)
                       for s in sigmas])  # fmt: skip
        turn = -(q_r[i] + x[i, 0])
        Rz = np.array([[math.cos(turn), -math.sin(turn), 0], [math.sin(turn), math.cos(turn), 0],
                       [0, 0, 1]])  # fmt: skip
        z = (y[i] @ Rz.T).ravel()
        zp = Wm @ hs
        D = hs - zp
        expected_S = (D.T * Wc) @ D
        for g in range(G):
            expected_S[3 * g : 3 * g + 3, 3 * g : 3 * g + 3] += noise[i, g]
        np.testing.assert_allclose(S[i], expected_S, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(rho[i], z - zp, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(Pxz[i], ((sigmas - x[i]).T * Wc) @ D, rtol=1e-10, atol=1e-12)
        for g in range(G):
            block = expected_S[3 * g : 3 * g + 3, 3 * g : 3 * g + 3]
            e = (z - zp)[3 * g : 3 * g + 3]
            assert d2[i, g] == pytest.approx(e @ np.linalg.solve(block, e), rel=1e-10)
    # The same statistics from the model's predictions made apart.
    sigmas, offsets2 = K.sigma_rows(x, L, spread)
    np.testing.assert_allclose(offsets2, offsets, rtol=1e-14)
    hs = np.empty((r, sigmas.shape[1], 3 * G))
    for i in range(r):
        K.predict_3d(sigmas[i], c[i], JK[i], x[i, 0], deviation, rate, has_velocity, hs[i])
    z = np.empty((r, 3 * G))
    for i in range(r):
        t = -(q_r[i] + x[i, 0])
        Rz = np.array([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]])
        z[i] = (y[i] @ Rz.T).ravel()
    S2, rho2, Pxz2, d22 = K.innovation_stats(hs, z, offsets, noise, Wm, Wc, 3)
    for a, b in ((S, S2), (rho, rho2), (Pxz, Pxz2), (d2, d22)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


def test_frame_radius_and_model_error():
    rng = np.random.default_rng(RNG_SEED)
    B, G = 3, 4
    c = rng.normal(size=(B, G, 3))
    present = rng.random((B, G)) < 0.7
    P = G - 1  # the last group is the velocity
    radius = MK.horizontal_radius(c, present, P)
    expected = np.sqrt([sum(c[t, g, 0] ** 2 + c[t, g, 1] ** 2 for g in range(P) if present[t, g])
                        for t in range(B)])  # fmt: skip
    np.testing.assert_allclose(radius, expected, rtol=1e-14)
    JK = rng.normal(size=(B, G, 3, 5))
    u_norm, process_var = rng.uniform(0, 5, B), rng.uniform(0, 1e-4, B)
    dt = np.array([0.05, 0.0, 0.02])  # no interval: no torsion change term
    rate_var = np.where(dt > 0, process_var / np.where(dt > 0, dt, 1.0) ** 2, 0.0)
    M = MK.model_error(JK, 0.05, True, c, u_norm, 0.1, process_var, dt)
    for t in range(B):
        for g in range(G):
            J = JK[t, g, :, :2]
            expected = 0.05**2 * J @ J.T
            if g == G - 1:
                tangent = np.cross([0.0, 0.0, 1.0], c[t, 0])
                expected = expected + (0.1 * u_norm[t]) ** 2 * np.eye(3)
                expected = expected + rate_var[t] * np.outer(tangent, tangent)
            np.testing.assert_allclose(M[t, g], expected, rtol=1e-12, atol=1e-15)
    without = MK.model_error(JK, 0.05, False, c, u_norm, 0.1, process_var, dt)
    np.testing.assert_allclose(without[:, -1], 0.05**2 * JK[:, -1, :, :2] @ np.swapaxes(
        JK[:, -1, :, :2], -1, -2), rtol=1e-12)  # fmt: skip


def _statistics(rng, n, G, d):
    m = G * d
    A = rng.normal(size=(n + m, n + m))
    joint = A @ A.T / (n + m) + 0.1 * np.eye(n + m)
    P = joint[:n, :n].copy()
    Pxz = joint[:n, n:].copy()
    S = joint[n:, n:].copy()
    rho = rng.normal(size=m)
    x = rng.normal(size=n) * 0.1
    return x, P, Pxz, S, rho


def _reference_update(x, P, Pxz, S, rho, inlier, d):
    keep = np.repeat(inlier, d)
    Sk, Pk, rk = S[np.ix_(keep, keep)], Pxz[:, keep], rho[keep]
    gain = np.linalg.solve(Sk, Pk.T).T
    x_post = x + gain @ rk
    x_post[0] = _wrap(x_post[0])
    P_post = P - gain @ Sk @ gain.T
    nis = rk @ np.linalg.solve(Sk, rk)
    return x_post, P_post, nis, np.linalg.slogdet(Sk)[1]


def test_fuse_uses_only_the_inlying_groups():
    rng = np.random.default_rng(RNG_SEED)
    n, G, d = 3, 4, 3
    rows = [_statistics(rng, n, G, d) for _ in range(4)]
    x, P, Pxz, S, rho = (np.stack(a) for a in zip(*rows, strict=True))
    inlier = np.array([[1, 1, 1, 1], [1, 0, 1, 1], [0, 0, 0, 1], [1, 1, 0, 0]], dtype=bool)
    products, logdet, ok, x_post, P_post = _fuse(S, rho, Pxz, inlier, d, x, P)
    assert ok.all()
    for i in range(4):
        ex, eP, nis, ld = _reference_update(x[i], P[i], Pxz[i], S[i], rho[i], inlier[i], d)
        np.testing.assert_allclose(x_post[i], ex, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(P_post[i], eP, rtol=1e-10, atol=1e-13)
        assert products[i, n, n] == pytest.approx(nis, rel=1e-10)
        assert logdet[i] == pytest.approx(ld, rel=1e-10)
    S[0, 0, 0] = -1.0  # not positive definite: no update, reported
    products, logdet, ok, x_post, _ = _fuse(S, rho, Pxz, inlier, d, x, P)
    assert not ok[0] and math.isnan(logdet[0]) and not products[0].any()
    np.testing.assert_allclose(x_post[0], x[0])


# Flag values in ukf_rules.FLAG_ORDER: one bit each.
_FLAGS = np.array([1 << i for i in range(len(R.FLAG_ORDER))], dtype=np.int64)
_FLAG = dict(zip(R.FLAG_ORDER, _FLAGS.tolist(), strict=True))


def _gate(S, rho, Pxz, d2, x, P, d, p=0.01, k=5.0, threshold=None, doubt=math.inf, gates=None):
    G = d2.shape[1]
    threshold = 2.0 * (math.log((1 - p) / p) + d * math.log(k)) / (1 - k**-2) if threshold is None else threshold
    gates = np.full(G + 1, np.inf) if gates is None else gates
    return Gate.gate_and_fuse(
        S, rho, Pxz, d2, np.ones(d2.shape, dtype=bool), np.ones(d2.shape[0], dtype=bool), x,
        P, d, p, k, threshold, doubt, gates, 1e-6, _FLAGS,
    )  # fmt: skip


def test_the_gate_rejects_a_gross_error_and_the_likelihood_counts_it_under_the_tail():
    rng = np.random.default_rng(RNG_SEED)
    n, G, d = 2, 3, 3
    x, P, Pxz, S, rho = (a[None] for a in _statistics(rng, n, G, d))
    d2 = np.array([[1.0, 400.0, 2.0]])
    p, k = 0.01, 5.0
    x_post, P_post, nis, dof, log_lik, inlier, status, rejected, done, shown = _gate(
        S, rho, Pxz, d2, x, P, d, p, k
    )
    assert inlier.tolist() == [[True, False, True]]
    assert rejected[0] == 1 and status[0] == _FLAG["OUTLIER_REJECTED"]
    assert done[0] and dof[0] == 6
    ex, eP, enis, ld = _reference_update(x[0], P[0], Pxz[0], S[0], rho[0], inlier[0], d)
    np.testing.assert_allclose(x_post[0], ex, rtol=1e-10)
    assert nis[0] == pytest.approx(enis, rel=1e-10)
    block = S[0, 3:6, 3:6]
    expected = (
        2 * (math.log1p(-p) - 1.5 * math.log(2 * math.pi)) - 0.5 * (enis + ld)
        + math.log(p) - d * math.log(k) - 0.5 * 400.0 / k**2
        - 0.5 * (np.linalg.slogdet(block)[1] + d * math.log(2 * math.pi))
    )  # fmt: skip
    assert log_lik[0] == pytest.approx(expected, rel=1e-10)


def test_a_group_inconsistent_with_the_others_is_left_out():
    rng = np.random.default_rng(RNG_SEED)
    n, G, d = 2, 4, 3
    m = G * d
    # Every group sees the same uncertain 3-vector (prior variance 10) plus unit noise, so
    # each passes its own block of S easily; group 2 is 4 off on each axis where the others
    # agree on zero: given the others it is far outside its gate.
    H = np.tile(np.eye(3), (G, 1))
    S = 10.0 * H @ H.T + np.eye(m)
    rho = rng.normal(size=m) * 0.1
    rho[6:9] = 4.0
    d2 = np.array([[rho[3 * g : 3 * g + 3] @ np.linalg.solve(S[3 * g : 3 * g + 3, 3 * g : 3 * g + 3],
                                                             rho[3 * g : 3 * g + 3])
                    for g in range(G)]])  # fmt: skip
    assert d2.max() < 5.0
    Pxz = rng.normal(size=(1, n, m)) * 0.05
    x, P = np.zeros((1, n)), np.eye(n)[None] * 0.01
    gates = np.array([math.inf] + [10.0 + 3 * k for k in range(1, G + 1)])
    out = _gate(S[None], rho[None], Pxz, d2, x, P, d, threshold=20.0, gates=gates)
    assert out[5].tolist() == [[True, True, False, True]]
    ex, _, nis, _ = _reference_update(
        x[0], P[0], Pxz[0], S, rho, np.array([True, True, False, True]), d
    )
    np.testing.assert_allclose(out[0][0], ex, rtol=1e-10)
    assert out[2][0] == pytest.approx(nis, rel=1e-10) and nis < gates[3]
    # Without the joint gate every group is let in.
    assert _gate(S[None], rho[None], Pxz, d2, x, P, d, threshold=20.0)[5].all()


def test_a_doubtful_group_is_mixed_with_the_update_without_it():
    rng = np.random.default_rng(RNG_SEED)
    n, G, d = 2, 3, 3
    x, P, Pxz, S, rho = (a[None] for a in _statistics(rng, n, G, d))
    p, k = 0.01, 5.0
    d2 = np.array([[1.0, 15.0, 2.0]])
    out = _gate(S, rho, Pxz, d2, x, P, d, p, k, threshold=30.0, doubt=10.0)
    x_with, P_with, *_ = _reference_update(x[0], P[0], Pxz[0], S[0], rho[0], np.ones(G, bool), d)
    x_without, P_without, *_ = _reference_update(
        x[0], P[0], Pxz[0], S[0], rho[0], np.array([True, False, True]), d
    )
    log_ratio = math.log(p / (1 - p)) - d * math.log(k) + 0.5 * (1 - k**-2) * 15.0
    w = 1 / (1 + math.exp(log_ratio))
    diff = x_with - x_without
    np.testing.assert_allclose(out[0][0], x_without + w * diff, rtol=1e-10)
    expected_P = w * P_with + (1 - w) * P_without + w * (1 - w) * np.outer(diff, diff)
    np.testing.assert_allclose(out[1][0], expected_P, rtol=1e-10)


def test_an_uninformative_update_is_held_and_not_shown():
    rng = np.random.default_rng(RNG_SEED)
    n, G, d = 2, 2, 3
    x, P, Pxz, S, rho = (a[None] for a in _statistics(rng, n, G, d))
    Pxz[:] = 0.0  # the frame says nothing about the state
    out = _gate(S, rho, Pxz, np.ones((1, G)), x, P, d)
    x_post, _, nis, dof, _, _, status, _, done, shown = out
    assert not done[0] and not shown[0] and math.isnan(nis[0]) and dof[0] == 0
    assert status[0] == _FLAG["HELD"] | _FLAG["UNINFORMATIVE"]


def test_a_frame_s_position_groups_are_assembled_with_their_presence_and_invariant_noise():
    rng = np.random.default_rng(RNG_SEED)
    B, P = 3, 4
    tip = rng.normal(size=(B, 3))
    tip_cov = np.stack([_spd(rng, 3) for _ in range(B)])
    markers = rng.normal(size=(B, P - 1, 3))
    markers_cov = np.stack([[_spd(rng, 3) for _ in range(P - 1)] for _ in range(B)])
    markers[0, 1] = np.nan  # not found
    tip_cov[2, 0, 1] = np.inf  # unusable
    for has_tip, has_markers, G in ((True, True, P), (True, False, P + 1), (False, True, P)):
        y, R, R_bar, present = MK.assemble_positions(
            tip, tip_cov, markers, markers_cov, B, P, G, has_tip, has_markers
        )
        for t in range(B):
            for g in range(G):
                if g == 0:
                    v, C, given = tip[t], tip_cov[t], has_tip
                elif g < P:
                    v, C, given = markers[t, g - 1], markers_cov[t, g - 1], has_markers
                else:
                    v, C, given = np.zeros(3), np.eye(3), False  # the caller's velocity
                ok = given and np.isfinite(v).all() and np.isfinite(C).all()
                assert present[t, g] == ok
                np.testing.assert_array_equal(y[t, g], v if ok else 0.0)
                np.testing.assert_array_equal(R[t, g], C if ok else np.eye(3))
                A = R[t, g]
                horizontal = 0.5 * (A[0, 0] + A[1, 1])
                skew = 0.5 * (A[0, 1] - A[1, 0])
                expected = np.array([[horizontal, skew, 0], [-skew, horizontal, 0], [0, 0, A[2, 2]]])
                np.testing.assert_allclose(R_bar[t, g], expected, rtol=1e-15)


def test_the_expansion_carried_from_its_node_is_the_product_with_the_transport_matrix():
    rng = np.random.default_rng(9)
    JK = rng.normal(size=(4, 3, 5))
    p, d = 0.007, -0.004
    T = np.eye(5)
    T[2, 0], T[3, 0], T[3, 1], T[4, 1] = 2 * p, d, p, 2 * d
    np.testing.assert_allclose(MK.carry_expansion(JK, p, d)[0], JK @ T, rtol=1e-14, atol=1e-15)


def _rotation(rng):
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return Q * np.sign(np.linalg.det(Q))


def _single_view_groups(rng, views, n_points=(2, 3)):
    """ViewGroups of random model vectors in ``views``, each with its own base pose, and the
    parts to project them by hand."""
    from tracker.estimators.measurement import ViewGroups

    parts = tuple(
        (view, rng.normal(0.0, 10.0, (n, 3)), _rotation(rng), rng.normal(0.0, 5.0, 3))
        for view, n in zip(views, n_points, strict=True)
    )
    G = sum(n_points)
    groups = ViewGroups(
        q=np.array([[0.4, 0.0, 0.0]]), z=np.zeros((1, G, 2)),
        R=np.broadcast_to(np.eye(2), (1, G, 2, 2)).copy(), present=np.ones((1, G), bool),
        parts=parts,
    )  # fmt: skip
    return groups, parts


def _projected_by_hand(parts, angles):
    """Each view's own ``project`` of ``R_w_b Rz(angle) C + o_b_w``: (..., G, 2)."""
    out = []
    for view, C, R_w_b, o_b_w in parts:
        c, s = np.cos(angles)[..., None], np.sin(angles)[..., None]
        turned = np.stack([c * C[:, 0] - s * C[:, 1], s * C[:, 0] + c * C[:, 1],
                           np.broadcast_to(C[:, 2], c.shape[:-1] + (len(C),))], -1)
        out.append(view.project(turned @ R_w_b.T + o_b_w))
    return np.concatenate(out, axis=-2)


def test_single_views_project_as_the_views_do_with_distortion_and_orthographic_planes():
    """The compiled projection of single views' sigma points (ViewGroups.predict) against
    the views' own project: OpenCV's projectPoints with its distortion, the orthographic
    plane's axes, and a view of another kind (projected by its own method)."""
    from models.imaging import OrthographicPlane, PinholeView

    rng = np.random.default_rng(RNG_SEED)
    distorted = PinholeView.look_at(
        [400.0, 30.0, 20.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1800.0,
        dist=np.array([-0.21, 0.08, 0.0013, -0.0021, -0.015]),
    )  # fmt: skip
    plain = PinholeView.look_at([0.0, -380.0, 40.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 2500.0)
    plane = OrthographicPlane.from_normal([0.3, 1.0, 0.2], 0.4)

    class Other:  # a view of another kind: anything with project
        def project(self, points_w):
            return 2.0 * points_w[..., :2] + 1.0

    sigmas = rng.normal(0.0, 1.0, (4, 7, 3))  # (r, S, n), the angle first
    for views in ((distorted, plain), (plane, distorted), (plain, Other())):
        groups, parts = _single_view_groups(rng, views)
        assert (groups.cameras is None) == isinstance(views[1], Other)
        predicted = groups.predict(np.zeros(4, np.intp), sigmas)
        expected = _projected_by_hand(parts, groups.q[0, 0] + sigmas[..., 0])
        assert predicted.shape == (4, 7, 5, 2)
        np.testing.assert_allclose(predicted, expected, rtol=1e-11, atol=1e-9)


def test_a_single_view_point_predicted_behind_its_camera_is_an_error():
    from models.imaging import PinholeView
    from tracker.estimators.measurement import ViewGroups

    view = PinholeView.look_at([0.0, -100.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1000.0)
    # 150 mm along y_b, the base at the origin: 100 + 150 cos(angle) mm in front of the camera.
    C = np.array([[0.0, 0.0, 0.0], [0.0, 150.0, 0.0]])
    groups = ViewGroups(
        q=np.zeros((1, 3)), z=np.zeros((1, 2, 2)), R=np.broadcast_to(np.eye(2), (1, 2, 2, 2)),
        present=np.ones((1, 2), bool), parts=((view, C, np.eye(3), np.zeros(3)),),
    )  # fmt: skip
    in_front = np.linspace(-0.8, 0.8, 5)[:, None, None] * np.ones((1, 1, 3))
    assert np.isfinite(groups.predict(np.zeros(5, np.intp), in_front)).all()
    with pytest.raises(ValueError, match="behind a camera"):
        groups.predict(np.zeros(5, np.intp), in_front + np.pi)


_NO_COMPILE_SCRIPT = """
import importlib, math, numba, numpy as np
from dataclasses import replace
from models.catheter import default_catheter
from tracker.estimators import make_estimator
from tracker.types import Observation, ViewMeasurement

modules = [importlib.import_module(f"tracker.estimators.{name}") for name in (
    "ukf_kernels", "ukf_rules", "ukf_gate", "ukf_step", "measurement_kernels",
    "linalg_kernels", "grid_kernels", "check_kernels")] + [
    importlib.import_module(f"models.{name}")
    for name in ("_shape_kernels", "_imaging_kernels", "_fit_kernels")]

def signatures():
    return {(m.__name__, name): len(k.signatures) for m in modules
            for name, k in vars(m).items() if isinstance(k, numba.core.registry.CPUDispatcher)}

catheter = default_catheter()
estimators = [make_estimator(name, catheter) for name in (
    "ukf", "ukf-position", "grid", "tip-position", "body-positions", "tip-velocity")]
from models.imaging import default_pinhole_rig
rig = default_pinhole_rig()
before = signatures()
for batch in ((), (3,)):  # the reconstruction of a frame's points, read-only inputs too
    uv = rig.project_all(np.ones(batch + (3,))) if hasattr(rig, "project_all") else np.stack(
        [view.project(np.ones(batch + (3,))) for view in rig.views], -2)
    cov = np.broadcast_to(np.eye(2), uv.shape[:-1] + (2, 2))
    rig.reconstruct_with_covariance(uv, cov)
    uv.flags.writeable = False
    rig.reconstruct_with_covariance(uv, cov)
rng = np.random.default_rng(3)
cov = np.diag([0.01, 0.01, 0.005])
n_markers = len(catheter.marker_arclengths_mm)
for k in range(40):
    q = np.array([0.3 + 0.01 * k, 0.6, -0.4 + 0.02 * k])
    points = catheter.points(q)
    a = q[0] + 1.0
    turn = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    measured = points @ turn.T + rng.normal(0, 0.1, points.shape)
    if k % 7 == 3:
        measured[0] += 5.0  # a gross error: the gate's other paths
    observation = Observation(
        time_s=0.05 * k, q=q, q_dot=np.array([0.2, 0.0, 0.4]), tip_b_mm=measured[0],
        tip_cov_b=cov, markers_b_mm=measured[1:],
        markers_cov_b=np.broadcast_to(cov, (n_markers, 3, 3)).copy())
    if k % 4 == 2:  # a velocity (fused after a frame without a tip, and by Tip Velocity)
        observation = replace(observation, velocity_b_mm_s=np.array([1.0, 2.0, 0.5]),
                              velocity_cov_b=4 * cov, velocity_tip_cov_b=0.5 * cov)
    if k % 8 == 1:
        observation = replace(observation, tip_b_mm=np.full(3, np.nan))
    if k % 6 == 4:  # points seen in one view only (the single-view update)
        view = rig.views[k % 2]
        uv = view.project(measured[:2])
        observation = replace(observation, tip_b_mm=None, markers_b_mm=None, views=(
            ViewMeasurement(view, np.eye(3), np.zeros(3), uv,
                            np.broadcast_to(np.eye(2), (2, 2, 2)).copy(), np.array([-1, 0])),))
    if k % 5 == 1:  # recorded arrays are often read-only
        for value in vars(observation).values():
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
    for estimator in estimators:
        estimator.step(observation)
after = signatures()
print(sorted(f"{m}.{n}" for (m, n) in after if after[(m, n)] != before[(m, n)]))
"""


def test_a_run_compiles_nothing_after_the_filters_are_made():
    """The warm-ups compile (or load) every kernel with the argument types a run passes
    (read-only index and plan arrays included), so that no frame waits for the compiler
    and no thread compiles while another one runs: a compilation during a live run stalls
    the loop and can deadlock with the threads of the outputs. In a fresh interpreter: a
    kernel's new signature counts whether compiled or loaded from the disk cache."""
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-c", _NO_COMPILE_SCRIPT], capture_output=True, text=True, check=True,
        timeout=600,
    )  # fmt: skip
    assert result.stdout.strip().splitlines()[-1] == "[]", result.stdout


def _update_views_one_by_one(
    b, h, x_all, P_all, L_all, factor_ok, good_x, good_P, log_weight, mismatch_scale,
    mismatch_decay, spread, q_r, C, A, t, intrinsics, dist, pinhole, z, R, scale, present, Wm,
    Wc, *rules,
):  # fmt: skip
    """Gate.update_views as the separate kernels it calls, one by one from Python."""
    P, L, ok_sigma = K.row_factors(b, h, P_all, L_all, factor_ok)
    x = x_all[b, h]
    sigmas, offsets = K.sigma_rows(x, L, spread)
    r, n_sigma = sigmas.shape[:2]
    points, least = MK.view_projections(
        np.ascontiguousarray(q_r + sigmas[..., 0]).reshape(-1), C, A, t, intrinsics, dist, pinhole
    )
    hs = np.ascontiguousarray(points.reshape(r, n_sigma, -1))
    noise = R[b] * scale[b][:, None, None, None]
    S, rho, Pxz, d2 = K.innovation_stats(hs, np.ascontiguousarray(z[b].reshape(r, -1)), offsets,
                                         noise, Wm, Wc, 2)  # fmt: skip
    x_post, P_post, nis, dof, log_lik, inlier, status, rejected, done, shown = (
        Gate.gate_and_fuse(S, rho, Pxz, d2, present[b], ok_sigma, x, P, 2, *rules)
    )
    if least > 0.0:
        Gate.commit_update(b, h, done, x_post, P_post, log_lik, x_all, P_all, good_x, good_P,
                           log_weight, mismatch_scale, mismatch_decay)  # fmt: skip
    return status, nis, dof, rejected, inlier, shown, rho, least


def test_single_views_update_in_one_call_as_their_kernels_one_by_one(monkeypatch):
    """The UKF over frames of single views (one view or the other, the tip or a marker
    missing, a gross error): the fused update (ukf_gate.update_views) gives the estimates of
    its kernels called one by one, bit for bit."""
    from dataclasses import replace

    from models.catheter import default_catheter
    from models.imaging import default_pinhole_rig
    from tracker.estimators.ukf import BendingPlaneUKF
    from tracker.types import Observation, ViewMeasurement

    catheter, rig = default_catheter(), default_pinhole_rig()
    n = len(catheter.marker_arclengths_mm)
    rng = np.random.default_rng(RNG_SEED)
    cov3 = np.diag([0.01, 0.01, 0.005])
    observations = []
    for k in range(60):
        q = np.array([0.3 + 0.02 * k, 0.6 - 0.004 * k, -0.4 + 0.01 * k])
        a = q[0] + 1.0
        turn = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        points = catheter.points(q) @ turn.T
        observation = Observation(
            time_s=0.05 * k, q=q, tip_b_mm=points[0] + rng.normal(0, 0.1, 3), tip_cov_b=cov3,
            markers_b_mm=points[1:], markers_cov_b=np.broadcast_to(cov3, (n, 3, 3)).copy(),
        )  # fmt: skip
        if k >= 5 and k % 3:  # single views from here on, two frames in three
            view = rig.views[k % 2]
            rows = [0] if k % 5 == 1 else list(range(1 + n))
            uv = view.project(points[rows]) + rng.normal(0, 0.5, (len(rows), 2))
            if k % 11 == 7:
                uv[0] += 40.0  # a gross error
            observation = replace(observation, tip_b_mm=None, markers_b_mm=None, views=(
                ViewMeasurement(view, np.eye(3), np.zeros(3), uv,
                                np.broadcast_to(0.25 * np.eye(2), (len(rows), 2, 2)).copy(),
                                np.array(rows) - 1),
            ))  # fmt: skip
        observations.append(observation)
    ukf = BendingPlaneUKF(catheter)
    fused = [ukf.step(o) for o in observations]
    monkeypatch.setattr(Gate, "update_views", _update_views_one_by_one)
    ukf = BendingPlaneUKF(catheter)
    separate = [ukf.step(o) for o in observations]
    assert sum(e.nis is not None for e in fused[5:]) >= 30  # the single views updated
    for a, b in zip(fused, separate, strict=True):
        assert (a.delta_L_rad, a.std_rad, a.flags, a.nis, a.nis_dof, a.rejected_outliers) == (
            b.delta_L_rad, b.std_rad, b.flags, b.nis, b.nis_dof, b.rejected_outliers
        ) or (np.isnan(a.delta_L_rad) and np.isnan(b.delta_L_rad))
