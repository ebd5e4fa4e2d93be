"""Per-frame estimators: closed forms against the paper's least-squares baseline and the bound."""

import numpy as np
import pytest

from models.bounds import (
    block_diagonal,
    crb_markers,
    crb_tip,
    crb_velocity,
    information_from_covariance,
)
from models.catheter import default_catheter
from models.imaging import default_orthographic_rig, isotropic_covariance
from models.rotation_fit import fit_rotation_z
from models.rotations import rotate_z, wrap_angle
from tracker.estimators import estimator_names, make_estimator
from tracker.estimators.per_frame import PerFrameEstimator, build_problem_batch, closed_form_batch
from tracker.types import Flag, Observation, velocity_from_positions

DELTA_2 = [0.0, np.pi / 2]
BENT = [np.array([0.3, 0.8, 0.6]), np.array([-1.2, -0.7, 0.9])]


def observation_for(catheter, q, delta_L, rng, sigma=1.0, q_dot=None, cov_scale=None):
    """Noisy tip, markers and velocity, noise drawn from the given {B} covariance."""
    cov = np.eye(3) * sigma**2 if cov_scale is None else cov_scale
    tip = catheter.tip(q, delta_L) + rng.multivariate_normal(np.zeros(3), cov)
    markers_true = catheter.backbone(q, delta_L, catheter.marker_arclengths_mm)
    n = markers_true.shape[0]
    markers = markers_true + rng.multivariate_normal(np.zeros(3), cov, size=n)
    kwargs = {}
    if q_dot is not None:
        v = catheter.tip_twist(q, q_dot, delta_L)[:3] + rng.multivariate_normal(np.zeros(3), cov)
        kwargs = dict(q_dot=q_dot, velocity_b_mm_s=v, velocity_cov_b=cov)
    return Observation(
        time_s=0.0,
        q=q,
        tip_b_mm=tip,
        tip_cov_b=cov,
        markers_b_mm=markers,
        markers_cov_b=np.broadcast_to(cov, (n, 3, 3)).copy(),
        **kwargs,
    )


def cost(kind, catheter, obs, delta_L):
    """The paper's unweighted squared residual of one estimator at delta_L."""
    if kind == "tip-position":
        r = obs.tip_b_mm - catheter.tip(obs.q, delta_L)
    elif kind == "body-positions":
        r = obs.markers_b_mm - catheter.backbone(obs.q, delta_L, catheter.marker_arclengths_mm)
        r = np.concatenate([r.ravel(), obs.tip_b_mm - catheter.tip(obs.q, delta_L)])
    else:
        r = obs.velocity_b_mm_s - catheter.tip_twist(obs.q, obs.q_dot, delta_L)[:3]
    return float(np.sum(r**2))


@pytest.mark.parametrize("delta_2", DELTA_2)
@pytest.mark.parametrize("kind", ["tip-position", "body-positions", "tip-velocity"])
def test_closed_form_matches_least_squares_where_baseline_converges(delta_2, kind):
    catheter = default_catheter(delta_2)
    rng = np.random.default_rng(1)
    closed, baseline = make_estimator(kind, catheter), make_estimator(kind + "-lsq", catheter)
    checked = 0
    for _ in range(40):
        q = np.array([rng.uniform(-np.pi, np.pi), rng.uniform(0.3, 1), rng.uniform(-1, 1)])
        q_dot = rng.uniform(-1, 1, 3) * np.array([2.0, 1.0, 1.0])
        truth = rng.uniform(-2.5, 2.5)  # within 145 degrees of the baseline's start at 0
        obs = observation_for(catheter, q, truth, rng, sigma=0.5, q_dot=q_dot)
        a, b = closed.step(obs), baseline.step(obs)
        assert a.valid and b.valid
        if Flag.NOT_CONVERGED in b.flags:
            continue
        # The unweighted baseline and the closed form minimise the same cost for isotropic noise:
        # same minimiser up to the baseline's stopping tolerance, and never a lower cost.
        assert abs(wrap_angle(a.delta_L_rad - b.delta_L_rad)) < 1e-4
        cost_closed = cost(kind, catheter, obs, a.delta_L_rad)
        assert cost_closed <= cost(kind, catheter, obs, b.delta_L_rad) * (1 + 1e-9) + 1e-12
        assert a.std_rad == pytest.approx(b.std_rad, rel=1e-4)
        checked += 1
    assert checked >= 35


