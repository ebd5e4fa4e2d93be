"""Registration of the base pose: exact recovery, accuracy under noise, the delta_L convention."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig, default_pinhole_rig
from models.pose import Pose
from models.registration import fit_rigid, register_base, registration_routine

# Noise of the segmented points per axis: 0.5 px at 2.5 px/mm (0.2 mm), or 0.1 mm in a plane.
RIGS = {
    "pinhole": (default_pinhole_rig(), 0.5),
    "orthographic": (default_orthographic_rig(), 0.1),
}
TRUE_POSE = Pose(
    Rotation.from_rotvec(np.radians([8.0, -5.0, 35.0])).as_matrix(), np.array([2.0, -1.5, -15.0])
)
# Stated accuracy of a 9-step routine with 10 image pairs per step at that noise.
ORIGIN_TOLERANCE_MM = 0.1
ROTATION_TOLERANCE_DEG = 0.2


def observe(rig, q, sigma=0.0, rng=None, pose=TRUE_POSE, delta_L=0.0):
    """Each view's tip and markers (n, 2, 2) with Gaussian noise ``sigma`` per axis."""
    catheter = default_catheter()
    s = np.array([catheter.length_mm, *catheter.marker_arclengths_mm])
    points_w = pose.world_from_base(catheter.backbone(q, delta_L, s))
    out = [view.project(points_w) for view in rig.views]
    if sigma:
        out = [uv + sigma * rng.standard_normal(uv.shape) for uv in out]
    return out


def rotation_error_deg(R, R_true):
    return float(np.degrees(Rotation.from_matrix(R @ R_true.T).magnitude()))


def test_routine_is_straight_then_each_bend_in_each_plane():
    q = registration_routine(planes=4)
    assert q.shape == (9, 3)
    np.testing.assert_array_equal(q[0], 0.0)
    np.testing.assert_allclose(np.degrees(q[1::2, 0]), [0, 90, 180, 270])
    np.testing.assert_allclose(q[1:3, 1:], [[0.5, 0.0], [0.8, 0.8]])
    with pytest.raises(ValueError, match="at least one bending plane"):
        registration_routine(planes=0)


def test_fit_rigid_recovers_a_pose_exactly():
    rng = np.random.default_rng(0)
    points_b = rng.normal(size=(6, 3))
    pose = fit_rigid(points_b, TRUE_POSE.world_from_base(points_b))
    np.testing.assert_allclose(pose.R_w_b, TRUE_POSE.R_w_b, atol=1e-12)
    np.testing.assert_allclose(pose.o_b_w_mm, TRUE_POSE.o_b_w_mm, atol=1e-12)
    with pytest.raises(ValueError, match="on a line"):
        fit_rigid(np.outer(np.arange(4.0), [1, 2, 3]), np.outer(np.arange(4.0), [1, 2, 3]))


@pytest.mark.parametrize("kind", RIGS)
def test_noise_free_routine_gives_the_pose_exactly(kind):
    rig, _ = RIGS[kind]
    q = registration_routine()
    registration = register_base(default_catheter(), rig, q, observe(rig, q))
    np.testing.assert_allclose(registration.pose.o_b_w_mm, TRUE_POSE.o_b_w_mm, atol=1e-8)
    assert rotation_error_deg(registration.pose.R_w_b, TRUE_POSE.R_w_b) < 1e-8
    assert max(registration.residual_rms) < 1e-8
    assert registration.n_configurations == 9


@pytest.mark.parametrize("kind", RIGS)
def test_noisy_routine_recovers_the_pose_within_tolerance_and_its_uncertainty(kind):
    rig, sigma = RIGS[kind]
    q = np.repeat(registration_routine(), 10, axis=0)
    rng = np.random.default_rng(1)
    registration = register_base(default_catheter(), rig, q, observe(rig, q, sigma, rng))
    error_mm = registration.pose.o_b_w_mm - TRUE_POSE.o_b_w_mm
    error_deg = rotation_error_deg(registration.pose.R_w_b, TRUE_POSE.R_w_b)
    assert np.linalg.norm(error_mm) < ORIGIN_TOLERANCE_MM
    assert error_deg < ROTATION_TOLERANCE_DEG
    # The reported uncertainty is honest: the errors are a few of its sigmas, and the image
    # residual estimates the noise (sqrt(2) sigma per point).
    assert np.all(np.abs(error_mm) < 4 * registration.std_origin_mm)
    assert np.radians(error_deg) < 4 * np.linalg.norm(registration.std_rotation_base_rad)
    for rms in registration.residual_rms:
        assert rms == pytest.approx(np.sqrt(2) * sigma, rel=0.15)


def test_constant_torsion_during_the_routine_turns_the_base_about_z_b():
    """The convention: delta_L = 0 during the routine. A body twisted by d registers a base
    turned by d about z_b, so that the bending plane in the world stays right."""
    rig, sigma = RIGS["orthographic"]
    q = registration_routine()
    d = np.radians(20.0)
    uv = observe(rig, q, delta_L=d)
    registration = register_base(default_catheter(), rig, q, uv)
    turned = TRUE_POSE.R_w_b @ Rotation.from_rotvec([0.0, 0.0, d]).as_matrix()
    assert rotation_error_deg(registration.pose.R_w_b, turned) < 1e-8
    np.testing.assert_allclose(registration.pose.o_b_w_mm, TRUE_POSE.o_b_w_mm, atol=1e-8)


def test_missing_points_are_left_out():
    rig, sigma = RIGS["pinhole"]
    q = np.repeat(registration_routine(), 3, axis=0)
    uv = observe(rig, q, sigma, np.random.default_rng(2))
    uv[0][::2, 1] = np.nan  # the front view loses the marker in every other pair
    uv[1][1::5, 0] = np.nan
    registration = register_base(default_catheter(), rig, q, uv)
    assert registration.n_points == (q.shape[0] * 2 - 14, q.shape[0] * 2 - 6)
    assert np.linalg.norm(registration.pose.o_b_w_mm - TRUE_POSE.o_b_w_mm) < 0.2


def test_a_routine_that_never_bends_or_is_unseen_is_a_clear_error():
    rig, _ = RIGS["orthographic"]
    catheter = default_catheter()
    straight = np.zeros((5, 3))
    straight[:, 0] = np.linspace(0, np.pi, 5)
    with pytest.raises(ValueError, match="cannot determine the base pose"):
        register_base(catheter, rig, straight, observe(rig, straight))
    q = registration_routine()
    unseen = [np.full((q.shape[0], 2, 2), np.nan), np.full((q.shape[0], 2, 2), np.nan)]
    with pytest.raises(ValueError, match="seen in every view"):
        register_base(catheter, rig, q, unseen)
    with pytest.raises(ValueError, match="must have shape"):
        register_base(catheter, rig, q, [np.zeros((q.shape[0], 3, 2))] * 2)
