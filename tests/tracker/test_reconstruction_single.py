"""Reconstructor.observe's single-frame path against the batch path, frame by frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from models.catheter import default_catheter
from models.imaging import OrthographicPlane, PinholeView, Rig, default_orthographic_rig
from models.rotations import rot_z
from replay.simulation.render import default_render_rig
from replay.simulation.simulator import NoiseSettings, Scene, simulate_frames, sinusoidal
from tests.fresh import last_value
from tests.tracker.test_reconstruction import ARRAYS
from tracker.reconstruction import Reconstructor

ORIGIN = np.zeros(3)
UP = np.array([0.0, 0.0, 1.0])


def _rig(kind: str) -> Rig:
    if kind == "pinhole":
        return default_render_rig()
    if kind == "orthographic":
        return default_orthographic_rig()
    if kind == "distorted":
        dist = [-0.2, 0.05, 1e-3, -5e-4, 0.0]
        return Rig(
            PinholeView.look_at([0.0, -400.0, 0.0], ORIGIN, UP, 2500.0, dist=dist),
            PinholeView.look_at([400.0, 0.0, 0.0], ORIGIN, UP, 2500.0),
        )
    if kind == "three_pinhole":
        return Rig(
            PinholeView.look_at([0.0, -400.0, 0.0], ORIGIN, UP, 1000.0),
            PinholeView.look_at([400.0, 0.0, 0.0], ORIGIN, UP, 1000.0),
            PinholeView.look_at([0.0, 0.0, 400.0], ORIGIN, [0.0, 1.0, 0.0], 1000.0),
        )
    normals = ([0, -1, 0], [1, 0, 0], [0, 0, 1])
    return Rig(*(OrthographicPlane.from_normal(n) for n in normals))


def _scene(kind: str) -> Scene:
    R_w_b = rot_z(0.4) @ np.array([[1.0, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]])
    return Scene(default_catheter(), _rig(kind), R_w_b, np.array([1.0, -2.0, -15.0]))


def _anisotropic(rng: np.random.Generator, n: int, rank: int = 2) -> np.ndarray:
    A = rng.normal(size=(n, 2, rank))
    return A @ A.swapaxes(-1, -2)


def _frames(scene: Scene, seed: int) -> tuple[list, set[int]]:
    """Frames mixing usual ones with every kind of unusual one, and the indices of the
    frames that are not the usual case (missing points)."""
    rng = np.random.default_rng(seed)
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.3, 0.1, 0.1], [3, 3, 3], 3.0)
    noise = NoiseSettings(sigma=0.5, dropout_probability=0.03)
    frames = simulate_frames(scene, trajectory, 1.0, noise, rng)
    replace = dataclasses.replace
    frames[3] = replace(frames[3], q_dot=None)
    frames[4] = replace(frames[4], q_dot=np.array([0.1, np.nan, 0.2]))
    frames[6] = replace(frames[6], time_s=frames[5].time_s + 0.5)  # a gap
    frames[7] = replace(frames[7], time_s=frames[6].time_s)  # no time between
    frames[9] = replace(frames[9], time_s=frames[8].time_s - 0.01)  # back in time
    frames[10] = replace(frames[10], q=list(frames[10].q), q_dot=tuple(frames[10].q_dot))
    n_points = frames[0].uv[0].shape[0]
    # Anisotropic covariances, then singular ones, on otherwise usual frames.
    for i in range(12, 20):
        frames[i] = replace(
            frames[i], cov=tuple(_anisotropic(rng, n_points) for _ in frames[i].cov)
        )
    for i in range(20, 24):
        cov = tuple(_anisotropic(rng, n_points, rank=1) for _ in frames[i].cov)
        frames[i] = replace(frames[i], cov=cov)
    # A missing point: the tip in one view, a marker in another; all views but one.
    uv = [u.copy() for u in frames[30].uv]
    uv[0][0] = np.nan
    frames[30] = replace(frames[30], uv=tuple(uv))
    uv = [u.copy() for u in frames[35].uv]
    uv[-1][-1] = np.nan
    frames[35] = replace(frames[35], uv=tuple(uv))
    uv = [u.copy() for u in frames[40].uv]
    for u in uv[1:]:
        u[:] = np.nan
    frames[40] = replace(frames[40], uv=tuple(uv))
    unusual = {i for i, f in enumerate(frames) if not all(np.isfinite(u).all() for u in f.uv)}
    return frames, unusual


def _assert_identical(a, b) -> None:
    assert type(a.time_s) is type(b.time_s)
    np.testing.assert_equal(a.time_s, b.time_s)  # NaN equals NaN
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.shape(x) == np.shape(y), name
            np.testing.assert_array_equal(x, y, err_msg=name, strict=True)
    assert len(a.views) == len(b.views)
    for va, vb in zip(a.views, b.views, strict=True):
        assert va.view is vb.view
        for name in ("uv", "cov", "point_index", "R_w_b", "o_b_w_mm"):
            np.testing.assert_array_equal(getattr(va, name), getattr(vb, name), err_msg=name)


def _counting(reconstructor: Reconstructor) -> list[int]:
    """Make the batch path of ``reconstructor`` count its calls (the frames not taken by the
    single-frame path)."""
    calls = []
    batch = reconstructor.observe_batch

    def observe_batch(frames):
        calls.append(len(frames))
        return batch(frames)

    reconstructor.observe_batch = observe_batch
    return calls


def _pair(scene: Scene) -> tuple[Reconstructor, Reconstructor]:
    def make():
        return Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)

    return make(), make()


@pytest.mark.parametrize(
    "kind", ["pinhole", "orthographic", "distorted", "three_pinhole", "three_orthographic"]
)
@pytest.mark.parametrize("seed", [0, 1])
def test_observe_is_exactly_the_batch_of_one(kind, seed):
    scene = _scene(kind)
    frames, unusual = _frames(scene, seed)
    new, reference = _pair(scene)
    fallbacks = _counting(new)
    for i, frame in enumerate(frames):
        want = reference.observe_batch([frame])[0]
        _assert_identical(new.observe(frame), want)
        assert len(fallbacks) <= len(unusual), i  # the usual frames take the short path
    assert len(fallbacks) >= len(unusual) > 0
    # Every kind of frame and velocity was there.
    observed = [reference.observe_batch([f])[0] for f in frames]
    assert sum(o.velocity_b_mm_s is not None for o in observed) > 20
    assert any(o.views for o in observed)
    # The state carried on is the same: one more frame continues the same way.
    later = dataclasses.replace(frames[-1], time_s=frames[-1].time_s + 0.05)
    _assert_identical(new.observe(later), reference.observe_batch([later])[0])


def test_the_usual_frames_all_take_the_short_path():
    scene = _scene("pinhole")
    frames, unusual = _frames(scene, 0)
    new, _ = _pair(scene)
    fallbacks = _counting(new)
    for frame in frames:
        new.observe(frame)
    assert len(fallbacks) == len(unusual)


def test_bad_frames_raise_the_batch_errors_and_leave_the_state():
    scene = _scene("pinhole")
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.3, 0.1, 0.1], [3, 3, 3], 0.2)
    rng = np.random.default_rng(2)
    good = simulate_frames(scene, trajectory, 1.0, NoiseSettings(sigma=0.5), rng)
    P = good[0].uv[0].shape[0]
    asymmetric = np.broadcast_to(np.array([[1.0, 0.5], [0.0, 1.0]]), (P, 2, 2))
    indefinite = np.broadcast_to(np.array([[1.0, 2.0], [2.0, 1.0]]), (P, 2, 2))
    # Just outside and just inside the rig's tolerance of -1e-12 of the scale.
    outside = np.broadcast_to(np.diag([1.0, -5e-12]), (P, 2, 2))
    inside = np.broadcast_to(np.diag([1.0, -5e-13]), (P, 2, 2))
    replace = dataclasses.replace
    bad = [
        replace(good[1], cov=(good[1].cov[0], outside)),
        replace(good[1], cov=(inside, good[1].cov[1])),
        replace(good[1], cov=(good[1].cov[0], asymmetric)),
        replace(good[1], cov=(indefinite, good[1].cov[1])),
        replace(good[1], cov=(good[1].cov[0], np.full((P, 2, 2), np.inf))),
        replace(good[1], q=np.array([0.1, np.nan, 0.2])),
        replace(good[1], q=np.zeros(4)),
        replace(good[1], uv=(good[1].uv[0][:-1], good[1].uv[1])),
        replace(good[1], uv=good[1].uv * 2, cov=good[1].cov * 2),
        replace(good[1], time_s=None),
        replace(good[1], time_s=np.nan),
        replace(good[1], time_s=np.inf),  # an infinite interval, with an infinite gap
    ]
    raised = 0
    for frame in bad:
        new, reference = _pair(scene)
        new.max_velocity_gap_s = reference.max_velocity_gap_s = np.inf
        _assert_identical(new.observe(good[0]), reference.observe_batch([good[0]])[0])
        got, want = _outcome(new.observe, frame), _outcome(reference.observe_batch, [frame])
        if isinstance(want, Exception):
            assert type(got) is type(want) and str(got) == str(want)
            raised += 1
        else:  # a time of None or NaN: NaN
            _assert_identical(got, want[0])
        _assert_identical(new.observe(good[1]), reference.observe_batch([good[1]])[0])
    assert raised == 8  # an infinite covariance makes a single-view point, None a NaN


def test_a_point_behind_a_camera_or_on_the_baseline_gets_the_batch_error():
    """The compiled single-frame step refuses what the rig refuses (a point at or behind a
    camera, rays that are parallel): the batch path then raises its error, and the state is
    left as it was."""
    scene = _scene("pinhole")
    trajectory = sinusoidal([0.3, 0.6, 0.4], [0.3, 0.1, 0.1], [3, 3, 3], 0.2)
    good = simulate_frames(
        scene, trajectory, 1.0, NoiseSettings(sigma=0.5), np.random.default_rng(3)
    )
    rig = scene.rig
    centres = [-view.R_cam_w.T @ view.t_cam_w for view in rig.views]
    P = good[0].uv[0].shape[0]
    # Behind the first camera (twice as far from the origin, on its axis) and in front of
    # the others; on the line through the two centres (its rays are that line).

    def pixel(view, point):  # the pinhole's formula, whatever the sign of the depth
        x = view.K @ (view.R_cam_w @ point + view.t_cam_w)
        return x[:2] / x[2]

    for point in (2.0 * centres[0], 0.5 * (centres[0] + centres[1])):
        uv = tuple(np.tile(pixel(view, point), (P, 1)) for view in rig.views)
        frame = dataclasses.replace(good[1], uv=uv)
        new, reference = _pair(scene)
        fallbacks = _counting(new)
        _assert_identical(new.observe(good[0]), reference.observe_batch([good[0]])[0])
        got, want = _outcome(new.observe, frame), _outcome(reference.observe_batch, [frame])
        assert isinstance(want, ValueError), want
        assert type(got) is type(want) and str(got) == str(want)
        assert fallbacks == [1]  # the compiled step gave the frame to the batch path
        _assert_identical(new.observe(good[1]), reference.observe_batch([good[1]])[0])


def _outcome(function, argument):
    try:
        return function(argument)
    except (TypeError, ValueError) as error:
        return error


def test_the_usual_frame_compiles_nothing():
    """The single-frame path hands the compiled kernels arrays of the layout the rig warmed
    them up with: a live session's first frame loads or compiles nothing (in a fresh
    interpreter, as compiled versions only accumulate)."""
    script = """
import numpy as np
from models import _imaging_kernels as K
from tests.tracker.test_reconstruction_single import _frames, _scene
from tracker.reconstruction import Reconstructor
scene = _scene("pinhole")
reconstructor = Reconstructor(scene.catheter, scene.rig, scene.R_w_b, scene.o_b_w_mm)
frames, unusual = _frames(scene, 0)
kernels = (K.triangulate, K.propagate, K.observe_frame, K.to_base)
before = tuple(len(k.signatures) for k in kernels)
batch = []
reconstructor.observe_batch = lambda frames: batch.append(1) or [None]  # counted, not run
observations = [reconstructor.observe(f) for i, f in enumerate(frames[:3]) if i not in unusual]
after = tuple(len(k.signatures) for k in kernels)
print(repr((before, after, len(observations), len(batch))))
"""
    before, after, n, batch = last_value(script)
    assert n >= 2 and batch == 0 and before == (1, 1, 1, 1)
    assert after == before
