"""The session simulator: trajectories, torsion, deflection, views, noise, reproducibility."""

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig, default_pinhole_rig
from replay.simulation.simulator import (
    NoiseSettings,
    base_rotation,
    bending_sweep,
    default_scene,
    hold,
    image_sigma,
    in_plane_joint_offset,
    joints_from_tip_angles,
    out_of_plane_offsets_b,
    point_arclengths,
    ramp,
    simulate_batch,
    simulate_frames,
    torsion_constant,
    torsion_steps,
    torsion_windup,
    true_points_b,
)
from tracker.reconstruction import Reconstructor
from tracker.types import Frame

DELTA_2 = [0.0, np.pi / 2]
VIEWS = ["orthographic", "pinhole"]


def scene_for(view: str, delta_2: float = 0.0):
    rig = default_orthographic_rig() if view == "orthographic" else default_pinhole_rig()
    return default_scene(default_catheter(delta_2), rig)


def reconstructed_b(scene, frames):
    reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
    obs = [reconstructor.observe(f) for f in frames]
    return np.array([np.vstack([o.tip_b_mm, o.markers_b_mm]) for o in obs])


# ------------------------------------------------------------------------------ trajectories
def test_ramp_arrives_at_the_configuration_at_the_stated_rates():
    q_end, q_dot = np.array([0.3, 0.4, -0.2]), np.array([0.5, 0.25, -0.1])
    t = ramp(q_end, q_dot, n_frames=10, frame_interval_s=0.05)
    assert t.time_s == pytest.approx(0.05 * np.arange(10))
    assert t.q[-1] == pytest.approx(q_end)
    assert np.diff(t.q, axis=0) == pytest.approx(np.tile(0.05 * q_dot, (9, 1)))
    assert np.all(t.q_dot == q_dot)


def test_bending_sweep_covers_its_ranges_at_fixed_base_rotation():
    t = bending_sweep(0.7, (-0.5, 0.9), (0.1, 0.6), period_s=2.0, duration_s=4.0)
    assert np.all(t.q[:, 0] == 0.7) and np.all(t.q_dot[:, 0] == 0.0)
    assert t.q[:, 1].min() == pytest.approx(-0.5, abs=1e-2)
    assert t.q[:, 1].max() == pytest.approx(0.9, abs=1e-2)
    assert t.q[:, 2].min() >= 0.1 - 1e-12 and t.q[:, 2].max() <= 0.6 + 1e-12
    # The rates are the derivative of the sweep.
    mid = np.gradient(t.q[:, 1], t.time_s)[5:-5]
    assert mid == pytest.approx(t.q_dot[5:-5, 1], abs=0.05)


def test_base_rotation_and_hold():
    t = base_rotation([0.5, -0.3], speed_rad_s=0.8, duration_s=1.0, frame_rate_hz=10)
    assert t.q[:, 0] == pytest.approx(0.8 * t.time_s)
    assert np.all(t.q[:, 1:] == [0.5, -0.3])
    h = hold([0.1, 0.2, 0.3], duration_s=1.0)
    assert np.all(h.q_dot == 0) and np.all(h.q == [0.1, 0.2, 0.3])


def test_torsion_profiles():
    t = np.linspace(0, 10, 101)
    assert np.all(torsion_constant(t, 1.2) == 1.2)
    steps = torsion_steps(t, [2.0, 5.0], [0.0, 1.0, -1.0])
    assert steps[t < 2].max() == 0 and np.all(steps[(t >= 2) & (t < 5)] == 1)
    assert np.all(steps[t >= 5] == -1)
    # Wind-up: within offset +/- play, and it lags a reversal of the base (hysteresis).
    q_r = np.concatenate([np.linspace(0, 3, 50), np.linspace(3, 0, 50)])
    windup = torsion_windup(q_r, play_rad=0.5, offset_rad=1.0)
    assert np.all(np.abs(windup - 1.0) <= 0.5 + 1e-12)
    assert windup[49] == pytest.approx(0.5) and windup[-1] == pytest.approx(1.5)


