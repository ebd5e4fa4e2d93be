"""The grid filter's compiled kernels against plain numpy written here (the arithmetic the
filter did in numpy before), on random inputs with fixed seeds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tracker.estimators import grid_kernels
from tracker.estimators.deviation import deviation_jacobian, expansion_basis, quadratic_moments
from tracker.estimators.grid import _mixture_constants
from tracker.estimators.linalg_kernels import _lu_solve
from tracker.estimators.measurement import mixture_log_likelihood

N = 256
CELL_RAD = 2 * math.pi / N
ANGLES = -math.pi + CELL_RAD * np.arange(N)
COS, SIN = np.cos(ANGLES), np.sin(ANGLES)


def spd(rng, shape, scale=1.0):
    """Random symmetric positive-definite 3 x 3 matrices (..., 3, 3)."""
    B = rng.normal(size=shape + (3, 3))
    return scale * (B @ np.swapaxes(B, -1, -2) + 0.5 * np.eye(3))


def basis(mu):
    """The cells' basis rows [cos, sin, 1, expansion_basis(mu)] (8, N)."""
    return np.vstack([COS, SIN, np.ones(N), expansion_basis(mu.T).T])


def frame(rng, G=4):
    """A frame's group arrays as the filter passes them."""
    return dict(
        y=rng.normal(0.0, 20.0, (G, 3)),
        c=rng.normal(0.0, 20.0, (G, 3)),
        JK=rng.normal(0.0, 3.0, (G, 3, 5)),
        R_bar=spd(rng, (G,)),
        M=spd(rng, (G,), 0.01),
    )


def reference_group_terms(y, c, JK, R_bar, M, present, q_r, Sigma, p, mu, deviation):
    """What the numpy filter computed: C, J, noise, S and L^-1 C of the present groups."""
    y, c, JK, S = y[present], c[present], JK[present], R_bar[present] + M[present]
    G = y.shape[0]
    J = np.zeros((G, 3, 2))
    noise = S
    if deviation:
        J = deviation_jacobian(JK[..., :2], JK[..., 2:], mu[:, int(np.argmax(p))])
        bias, spread = quadratic_moments(JK[..., 2:], Sigma)
        noise = S + spread
        S = noise + J @ Sigma @ J.mT
        c = c + bias
    cq, sq = math.cos(q_r), math.sin(q_r)
    u_x, u_y = cq * y[:, 0] + sq * y[:, 1], cq * y[:, 1] - sq * y[:, 0]
    zero = np.zeros(G)
    C = np.stack(
        [np.stack([-u_x, -u_y, c[:, 0]], -1), np.stack([-u_y, u_x, c[:, 1]], -1),
         np.stack([zero, zero, c[:, 2] - y[:, 2]], -1)], axis=1,
    )  # fmt: skip
    if deviation:
        C = np.concatenate((C, JK), axis=-1)
    return C, J, noise, S, np.linalg.inv(np.linalg.cholesky(S)) @ C


