"""Tests of models.imaging: projection, reconstruction and noise propagation."""

from dataclasses import replace

import numpy as np
import pytest

from models.imaging import (
    OrthographicPlane,
    PinholeView,
    Rig,
    default_orthographic_rig,
    default_pinhole_rig,
    isotropic_covariance,
)

DIST_FRONT = np.array([-0.25, 0.08, 1e-3, -5e-4, 0.01])
DIST_SIDE = np.array([0.15, -0.05, -8e-4, 6e-4, 0.0])
RIGS = ["orthographic", "orthographic-oblique", "pinhole", "pinhole-distorted"]


def make_rig(name: str) -> Rig:
    """The default rigs, an oblique orthographic rig and an oblique distorted camera pair."""
    if name == "orthographic":
        return default_orthographic_rig()
    if name == "orthographic-oblique":
        return Rig(
            OrthographicPlane.from_normal([0.3, -1.0, 0.2], in_plane_rotation_rad=0.4),
            OrthographicPlane.from_normal([1.0, 0.5, -0.3], in_plane_rotation_rad=-1.1),
        )
    if name == "pinhole":
        return default_pinhole_rig()
    up = np.array([0.0, 0.0, 1.0])
    front = PinholeView.look_at([40.0, -380.0, 90.0], [5.0, 0.0, -10.0], up, 1100.0)
    side = PinholeView.look_at([390.0, 60.0, -80.0], [0.0, 5.0, 0.0], up, 950.0)
    return Rig(
        replace(front, K=np.array([[1100.0, 0, 300], [0, 1050, 250], [0, 0, 1]]), dist=DIST_FRONT),
        replace(side, dist=DIST_SIDE),
    )


@pytest.mark.parametrize("name", RIGS)
@pytest.mark.parametrize("batch", [(), (7,), (2, 5)])
def test_project_then_reconstruct_returns_the_points(name, batch):
    rig = make_rig(name)
    points_w = np.random.default_rng(1).uniform(-20.0, 20.0, batch + (3,))
    uv_front, uv_side = rig.project(points_w)
    assert uv_front.shape == uv_side.shape == batch + (2,)
    reconstructed = rig.reconstruct(uv_front, uv_side)
    assert reconstructed.shape == points_w.shape
    np.testing.assert_allclose(reconstructed, points_w, rtol=0, atol=1e-7)


@pytest.mark.parametrize("name", ["orthographic", "orthographic-oblique"])
def test_orthographic_reconstruction_is_eq_estDK(name):
    rig = make_rig(name)
    rng = np.random.default_rng(2)
    # Inconsistent measurements, so the pseudo-inverse really solves a least-squares problem.
    uv_front, uv_side = rng.normal(0.0, 10.0, (2, 2, 2))
    P = np.vstack([rig.views[0].projector_w, rig.views[1].projector_w])
    for k in range(2):
        rhs = np.concatenate(
            [rig.views[0].R_w_view @ [*uv_front[k], 0.0], rig.views[1].R_w_view @ [*uv_side[k], 0.0]]
        )
        expected = np.linalg.pinv(P) @ rhs
        np.testing.assert_allclose(rig.reconstruct(uv_front[k], uv_side[k]), expected, atol=1e-12)
    M = rig.reconstruction_matrix()
    assert M.shape == (3, 4)
    np.testing.assert_allclose(
        np.concatenate([uv_front, uv_side], -1) @ M.T, rig.reconstruct(uv_front, uv_side)
    )


@pytest.mark.parametrize("name", ["orthographic", "orthographic-oblique"])
def test_orthographic_reconstruction_maps_difference_vectors(name):
    rig = make_rig(name)
    base_w, tip_w = np.random.default_rng(3).uniform(-20.0, 20.0, (2, 3))
    (base_f, base_s), (tip_f, tip_s) = rig.project(base_w), rig.project(tip_w)
    np.testing.assert_allclose(rig.reconstruct(tip_f - base_f, tip_s - base_s), tip_w - base_w)