# ------------------------------------------------------------------------------ configurations
@pytest.mark.parametrize("theta_deg", [(90.0, 90.0), (45.0, 135.0), (0.0, 180.0), (160.0, 10.0)])
def test_joints_from_tip_angles_inverts_the_model(theta_deg):
    catheter = default_catheter()
    theta = np.radians(theta_deg)
    q = joints_from_tip_angles(catheter, *theta, q_r_rad=0.4)
    assert q[0] == 0.4
    assert catheter.proximal.theta(13.0, q[1]) == pytest.approx(theta[0], abs=1e-9)
    assert catheter.distal.theta(16.0, q[2]) == pytest.approx(theta[1], abs=1e-9)
    if theta_deg == (90.0, 90.0):
        assert q[1:] == pytest.approx([0.0, 0.0], abs=1e-12)  # straight


def test_unreachable_tip_angle_is_a_clear_error():
    with pytest.raises(ValueError, match=r"theta_L1 = 250 deg is not reachable with q_p"):
        joints_from_tip_angles(default_catheter(), np.radians(250), np.radians(90))


@pytest.mark.parametrize("delta_2", DELTA_2)
@pytest.mark.parametrize("deflection_mm", [0.0, 2.0, 10.0])
def test_in_plane_deflection_moves_the_tip_by_the_distance(delta_2, deflection_mm):
    catheter = default_catheter(delta_2)
    q = joints_from_tip_angles(catheter, np.radians(45), np.radians(45))
    offset = in_plane_joint_offset(catheter, q, deflection_mm)
    assert offset[:2] == pytest.approx([0.0, 0.0]) and offset[2] >= 0
    moved = np.linalg.norm(catheter.tip(q + offset) - catheter.tip(q))
    assert moved == pytest.approx(deflection_mm, abs=1e-9)


def test_unreachable_deflection_is_a_clear_error():
    q = np.array([0.0, 0.4, 0.4])
    with pytest.raises(ValueError, match="not reachable by a joint offset"):
        in_plane_joint_offset(default_catheter(), q, 500.0)


def test_out_of_plane_deflection_is_normal_to_the_bending_plane():
    catheter = default_catheter()
    delta_1 = np.array([0.0, 1.1, -2.5])
    offsets = out_of_plane_offsets_b(catheter, delta_1, 4.0)  # (3, P, 3)
    assert offsets.shape == (3, 1 + len(catheter.marker_arclengths_mm), 3)
    assert np.linalg.norm(offsets[:, 0], axis=-1) == pytest.approx([4.0] * 3)  # tip
    in_plane_axis = np.stack([np.cos(delta_1), np.sin(delta_1), 0 * delta_1], -1)
    assert np.einsum("kpi,ki->kp", offsets, in_plane_axis) == pytest.approx(0 * offsets[..., 0])
    assert np.all(offsets[..., 2] == 0)
    # Markers nearer the base move less (cantilever profile).
    assert np.linalg.norm(offsets[0, 1]) < np.linalg.norm(offsets[0, 0])


# ------------------------------------------------------------------------------ frames
@pytest.mark.parametrize("view", VIEWS)
@pytest.mark.parametrize("delta_2", DELTA_2)
def test_noise_free_frames_reconstruct_to_the_true_shape(view, delta_2):
    scene = scene_for(view, delta_2)
    trajectory = bending_sweep(0.3, (0.2, 0.9), (-0.8, 0.7), period_s=1.0, duration_s=1.0)
    truth = torsion_windup(trajectory.q[:, 0] + np.linspace(0, 2, 20), 0.3, 2.0)
    frames = simulate_frames(
        scene, trajectory, truth, NoiseSettings(sigma=0.0), np.random.default_rng(0)
    )
    assert all(isinstance(f, Frame) for f in frames)
    assert [f.delta_L_true_rad for f in frames] == pytest.approx(truth)
    expected = true_points_b(scene.catheter, trajectory.q, truth)
    assert reconstructed_b(scene, frames) == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("view", VIEWS)
def test_deflections_reach_the_frames(view):
    scene = scene_for(view)
    q = joints_from_tip_angles(scene.catheter, np.radians(50), np.radians(60))
    trajectory = hold(q, duration_s=0.2)
    offset = in_plane_joint_offset(scene.catheter, q, 3.0)
    rng = np.random.default_rng(0)
    noise = NoiseSettings(sigma=0.0)
    bent = simulate_frames(scene, trajectory, 0.7, noise, rng, model_joint_offset=offset)
    pushed = simulate_frames(scene, trajectory, 0.7, noise, rng, out_of_plane_mm=3.0)
    plain = reconstructed_b(scene, simulate_frames(scene, trajectory, 0.7, noise, rng))
    for frames in (bent, pushed):
        assert np.all(frames[0].q == q)  # the model sees the commanded joints
        tip_moved = np.linalg.norm(reconstructed_b(scene, frames)[:, 0] - plain[:, 0], axis=-1)
        assert tip_moved == pytest.approx(3.0, abs=1e-6)