@pytest.mark.parametrize("kind", ["tip-position", "body-positions"])
def test_baseline_started_at_zero_stalls_at_half_turn_where_closed_form_does_not(kind):
    """delta_L = 180 degrees with q_r = 0: the baseline's start (0) is the maximum of its cost.

    scipy's least_squares sees a vanishing gradient there and stops, reporting a bending plane
    that is wrong by 180 degrees; the closed form takes the global minimum.
    """
    catheter = default_catheter()
    rng = np.random.default_rng(7)
    q = np.array([0.0, 0.8, 0.5])
    wrong = 0
    for _ in range(50):
        obs = observation_for(catheter, q, np.pi, rng, sigma=1e-3)
        closed = make_estimator(kind, catheter).step(obs)
        baseline = make_estimator(kind + "-lsq", catheter).step(obs)
        assert abs(wrap_angle(closed.delta_L_rad - np.pi)) < 1e-3
        wrong += abs(wrap_angle(baseline.delta_L_rad - np.pi)) > np.pi / 2
    assert wrong >= 45


def _orthographic_cov(sigma_mm):
    rig = default_orthographic_rig()
    cov2 = isotropic_covariance(sigma_mm)
    return rig.reconstruction_covariance(np.zeros(3), cov2, cov2)


@pytest.mark.parametrize("delta_2", DELTA_2)
@pytest.mark.parametrize("q", BENT, ids=["bent-a", "bent-b"])
def test_monte_carlo_error_sits_on_the_bound_at_1mm(delta_2, q):
    """RMS error of each closed-form estimator within 10% of the CRB, 2,000 seeded trials.

    Noise: 1 mm isotropic in each of two orthogonal imaging planes, propagated through the
    paper's pseudo-inverse reconstruction (the base pose is registered: {B} = {W}). The tip
    velocity is the instantaneous model velocity plus noise of a finite difference at 4 Hz
    while the base turns at 5 rad/s, where the velocity model is exact.
    """
    catheter = default_catheter(delta_2)
    cov = _orthographic_cov(1.0)
    dt = 0.25
    cov_v = 2 * cov / dt**2
    q_dot = np.array([5.0, 0.4, -0.3])
    truth = 0.7
    rng = np.random.default_rng(11)
    n_trials = 2000
    tip0 = catheter.tip(q, truth)
    markers0 = catheter.backbone(q, truth, catheter.marker_arclengths_mm)
    v0 = catheter.tip_twist(q, q_dot, truth)[:3]
    errors = {"tip-position": [], "body-positions": [], "tip-velocity": []}
    estimators = {name: make_estimator(name, catheter) for name in errors}
    n = markers0.shape[0]
    for _ in range(n_trials):
        obs = Observation(
            time_s=0.0,
            q=q,
            q_dot=q_dot,
            tip_b_mm=tip0 + rng.multivariate_normal(np.zeros(3), cov),
            tip_cov_b=cov,
            markers_b_mm=markers0 + rng.multivariate_normal(np.zeros(3), cov, size=n),
            markers_cov_b=np.broadcast_to(cov, (n, 3, 3)).copy(),
            velocity_b_mm_s=v0 + rng.multivariate_normal(np.zeros(3), cov_v),
            velocity_cov_b=cov_v,
        )
        for name, est in estimators.items():
            errors[name].append(wrap_angle(est.step(obs).delta_L_rad - truth))
    bounds = {
        "tip-position": crb_tip(catheter, q, truth, cov),
        "body-positions": crb_markers(catheter, q, truth, cov),
        "tip-velocity": crb_velocity(catheter, q, q_dot, truth, cov_v),
    }
    for name, errs in errors.items():
        rms = np.sqrt(np.mean(np.square(errs)))
        assert bounds[name] < 0.2, f"{name}: configuration not in the local regime"
        assert rms == pytest.approx(bounds[name], rel=0.10), name


