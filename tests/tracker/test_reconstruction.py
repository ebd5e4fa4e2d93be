"""Frames -> observations (tracker.reconstruction) and the finite-difference velocity rule."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import default_orthographic_rig
from models.rotations import rot_z
from replay.simulation.render import default_render_rig
from replay.simulation.simulator import (
    NoiseSettings,
    Scene,
    simulate_frames,
    sinusoidal,
    true_points_b,
)
from tracker.reconstruction import Reconstructor
from tracker.types import velocity_from_positions

ARRAYS = (
    "q",
    "q_dot",
    "tip_b_mm",
    "tip_cov_b",
    "markers_b_mm",
    "markers_cov_b",
    "velocity_b_mm_s",
    "velocity_cov_b",
    "velocity_tip_cov_b",
)


def _scene(kind: str) -> Scene:
    rig = default_render_rig() if kind == "pinhole" else default_orthographic_rig()
    R_w_b = rot_z(0.4) @ np.array([[1.0, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]])
    return Scene(default_catheter(), rig, R_w_b, np.array([1.0, -2.0, -15.0]))


def _frames(scene: Scene, seed: int, sigma: float = 0.5, dropout: float = 0.15):
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.3, 0.1, 0.1], [3, 3, 3], 3.0)
    noise = NoiseSettings(sigma=sigma, dropout_probability=dropout)
    frames = simulate_frames(scene, trajectory, 1.0, noise, np.random.default_rng(seed))
    frames[7] = dataclasses.replace(frames[7], q_dot=None)
    return frames


def _reconstructor(scene: Scene) -> Reconstructor:
    return Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)


def _assert_identical(a, b) -> None:
    assert a.time_s == b.time_s
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert len(a.views) == len(b.views)
    for va, vb in zip(a.views, b.views, strict=True):
        assert va.view is vb.view
        for name in ("uv", "cov", "point_index", "R_w_b", "o_b_w_mm"):
            np.testing.assert_array_equal(getattr(va, name), getattr(vb, name), err_msg=name)


@pytest.mark.parametrize("kind", ["pinhole", "orthographic"])
@pytest.mark.parametrize("seed", [0, 1])
def test_batch_is_exactly_observe_frame_by_frame(kind, seed):
    scene = _scene(kind)
    frames = _frames(scene, seed)
    reconstructor = _reconstructor(scene)
    batch = reconstructor.observe_batch(frames)
    reconstructor.reset()
    single = [reconstructor.observe(f) for f in frames]
    assert sum(len(o.views) for o in single) > 0  # some single-view points
    assert sum(o.velocity_b_mm_s is not None for o in single) > 0
    assert single[7].velocity_b_mm_s is None  # no joint rates, no velocity
    for a, b in zip(batch, single, strict=True):
        _assert_identical(a, b)


def test_batches_continue_from_the_previous_call():
    scene = _scene("orthographic")
    frames = _frames(scene, 2, dropout=0.0)
    reconstructor = _reconstructor(scene)
    whole = reconstructor.observe_batch(frames)
    reconstructor.reset()
    parts = reconstructor.observe_batch(frames[:20]) + reconstructor.observe_batch(frames[20:])
    assert parts[20].velocity_b_mm_s is not None
    for a, b in zip(parts, whole, strict=True):
        _assert_identical(a, b)
    reconstructor.reset()
    assert reconstructor.observe(frames[20]).velocity_b_mm_s is None


def test_velocity_needs_the_tip_twice_within_the_gap():
    scene = _scene("orthographic")
    frames = _frames(scene, 3, dropout=0.0)[:6]
    frames[2] = dataclasses.replace(frames[2], uv=(frames[2].uv[0], np.full_like(frames[2].uv[1], np.nan)))
    frames[5] = dataclasses.replace(frames[5], time_s=frames[4].time_s + 0.5)
    reconstructor = _reconstructor(scene)
    observations = reconstructor.observe_batch(frames)
    has_velocity = [o.velocity_b_mm_s is not None for o in observations]
    assert has_velocity == [False, True, False, False, True, False]
    assert len(observations[2].views) == 1 and not observations[2].has_tip()
    o, before = observations[1], observations[0]
    dt = frames[1].time_s - frames[0].time_s
    np.testing.assert_allclose(o.velocity_b_mm_s, (o.tip_b_mm - before.tip_b_mm) / dt)
    np.testing.assert_allclose(o.velocity_tip_cov_b, o.tip_cov_b / dt)


@pytest.mark.parametrize("kind", ["pinhole", "orthographic"])
def test_noise_free_frames_give_the_true_points_in_the_base_frame(kind):
    """Projection into both views, reconstruction and {W} -> {B} return the points."""
    scene = _scene(kind)
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.3, 0.1, 0.1], [3, 3, 3], 1.0)
    frames = simulate_frames(
        scene, trajectory, 1.0, NoiseSettings(sigma=0.0), np.random.default_rng(0)
    )
    observations = _reconstructor(scene).observe_batch(frames)
    truth = true_points_b(scene.catheter, trajectory.q, np.ones(len(frames)))
    np.testing.assert_allclose([o.tip_b_mm for o in observations], truth[:, 0], atol=1e-8)
    np.testing.assert_allclose([o.markers_b_mm for o in observations], truth[:, 1:], atol=1e-8)


def test_bad_frames_are_named():
    scene = _scene("orthographic")
    frames = _frames(scene, 0)[:3]
    reconstructor = _reconstructor(scene)
    bad = dataclasses.replace(frames[1], uv=(frames[1].uv[0][:-1], frames[1].uv[1]))
    with pytest.raises(ValueError, match=rf"frame at {frames[1].time_s} s has uv\[front\] of shape"):
        reconstructor.observe_batch([frames[0], bad, frames[2]])
    bad = dataclasses.replace(frames[2], q=np.array([0.1, np.nan, 0.2]))
    with pytest.raises(ValueError, match="three finite numbers"):
        reconstructor.observe_batch([frames[0], frames[1], bad])
    assert reconstructor.observe_batch([]) == []


def test_velocity_rule_is_the_same_one_frame_or_many():
    rng = np.random.default_rng(5)
    tips_now, tips_before = rng.normal(size=(2, 4, 7, 3))
    covs_now, covs_before = rng.normal(size=(2, 4, 7, 3, 3))
    dt = rng.uniform(0.01, 0.2, (4, 7))
    v, cov_v, cross = velocity_from_positions(tips_now, covs_now, tips_before, covs_before, dt)
    for i in range(4):
        for k in range(7):
            one = velocity_from_positions(
                tips_now[i, k], covs_now[i, k], tips_before[i, k], covs_before[i, k], dt[i, k]
            )
            for got, want in zip((v[i, k], cov_v[i, k], cross[i, k]), one, strict=True):
                np.testing.assert_array_equal(got, want)
    np.testing.assert_allclose(cov_v[1, 2], (covs_now[1, 2] + covs_before[1, 2]) / dt[1, 2] ** 2)
    dt[2, 3] = 0.0
    with pytest.raises(ValueError, match="positive and finite"):
        velocity_from_positions(tips_now, covs_now, tips_before, covs_before, dt)


@pytest.mark.parametrize("kind", ["pinhole", "orthographic"])
def test_complete_frames_give_the_same_alone_as_among_incomplete_ones(kind):
    """Frames with every point in every view are reconstructed in one call; among frames
    with missing points, grouped by the views that found each point: the same values."""
    scene = _scene(kind)
    frames = _frames(scene, 4)
    complete = [all(np.isfinite(u).all() for u in f.uv) for f in frames]
    assert any(complete) and not all(complete)
    mixed = _reconstructor(scene).observe_batch(frames)
    alone = _reconstructor(scene).observe_batch([f for f, c in zip(frames, complete, strict=True) if c])
    for a, b in zip([o for o, c in zip(mixed, complete, strict=True) if c], alone, strict=True):
        for name in ("tip_b_mm", "tip_cov_b", "markers_b_mm", "markers_cov_b"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert a.views == b.views == ()