def test_image_sigma_is_mm_in_a_plane_and_px_in_a_camera():
    assert image_sigma(default_orthographic_rig().views[0], 1.5) == 1.5
    # 1000 px focal length at 400 mm: 2.5 px per mm at the isocentre.
    assert image_sigma(default_pinhole_rig().views[0], 1.5) == pytest.approx(3.75)


@pytest.mark.parametrize("view", VIEWS)
def test_simulation_is_seeded_and_reproducible(view):
    scene = scene_for(view)
    trajectory = base_rotation([0.5, 0.3], speed_rad_s=0.5, duration_s=1.0)
    noise = NoiseSettings(sigma=1.0, outlier_probability=0.1, dropout_probability=0.1)
    runs = [
        simulate_frames(scene, trajectory, 0.4, noise, np.random.default_rng(7)) for _ in range(2)
    ]
    other = simulate_frames(scene, trajectory, 0.4, noise, np.random.default_rng(8))
    for a, b, c in zip(*runs, other, strict=True):
        assert np.array_equal(a.uv[0], b.uv[0], equal_nan=True)
        assert np.array_equal(a.uv[1], b.uv[1], equal_nan=True)
        assert not np.array_equal(a.uv[0], c.uv[0], equal_nan=True)


def test_outliers_and_dropped_markers():
    scene = scene_for("orthographic")
    trajectory = hold([0.0, 0.5, 0.5], duration_s=5.0)
    clean = simulate_frames(
        scene, trajectory, 0.0, NoiseSettings(sigma=0.0), np.random.default_rng(0)
    )
    noise = NoiseSettings(sigma=0.0, outlier_probability=0.2, outlier_magnitude=8.0)
    dirty = simulate_frames(scene, trajectory, 0.0, noise, np.random.default_rng(0))
    shift = np.array(
        [
            np.linalg.norm(d.uv[0] - c.uv[0], axis=-1)
            for d, c in zip(dirty, clean, strict=True)
        ]
    )
    moved = shift > 1e-9
    assert shift[moved] == pytest.approx(8.0)
    assert 0.1 < moved.mean() < 0.3
    dropped = simulate_frames(
        scene,
        trajectory,
        0.0,
        NoiseSettings(sigma=1.0, dropout_probability=1.0),
        np.random.default_rng(0),
    )
    assert all(np.isnan(f.uv[0]).all() and np.isnan(f.uv[1]).all() for f in dropped)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(sigma=-1.0), "non-negative"),
        (dict(outlier_probability=1.5), r"lie in \[0, 1\]"),
    ],
)
def test_bad_noise_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        NoiseSettings(**kwargs)


def test_points_behind_a_camera_are_a_clear_error():
    scene = scene_for("pinhole")
    far = default_scene(scene.catheter, default_pinhole_rig(distance_mm=10.0))
    with pytest.raises(ValueError, match="behind the camera"):
        simulate_frames(
            far, hold([0, 0.9, 0.9], 0.1), 0.0, NoiseSettings(), np.random.default_rng(0)
        )


# ------------------------------------------------------------------------------ batches
@pytest.mark.parametrize("view", VIEWS)
def test_batch_trials_are_sessions_of_frames(view):
    scene = scene_for(view, np.pi / 2)
    trajectory = ramp([0.0, 0.4, 0.5], [0.5, 0.25, 0.25], 6, 0.05)
    delta_L = np.array([-3.0, 0.0, 2.0])
    batch = simulate_batch(
        scene,
        trajectory,
        delta_L,
        NoiseSettings(sigma=0.0),
        np.random.default_rng(0),
        out_of_plane_mm=1.5,
    )
    assert batch.uv[0].shape == (3, 6, len(point_arclengths(scene.catheter)), 2)
    for i, truth in enumerate(delta_L):
        frames = batch.frames(i)
        single = simulate_frames(
            scene,
            trajectory,
            truth,
            NoiseSettings(sigma=0.0),
            np.random.default_rng(0),
            out_of_plane_mm=1.5,
        )
        for a, b in zip(frames, single, strict=True):
            assert a.uv[0] == pytest.approx(b.uv[0], abs=1e-9)
            assert a.uv[1] == pytest.approx(b.uv[1], abs=1e-9)
            assert a.delta_L_true_rad == truth