def test_exact_tip_solution_variance_equals_bound_and_bound_grows_when_straight():
    """The bound equals the Monte Carlo variance of the exact tip solution (10%, 2,000 trials)."""
    catheter = default_catheter()
    cov = _orthographic_cov(1.0)
    q = np.array([0.2, 0.9, 0.4])
    truth = -1.0
    rng = np.random.default_rng(3)
    est = make_estimator("tip-position", catheter)
    tip0 = catheter.tip(q, truth)
    errs = [
        wrap_angle(
            est.step(
                Observation(0.0, q, tip_b_mm=tip0 + rng.multivariate_normal(np.zeros(3), cov),
                            tip_cov_b=cov)
            ).delta_L_rad
            - truth
        )
        for _ in range(2000)
    ]
    bound = crb_tip(catheter, q, truth, cov)
    assert np.var(errs) == pytest.approx(bound**2, rel=0.10)
    bends = np.array([0.4, 0.2, 0.1, 0.05, 0.01, 0.001])
    straightening = [crb_tip(catheter, np.array([0.0, b, b]), truth, cov) for b in bends]
    assert np.all(np.diff(straightening) > 0)
    assert straightening[-1] > 100 * straightening[0]
    assert crb_tip(catheter, np.zeros(3), truth, cov) > 1e6


def test_weighted_closed_form_uses_anisotropic_covariance():
    """With strongly anisotropic noise the weighted closed form beats the unweighted baseline."""
    catheter = default_catheter()
    q = np.array([0.0, 0.8, 0.5])
    truth = 0.4
    cov = np.diag([25.0, 0.04, 0.04])
    rng = np.random.default_rng(5)
    closed, baseline = make_estimator("tip-position", catheter), make_estimator(
        "tip-position-lsq", catheter
    )
    e_closed, e_base = [], []
    for _ in range(400):
        obs = observation_for(catheter, q, truth, rng, cov_scale=cov)
        e_closed.append(wrap_angle(closed.step(obs).delta_L_rad - truth))
        e_base.append(wrap_angle(baseline.step(obs).delta_L_rad - truth))
    assert np.sqrt(np.mean(np.square(e_closed))) < 0.7 * np.sqrt(np.mean(np.square(e_base)))


def test_missing_data_is_flagged_not_silent():
    catheter = default_catheter()
    q = np.array([0.1, 0.5, 0.5])
    obs = Observation(0.0, q, tip_b_mm=np.full(3, np.nan), tip_cov_b=np.eye(3))
    for name in ["tip-position", "body-positions", "tip-velocity", "tip-position-lsq"]:
        est = make_estimator(name, catheter).step(obs)
        assert not est.valid
        assert Flag.NO_MEASUREMENT in est.flags
    markers = catheter.backbone(q, 0.3, catheter.marker_arclengths_mm)
    markers[0] = np.nan
    obs = Observation(0.0, q, tip_b_mm=catheter.tip(q, 0.3), tip_cov_b=np.eye(3),
                      markers_b_mm=markers, markers_cov_b=np.stack([np.eye(3)]))
    est = make_estimator("body-positions", catheter).step(obs)
    assert est.valid and Flag.PARTIAL in est.flags
    assert abs(wrap_angle(est.delta_L_rad - 0.3)) < 1e-9


def test_unknown_estimator_name_is_one_clear_error():
    with pytest.raises(ValueError, match="unknown estimator 'tip'.*tip-position"):
        make_estimator("tip", default_catheter())
    assert "ukf" in estimator_names()


# ------------------------------------------------------------------------------ single frame
def _random_covariance(rng, isotropic):
    if isotropic:
        return np.diag([1.0, 1.0, 0.5]) * rng.uniform(0.2, 2.0)
    a = rng.normal(size=(3, 3))
    return a @ a.T + 0.1 * np.eye(3)


def _weighted_cost(y, c, W, phi):
    r = (y - rotate_z(c, phi)).ravel()
    return r @ W @ r