@pytest.mark.parametrize("name", RIGS)
def test_projection_jacobian_matches_finite_differences(name):
    rig = make_rig(name)
    points_w = np.random.default_rng(4).uniform(-20.0, 20.0, (4, 3))
    h = 1e-4  # mm; central differences are then accurate to ~1e-8 relative
    for view in (rig.views[0], rig.views[1]):
        J = view.projection_jacobian(points_w)
        assert J.shape == (4, 2, 3)
        for i in range(3):
            step = h * np.eye(3)[i]
            numeric = (view.project(points_w + step) - view.project(points_w - step)) / (2 * h)
            np.testing.assert_allclose(J[..., i], numeric, rtol=1e-6, atol=1e-7)


def test_undistort_inverts_the_distortion():
    view = make_rig("pinhole-distorted").views[0]
    points_w = np.random.default_rng(5).uniform(-60.0, 60.0, (50, 3))
    distorted = view.project(points_w)
    ideal = replace(view, dist=None).project(points_w)
    assert np.abs(distorted - ideal).max() > 1.0  # the distortion is not negligible
    np.testing.assert_allclose(view.undistort(distorted), ideal, rtol=0, atol=1e-9)


def test_default_rigs_show_the_same_images():
    """Points in each plane through the origin: pixel = centre + f / d * (u, -v), exactly."""
    ortho, pinhole = default_orthographic_rig(), default_pinhole_rig(400.0, 1000.0)
    uv = np.random.default_rng(6).uniform(-30.0, 30.0, (10, 2))
    for plane, camera in ((ortho.views[0], pinhole.views[0]), (ortho.views[1], pinhole.views[1])):
        np.testing.assert_allclose(plane.project(uv @ plane.R_w_view[:, :2].T), uv, atol=1e-12)
        centre = np.array([319.5, 239.5])
        expected = centre + 1000.0 / 400.0 * uv * [1.0, -1.0]
        np.testing.assert_allclose(
            camera.project(uv @ plane.R_w_view[:, :2].T), expected, rtol=0, atol=1e-9
        )
    np.testing.assert_allclose(ortho.views[0].normal_w, [0.0, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(ortho.views[1].normal_w, [1.0, 0.0, 0.0], atol=1e-15)


def test_from_normal_builds_a_rotated_frame():
    normal = np.array([0.2, -1.0, 0.4])
    plane = OrthographicPlane.from_normal(normal)
    turned = OrthographicPlane.from_normal(normal, in_plane_rotation_rad=0.3)
    for R in (plane.R_w_view, turned.R_w_view):
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R[:, 2], normal / np.linalg.norm(normal))
    assert plane.R_w_view[2, 0] == pytest.approx(0.0, abs=1e-15)  # u horizontal, v up
    assert plane.R_w_view[2, 1] > 0.0
    u, v = plane.R_w_view[:, 0], plane.R_w_view[:, 1]
    np.testing.assert_allclose(turned.R_w_view[:, 0], np.cos(0.3) * u + np.sin(0.3) * v)
    np.testing.assert_allclose(plane.projector_w @ normal, 0.0, atol=1e-15)
    # A top view falls back to world y as image up instead of failing.
    np.testing.assert_allclose(OrthographicPlane.from_normal([0, 0, 2]).R_w_view, np.eye(3))


def test_far_pinhole_rig_converges_to_the_orthographic_one():
    """Same noisy in-plane measurements, converted to px at a constant 2.5 px/mm at the target."""
    ortho = default_orthographic_rig()
    rng = np.random.default_rng(7)
    points_w = rng.uniform(-5.0, 5.0, (200, 3))
    uv_front, uv_side = ortho.project(points_w)
    uv_front = uv_front + rng.normal(0.0, 0.05, uv_front.shape)
    uv_side = uv_side + rng.normal(0.0, 0.05, uv_side.shape)
    expected = ortho.reconstruct(uv_front, uv_side)

    differences = []
    for distance_mm in (1e3, 1e4, 1e5):
        pinhole = default_pinhole_rig(distance_mm, focal_px=1000.0 * distance_mm / 400.0)
        # Each plane passes through the target and faces its camera, so the point of the plane
        # with in-plane coordinates uv is seen at that measurement's pixel.
        px_front = pinhole.views[0].project(uv_front @ ortho.views[0].R_w_view[:, :2].T)
        px_side = pinhole.views[1].project(uv_side @ ortho.views[1].R_w_view[:, :2].T)
        differences.append(np.abs(pinhole.reconstruct(px_front, px_side) - expected).max())
    assert differences[0] > differences[1] > differences[2]
    assert differences[0] > 1e-2  # perspective matters at 1 m ...
    assert differences[2] < 1e-3  # ... and no longer at 100 m


COVARIANCES = {
    # mm^2 in the planes, px^2 in the cameras; anisotropic, correlated, different per view.
    "orthographic": (
        np.array([[0.04, 0.015], [0.015, 0.01]]),
        np.array([[0.01, -0.004], [-0.004, 0.0225]]),
    ),
    "pinhole": (np.array([[1.0, 0.4], [0.4, 0.5]]), np.array([[0.3, -0.1], [-0.1, 1.2]])),
}


@pytest.mark.parametrize("name", RIGS)
def test_propagated_covariance_matches_monte_carlo(name):
    rig = make_rig(name)
    cov_front, cov_side = COVARIANCES[rig.kind]
    rng = np.random.default_rng(8)
    point_w = np.array([12.0, -8.0, 15.0])
    n = 20_000
    uv_front, uv_side = rig.project(point_w)
    samples = rig.reconstruct(
        uv_front + rng.multivariate_normal(np.zeros(2), cov_front, n),
        uv_side + rng.multivariate_normal(np.zeros(2), cov_side, n),
    )
    sample_cov = np.cov(samples, rowvar=False)
    predicted = rig.reconstruction_covariance(point_w, cov_front, cov_side)
    assert predicted.shape == (3, 3)
    np.testing.assert_allclose(predicted, predicted.T)
    # For Gaussian samples E||S - Sigma||_F^2 = (||Sigma||_F^2 + tr(Sigma)^2) / (n - 1)
    # <= 4 ||Sigma||_F^2 / (n - 1), so the relative Frobenius error has RMS <= 2 / sqrt(n) = 1.4 %;
    # 5 % is more than three times that (the pinhole linearisation error is far smaller).
    error = np.linalg.norm(sample_cov - predicted) / np.linalg.norm(predicted)
    assert error < 0.05
    assert np.all(np.abs(samples.mean(axis=0) - point_w) < 4.0 * np.sqrt(np.diag(predicted) / n))


def test_orthographic_covariance_is_the_linear_propagation():
    rig = make_rig("orthographic-oblique")
    cov_front, cov_side = COVARIANCES["orthographic"]
    M = rig.reconstruction_matrix()
    C = np.zeros((4, 4))
    C[:2, :2], C[2:, 2:] = cov_front, cov_side
    np.testing.assert_allclose(
        rig.reconstruction_covariance(np.zeros(3), cov_front, cov_side), M @ C @ M.T, atol=1e-15
    )


@pytest.mark.parametrize("name", RIGS)
def test_covariance_broadcasts_over_points_and_noise(name):
    rig = make_rig(name)
    rng = np.random.default_rng(9)
    points_w = rng.uniform(-20.0, 20.0, (6, 3))
    sigmas = rng.uniform(0.1, 1.0, 6)
    batched = rig.reconstruction_covariance(points_w, isotropic_covariance(sigmas), np.eye(2))
    assert batched.shape == (6, 3, 3)
    for k in range(6):
        single = rig.reconstruction_covariance(points_w[k], sigmas[k] ** 2 * np.eye(2), np.eye(2))
        np.testing.assert_allclose(batched[k], single, rtol=1e-12, atol=1e-15)
    # Noise-free images give an exact reconstruction.
    zero = rig.reconstruction_covariance(points_w, isotropic_covariance(0.0), np.zeros((2, 2)))
    np.testing.assert_allclose(zero, 0.0, atol=1e-18)


@pytest.mark.parametrize("name", RIGS)
def test_stacked_views_give_reconstruct_and_its_covariance(name):
    """The live loop's one call per set of views is reconstruct, then reconstruction_covariance
    of the reconstructed points, view by view."""
    rig = make_rig(name)
    rng = np.random.default_rng(10)
    points_w = rng.uniform(-20.0, 20.0, (2, 5, 3))
    uv = tuple(u + rng.normal(0.0, 0.3, u.shape) for u in rig.project(points_w))
    covs = COVARIANCES[rig.kind]
    points, cov_w = rig.reconstruct_with_covariance(
        np.stack(uv, axis=-2), np.broadcast_to(np.stack(covs), (2, 5, 2, 2, 2))
    )
    expected = rig.reconstruct(*uv)
    np.testing.assert_allclose(points, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        cov_w, rig.reconstruction_covariance(expected, *covs), rtol=1e-12, atol=1e-15
    )


@pytest.mark.parametrize("name", ["pinhole", "pinhole-distorted"])
def test_camera_covariance_is_the_jacobian_propagation(name):
    """The closed-form lateral model (A = [I | -n] R_cam_w; L^-1 = Z K_2^-1 without distortion)
    is what the projection Jacobian gives: A = L^-1 J R_cam_w, C_e = L^-1 C L^-T."""
    rig = make_rig(name)
    rng = np.random.default_rng(11)
    points_w = rng.uniform(-20.0, 20.0, (4, 3))
    covs = COVARIANCES["pinhole"]
    H = N = 0.0
    for view, C in zip(rig.views, covs, strict=True):
        J = view.projection_jacobian(points_w) @ view.R_cam_w.T  # d pixel / d x_cam
        L = J[..., :2]
        A = np.linalg.solve(L, J) @ view.R_cam_w
        C_e = np.linalg.solve(L, np.swapaxes(np.linalg.solve(L, C), -1, -2))
        H = H + np.swapaxes(A, -1, -2) @ A
        N = N + np.swapaxes(A, -1, -2) @ C_e @ A
    expected = np.linalg.solve(H, np.swapaxes(np.linalg.solve(H, N), -1, -2))
    np.testing.assert_allclose(
        rig.reconstruction_covariance(points_w, *covs), expected, rtol=1e-9, atol=1e-15
    )


def test_stacked_views_are_checked_and_the_bad_view_named():
    rig = make_rig("pinhole")
    uv = np.stack(rig.project(np.zeros((3, 3))), axis=-2)
    good = np.tile(np.eye(2), (3, 2, 1, 1))
    asymmetric = good.copy()
    asymmetric[1, 1, 0, 1] = 0.5
    with pytest.raises(ValueError, match="cov_side must be symmetric"):
        rig.reconstruct_with_covariance(uv, asymmetric)
    negative = good.copy()
    negative[2, 0] = np.diag([1.0, -1.0])
    with pytest.raises(ValueError, match="cov_front must be positive semi-definite"):
        rig.reconstruct_with_covariance(uv, negative)
    # Each view against its own scale: tiny noise in one view is not judged by the other's.
    scaled = good.copy()
    scaled[:, 1] *= 1e-12
    scaled[0, 1, 0, 1] = 1e-12 * 1e-6
    with pytest.raises(ValueError, match="cov_side must be symmetric"):
        rig.reconstruct_with_covariance(uv, scaled)
    with pytest.raises(ValueError, match=r"uv must have shape \(\.\.\., 2, 2\)"):
        rig.reconstruct_with_covariance(uv[..., :1, :], good)
    nan = uv.copy()
    nan[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="uv contains non-finite values"):
        rig.reconstruct_with_covariance(nan, good)


def test_isotropic_covariance():
    np.testing.assert_allclose(isotropic_covariance(0.5), 0.25 * np.eye(2))
    assert isotropic_covariance([1.0, 2.0], dim=3).shape == (2, 3, 3)
    with pytest.raises(ValueError, match="sigma must be finite and >= 0"):
        isotropic_covariance(-0.1)
    with pytest.raises(ValueError, match="sigma must be finite and >= 0"):
        isotropic_covariance(np.nan)


# ------------------------------------------------------------------------------ bad input
def test_parallel_planes_are_rejected():
    front = OrthographicPlane.from_normal([0.0, 1.0, 0.0])
    tilted = OrthographicPlane.from_normal([np.sin(np.deg2rad(0.5)), np.cos(np.deg2rad(0.5)), 0])
    flipped = OrthographicPlane.from_normal([0.0, -1.0, 0.0])
    for side in (tilted, flipped):
        with pytest.raises(ValueError, match="cannot reconstruct: imaging planes are parallel"):
            Rig(front, side)
    Rig(front, OrthographicPlane.from_normal([np.sin(0.05), np.cos(0.05), 0.0]))


def test_coincident_cameras_are_rejected():
    up = [0.0, 0.0, 1.0]
    front = PinholeView.look_at([0.0, -400.0, 0.0], [0.0, 0.0, 0.0], up, 1000.0)
    side = PinholeView.look_at([0.0, -400.0, 0.5], [50.0, 0.0, 0.0], up, 1000.0)
    with pytest.raises(ValueError, match="camera centres are 0.5 mm apart"):
        Rig(front, side)


def test_mixed_view_kinds_are_rejected():
    plane = default_orthographic_rig().views[0]
    camera = default_pinhole_rig().views[1]
    with pytest.raises(ValueError, match="same kind"):
        Rig(plane, camera)
    with pytest.raises(TypeError, match="OrthographicPlane or a PinholeView"):
        Rig(plane, "side")


@pytest.mark.parametrize("name", ["orthographic", "pinhole"])
def test_bad_image_points_are_rejected(name):
    rig = make_rig(name)
    uv_front, uv_side = rig.project(np.zeros((3, 3)))
    uv_front[1, 0] = np.nan
    with pytest.raises(ValueError, match="uv_front contains non-finite values"):
        rig.reconstruct(uv_front, uv_side)
    with pytest.raises(ValueError, match=r"uv_side must have shape \(\.\.\., 2\), got \(3, 3\)"):
        rig.reconstruct(uv_side, np.zeros((3, 3)))
    with pytest.raises(ValueError, match="do not broadcast"):
        rig.reconstruct(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"points_w must have shape \(\.\.\., 3\)"):
        rig.project(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="positive semi-definite"):
        rig.reconstruction_covariance(np.zeros(3), np.diag([1.0, -1.0]), np.eye(2))
    with pytest.raises(ValueError, match=r"cov_side must have shape \(\.\.\., 2, 2\)"):
        rig.reconstruction_covariance(np.zeros(3), np.eye(2), 0.5)


def test_points_behind_a_camera_are_rejected():
    rig = default_pinhole_rig(400.0)
    behind = np.array([[0.0, 0.0, 0.0], [0.0, -500.0, 0.0]])  # behind the front camera at y = -400
    with pytest.raises(ValueError, match="1 point\\(s\\) behind the camera"):
        rig.views[0].project(behind)
    with pytest.raises(ValueError, match="behind the camera"):
        rig.reconstruction_covariance(behind, np.eye(2), np.eye(2))
    rig.views[1].project(behind)  # in front of the side camera: fine


def test_parallel_viewing_rays_are_rejected():
    rig = default_pinhole_rig(400.0)
    on_baseline = np.array([200.0, -200.0, 0.0])  # both cameras see it along the baseline
    with pytest.raises(ValueError, match="viewing rays are parallel"):
        rig.reconstruct(*rig.project(on_baseline))


def test_bad_views_are_rejected():
    with pytest.raises(ValueError, match="rotation matrix"):
        OrthographicPlane(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="non-zero vector"):
        OrthographicPlane.from_normal([0.0, 0.0, 0.0])
    camera = default_pinhole_rig().views[0]
    with pytest.raises(ValueError, match="no skew"):
        replace(camera, K=np.array([[1000.0, 2.0, 320.0], [0.0, 1000.0, 240.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="positive focal lengths"):
        default_pinhole_rig(focal_px=-5.0)
    with pytest.raises(ValueError, match=r"image_size must be \(width, height\)"):
        replace(camera, image_size=(0, 480))
    with pytest.raises(ValueError, match=r"dist must have shape \(5\)"):
        replace(camera, dist=np.zeros(4))
    with pytest.raises(ValueError, match="parallel to the viewing direction"):
        PinholeView.look_at([0.0, 0.0, -400.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1000.0)
    with pytest.raises(ValueError, match="only defined for orthographic rigs"):
        default_pinhole_rig().reconstruction_matrix()