@pytest.mark.parametrize("deviation", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_group_terms_are_the_numpy_maps_and_covariances(deviation, seed):
    rng = np.random.default_rng(seed)
    arrays = frame(rng)
    present = np.array([True, False, True, True])
    Sigma = spd(rng, ())[:2, :2] * 0.01
    p = rng.uniform(0.0, 1.0, N)
    mu = rng.normal(0.0, 0.1, (2, N))
    args = (*arrays.values(), present, 0.7, Sigma, p, mu, deviation)
    C, A, J, noise, S, ok = grid_kernels.group_terms(*args)
    assert ok
    for got, expected in zip((C, J, noise, S, A), reference_group_terms(*args), strict=True):
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


def test_group_terms_report_a_covariance_that_is_not_positive_definite():
    rng = np.random.default_rng(3)
    arrays = frame(rng, G=2)
    arrays["R_bar"][1] = -np.eye(3)
    present = np.ones(2, dtype=bool)
    args = (*arrays.values(), present, 0.1, np.eye(2), np.ones(N), np.zeros((2, N)), False)
    *_, S, ok = grid_kernels.group_terms(*args)
    assert not ok
    np.testing.assert_allclose(S[1], -np.eye(3) + arrays["M"][1], rtol=1e-15)


@pytest.mark.parametrize("k", [3, 8])
def test_squared_residuals_are_the_whitened_errors_squared(k):
    rng = np.random.default_rng(4)
    A = rng.normal(0.0, 5.0, (3, 3, k))
    mu = rng.normal(0.0, 0.2, (2, N))
    white = A.reshape(9, k) @ basis(mu)[:k]
    expected = np.add.reduce(np.square(white).reshape(3, 3, N), axis=1)
    np.testing.assert_allclose(
        grid_kernels.squared_residuals(A, COS, SIN, mu), expected, rtol=1e-12, atol=1e-12
    )


def reference_posterior(prior, d2, dim, outlier_probability, outlier_scale):
    log_lik = np.add.reduce(
        mixture_log_likelihood(d2, dim, outlier_probability, outlier_scale), axis=0
    )
    p = prior * np.exp(log_lik - log_lik.max())
    mass = p.sum()
    return (p / mass if mass > 0.0 else p), mass


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize(
    "outlier_probability, outlier_scale", [(0.02, 30.0), (0.2, 3.0), (0.0, 1.0)]
)
def test_posterior_is_the_prior_times_the_heavy_tailed_likelihood(
    dim, outlier_probability, outlier_scale
):
    rng = np.random.default_rng(5)
    d2 = rng.uniform(0.0, 1.0, (4, N)) ** 3 * 3000.0  # near and far groups, some underflow
    prior = rng.uniform(0.0, 1.0, N)
    prior /= prior.sum()
    shrink, scale2, ratio, mixture = _mixture_constants(dim, outlier_probability, outlier_scale)
    factors = np.exp(grid_kernels.exponents(d2, shrink, scale2, mixture))
    p, ok = grid_kernels.posterior(prior, factors, ratio, mixture)
    expected, _ = reference_posterior(prior, d2, dim, outlier_probability, outlier_scale)
    assert ok
    np.testing.assert_allclose(p, expected, rtol=1e-12, atol=1e-300)


def test_posterior_defers_to_logs_where_the_prior_has_no_mass_under_the_likelihood():
    """The numpy filter's test: the prior's mass times the likelihood shifted by its maximum
    below 1e-250 (here the prior lives where the likelihood is below exp(-600))."""
    rng = np.random.default_rng(6)
    d2 = np.tile((np.arange(N) - 40.0) ** 2 * 2.0, (2, 1))
    prior = np.where(np.arange(N) > 200, rng.uniform(0.5, 1.0, N), 0.0)
    prior /= prior.sum()
    shrink, scale2, ratio, mixture = _mixture_constants(3, 0.0, 1.0)
    factors = np.exp(grid_kernels.exponents(d2, shrink, scale2, mixture))
    _, ok = grid_kernels.posterior(prior, factors, ratio, mixture)
    _, mass = reference_posterior(prior, d2, 3, 0.0, 1.0)
    assert not ok and not mass > 1e-250


@pytest.mark.parametrize("center", [np.pi - 0.01, -np.pi + 0.004, 0.3, -2.0])
def test_circular_moments_are_the_mean_and_the_wrapped_spread(center):
    p = np.exp(-0.5 * ((ANGLES - center + np.pi) % (2 * np.pi) - np.pi) ** 2 / 0.3**2) + 1e-3
    p /= p.sum()
    mean, var = grid_kernels.circular_moments(p, COS, SIN, ANGLES, CELL_RAD)
    expected = math.atan2(p @ SIN, p @ COS)
    spread = (ANGLES - expected + np.pi) % (2 * np.pi) - np.pi
    assert mean == pytest.approx(expected, abs=1e-14)
    assert var == pytest.approx(p @ spread**2, rel=1e-12)


def test_reductions_are_numpys():
    rng = np.random.default_rng(7)
    for n in (1, 7, 8, 9, 2048, 2051):
        x, y = rng.normal(size=n), rng.normal(size=n)
        assert grid_kernels._sum(x) == pytest.approx(x.sum(), rel=1e-12, abs=1e-13)
        assert grid_kernels._dot(x, y) == pytest.approx(x @ y, rel=1e-12, abs=1e-13)
        assert grid_kernels._min(x) == x.min() and grid_kernels._max(x) == x.max()


def test_attenuate_multiplies_by_the_wrapped_normals_coefficients():
    rng = np.random.default_rng(8)
    full = rng.normal(size=(3, N // 2 + 1)) + 1j * rng.normal(size=(3, N // 2 + 1))
    k2 = np.arange(N // 2 + 1, dtype=float) ** 2
    expected = full[:, :50] * np.exp(-0.5 * 0.01 * k2[:50])
    spectrum = full.copy()
    grid_kernels.attenuate(spectrum[:, :50], 0.01, k2)
    np.testing.assert_allclose(spectrum[:, :50], expected, rtol=1e-14)
    np.testing.assert_array_equal(spectrum[:, 50:], full[:, 50:])


def reference_mix_in_jump(p, means, mu, jump, clip):
    """The numpy filter's predict after its convolution: (p', mu')."""
    p, mu = p.copy(), mu.copy()
    if clip:
        p = np.maximum(p, 0.0)
    scale = (1.0 - jump) / p.sum()
    if scale == 0.0:
        return np.full(p.size, 1.0 / p.size), np.zeros_like(mu)
    if means is None and jump == 0.0:
        return p * scale, mu
    if means is None:
        means = p * mu
    weight = p + max(jump / p.size / scale, 1e-300)
    return weight * scale, means / weight


@pytest.mark.parametrize("have_means", [True, False])
@pytest.mark.parametrize("jump, clip", [(1e-3, True), (0.0, False), (0.0, True), (1.0, False)])
def test_mix_in_jump_normalises_mixes_and_moment_matches(have_means, jump, clip):
    rng = np.random.default_rng(9)
    p = rng.uniform(-0.01, 1.0, N)
    p[:20] = 0.0
    mu = rng.normal(0.0, 0.1, (2, N))
    means = rng.normal(0.0, 0.1, (2, N))
    expected_p, expected_mu = reference_mix_in_jump(
        p, means if have_means else None, mu, jump, clip
    )
    got_mu = mu.copy()
    got_p = grid_kernels.mix_in_jump(p.copy(), means, have_means, got_mu, jump, clip)
    np.testing.assert_allclose(got_p, expected_p, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(got_mu, expected_mu, rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("inlier", [[True, True, True], [True, False, True]])
def test_update_deviation_is_the_kalman_update_of_every_cell(inlier):
    rng = np.random.default_rng(10)
    inlier = np.array(inlier)
    J = rng.normal(0.0, 2.0, (3, 3, 2))
    noise = spd(rng, (3,))
    C = rng.normal(0.0, 3.0, (3, 3, 8))
    Sigma = np.array([[0.02, 0.004], [0.004, 0.03]])
    mu = rng.normal(0.0, 0.1, (2, N))
    H = J[inlier].reshape(-1, 2)
    S = H @ Sigma @ H.T
    m = H.shape[0]
    for g in range(m // 3):
        S[3 * g : 3 * g + 3, 3 * g : 3 * g + 3] += noise[inlier][g]
    gain = np.linalg.solve(S, H @ Sigma).T
    expected_mu = mu - (gain @ C[inlier].reshape(m, 8)) @ basis(mu)
    expected_Sigma = Sigma - gain @ H @ Sigma
    got_mu = mu.copy()
    got_Sigma = grid_kernels.update_deviation(J, noise, inlier, C, Sigma, COS, SIN, got_mu)
    np.testing.assert_allclose(got_mu, expected_mu, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(got_Sigma, 0.5 * (expected_Sigma + expected_Sigma.T), rtol=1e-12)
    assert got_Sigma[0, 1] == got_Sigma[1, 0]


def test_lu_solve_is_numpys_solve_and_reports_a_singular_matrix():
    rng = np.random.default_rng(11)
    for m in (3, 6, 12):
        S = rng.normal(size=(m, m))  # not symmetric: the pivoting is exercised
        B = rng.normal(size=(m, 2))
        expected = np.linalg.solve(S, B)
        X = B.copy()
        logdet = _lu_solve(S, X, np.empty((m, m)))
        np.testing.assert_allclose(X, expected, rtol=1e-10)
        assert logdet == pytest.approx(np.linalg.slogdet(S)[1], rel=1e-10)
    assert _lu_solve(np.ones((3, 3)), np.ones((3, 2)), np.empty((3, 3))) == -np.inf


def test_mixture_constants_are_those_of_the_shared_likelihood():
    """exp of the kernels' terms is the shared mixture likelihood up to a constant."""
    d2 = np.linspace(0.0, 400.0, 50)
    shrink, scale2, ratio, _ = _mixture_constants(3, 0.05, 10.0)
    log_kernel = -0.5 * d2 / scale2 + np.log1p(ratio * np.exp(-0.5 * shrink * d2))
    shared = mixture_log_likelihood(d2, 3, 0.05, 10.0)
    np.testing.assert_allclose(log_kernel - log_kernel[0], shared - shared[0], atol=1e-12)