@pytest.mark.parametrize("delta_2", DELTA_2)
@pytest.mark.parametrize("isotropic", [True, False], ids=["isotropic", "anisotropic"])
def test_one_frame_is_the_batched_closed_form_of_the_same_frames(delta_2, isotropic):
    """The single-frame path (compiled) and the batched one (numpy) agree to rounding."""
    catheter = default_catheter(delta_2)
    rng = np.random.default_rng(21)
    n = 40
    q = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)])
    q_dot = rng.uniform(-1, 1, (n, 3))
    truth = rng.uniform(-np.pi, np.pi, n)
    shape = catheter.shape_vectors(q, q_dot)
    c = np.concatenate([shape.c_tip_mm[:, None], shape.c_markers_mm], axis=1)
    cov = np.stack([[_random_covariance(rng, isotropic) for _ in c[0]] for _ in range(n)])
    noise = np.stack([[rng.multivariate_normal(np.zeros(3), s) for s in frame] for frame in cov])
    points = rotate_z(c, (q[:, 0] + truth)[:, None]) + noise
    before = points[:, 0] - rng.normal(size=(n, 3))
    velocity, velocity_cov, _ = velocity_from_positions(
        points[:, 0], cov[:, 0], before, cov[:, 0], 0.1
    )
    for kind, name in PerFrameEstimator.NAMES.items():
        if kind == "velocity":
            problem = build_problem_batch(
                kind, shape, velocity_b_mm_s=velocity, velocity_cov_b=velocity_cov
            )
        else:
            problem = build_problem_batch(kind, shape, points, cov)
        delta_L, std = closed_form_batch(problem)
        estimator = make_estimator(name, catheter)
        for i in range(n):
            obs = Observation(
                time_s=0.0, q=q[i], q_dot=q_dot[i], tip_b_mm=points[i, 0], tip_cov_b=cov[i, 0],
                markers_b_mm=points[i, 1:], markers_cov_b=cov[i, 1:],
                velocity_b_mm_s=velocity[i], velocity_cov_b=velocity_cov[i],
            )  # fmt: skip
            estimate = estimator.step(obs)
            assert abs(wrap_angle(estimate.delta_L_rad - delta_L[i])) < 1e-12, (name, i)
            assert estimate.std_rad == pytest.approx(std[i], rel=1e-12), (name, i)


@pytest.mark.parametrize("n_points", [1, 2, 3])
def test_rotation_fit_of_one_problem_is_a_batch_of_one_and_information_per_vector_is_joint(
    n_points,
):
    """fit_rotation_z: one problem (compiled) = a batch of one (numpy); W per vector = joint W;
    and the minimiser is converged (no neighbour has a lower cost)."""
    rng = np.random.default_rng(n_points)
    for _ in range(50):
        c = rng.normal(size=(n_points, 3)) * 10
        cov = np.stack([_random_covariance(rng, False) for _ in range(n_points)])
        y = rotate_z(c, rng.uniform(-np.pi, np.pi)) + rng.normal(size=(n_points, 3))
        W_points = information_from_covariance(cov)
        W_joint = information_from_covariance(block_diagonal(cov))
        np.testing.assert_allclose(block_diagonal(W_points), W_joint, rtol=1e-12, atol=1e-12)
        one = fit_rotation_z(y, c, W_joint)
        others = [fit_rotation_z(y[None], c[None], W_joint[None])]
        if n_points > 1:
            others += [fit_rotation_z(y, c, W_points), fit_rotation_z(y[None], c[None], W_points[None])]
        for fit in others:
            assert abs(wrap_angle(float(np.squeeze(fit.phi_rad)) - one.phi_rad)) < 1e-12
            for name in ("fisher_information", "cost", "informative_radius_mm"):
                value = float(np.squeeze(getattr(fit, name)))
                assert value == pytest.approx(getattr(one, name), rel=1e-10, abs=1e-12), name
        at = _weighted_cost(y, c, W_joint, one.phi_rad)
        assert at == pytest.approx(one.cost, rel=1e-9, abs=1e-9)
        for step in (-1e-5, 1e-5):
            assert at <= _weighted_cost(y, c, W_joint, one.phi_rad + step)


def test_information_of_small_covariances_is_the_inverse():
    """The per-frame path (compiled, a frame's few blocks) equals numpy's inverse, and fails
    the same way on a covariance that is not finite or not positive definite."""
    rng = np.random.default_rng(4)
    for n in (1, 2, 4, 5):
        cov = np.stack([_random_covariance(rng, False) for _ in range(n)])
        expected = np.linalg.inv(cov)
        np.testing.assert_allclose(information_from_covariance(cov), expected, rtol=1e-10)
        np.testing.assert_allclose(information_from_covariance(cov[0]), expected[0], rtol=1e-10)
    for bad, message in (
        (np.diag([1.0, -1.0, 1.0]), "not positive definite"),
        (np.diag([1.0, np.nan, 1.0]), "non-finite"),
        (np.stack([np.eye(3), np.diag([1.0, 1.0, 0.0])]), "not positive definite"),
    ):
        with pytest.raises(ValueError, match=message):
            information_from_covariance(bad)
