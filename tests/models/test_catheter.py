"""Direct and instantaneous kinematics of the two-segment catheter (docs/design.md section 3)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.catheter import Catheter, default_catheter
from models.modal import ModalSegment, PowerBasis
from models.rotations import rot_y, rot_z

REFERENCE_PATH = (
    Path(__file__).resolve().parents[3] / "shared" / "reference" / "kinematics_vectors.json"
)
DELTA_2 = pytest.mark.parametrize("delta_2", [0.0, np.pi / 2], ids=["delta2=0", "delta2=pi/2"])


@pytest.fixture(scope="module")
def reference() -> dict:
    if not REFERENCE_PATH.is_file():
        pytest.fail(
            f"reference values not found at {REFERENCE_PATH}; the shared/ directory must sit "
            "beside the repository clone (shared/reference/kinematics_vectors.json)"
        )
    return json.loads(REFERENCE_PATH.read_text())


def _random_configurations(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    q = np.column_stack(
        [rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.0, 1.0, n), rng.uniform(-1.0, 1.0, n)]
    )
    q_dot = rng.normal(0.0, 1.0, (n, 3))
    delta_L = rng.uniform(-np.pi, np.pi, n)
    return q, q_dot, delta_L


def _angular_rate(R_plus: np.ndarray, R_minus: np.ndarray, h: float) -> np.ndarray:
    """omega from R(t+h) R(t-h)^T = exp(2 h [omega]x), in the frame R maps into."""
    return Rotation.from_matrix(R_plus @ np.swapaxes(R_minus, -1, -2)).as_rotvec() / (2 * h)


# ---------------------------------------------------------------------------- reference values
@DELTA_2
def test_default_model_reproduces_the_reference_vectors(reference, delta_2):
    tol = 1e-6
    assert reference["tolerance_mm"] >= tol
    cases = [c for c in reference["cases"] if np.isclose(c["delta2_rad"], delta_2)]
    assert cases, f"no reference case with delta2_rad = {delta_2}"
    catheter = default_catheter(delta_2_rad=delta_2)
    for model_name, segment in (("proximal", catheter.proximal), ("distal", catheter.distal)):
        model = reference["model"][model_name]
        assert segment.length_mm == model["length_mm"]
        np.testing.assert_allclose(segment.A, model["A"], rtol=0, atol=1e-15)
    for case in cases:
        q = np.array([case["q_r_rad"], case["q_p_mm"], case["q_d_mm"]])
        q_dot = np.array([case["qdot"][k] for k in ("q_r_rad_s", "q_p_mm_s", "q_d_mm_s")])
        delta_L = case["delta_L_rad"]
        frames = catheter.frames(q, delta_L)
        checks = {
            "o2_b_mm": frames.o_2_b,
            "R2_b": frames.R_b_2,
            "o4_b_mm": frames.o_4_b,
            "R4_b": frames.R_b_4,
            "theta_L1_rad": catheter.proximal.theta(catheter.proximal.length_mm, q[1]),
            "theta_L2_rad": catheter.distal.theta(catheter.distal.length_mm, q[2]),
            "backbone_b_mm": catheter.backbone(q, delta_L, case["backbone_arclength_mm"]),
            "tip_twist_b": catheter.tip_twist(q, q_dot, delta_L),
        }
        for key, value in checks.items():
            np.testing.assert_allclose(
                value, case[key], rtol=0, atol=tol, err_msg=f"{key} at q = {q}, delta_2 = {delta_2}"
            )
        np.testing.assert_allclose(catheter.tip(q, delta_L), case["o4_b_mm"], rtol=0, atol=tol)


# ---------------------------------------------------------------------------- finite differences
@DELTA_2
def test_tip_twist_matches_finite_differences_of_frames(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    q, q_dot, delta_L = _random_configurations(np.random.default_rng(11), 25)
    h = 1e-5
    plus = catheter.frames(q + h * q_dot, delta_L)
    minus = catheter.frames(q - h * q_dot, delta_L)
    twist = catheter.tip_twist(q, q_dot, delta_L)
    np.testing.assert_allclose(twist[:, :3], (plus.o_4_b - minus.o_4_b) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(twist[:, 3:], _angular_rate(plus.R_b_4, minus.R_b_4, h), atol=1e-6)


@DELTA_2
def test_segment_jacobians_match_finite_differences(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    q, _, delta_L = _random_configurations(np.random.default_rng(12), 25)
    jac = catheter.segment_jacobians(q, delta_L)
    h = 1e-5

    def proximal(c: Catheter, qq: np.ndarray):
        f = c.frames(qq, delta_L)
        return f.o_2_b, f.R_b_2

    def distal(c: Catheter, qq: np.ndarray):
        f = c.frames(qq, delta_L)
        R_2_b = np.swapaxes(f.R_b_2, -1, -2)
        return (R_2_b @ (f.o_4_b - f.o_2_b)[..., None])[..., 0], R_2_b @ f.R_b_4

    def numerical(function, c_plus, c_minus, q_plus, q_minus):
        o_p, R_p = function(c_plus, q_plus)
        o_m, R_m = function(c_minus, q_minus)
        return np.concatenate([(o_p - o_m) / (2 * h), _angular_rate(R_p, R_m, h)], -1)

    step = np.eye(3) * h
    # J_1 columns: (q_p_dot, q_r_dot); J_2 columns: (q_d_dot, delta_2_dot).
    expected_J_1 = [
        numerical(proximal, catheter, catheter, q + step[1], q - step[1]),
        numerical(proximal, catheter, catheter, q + step[0], q - step[0]),
    ]
    c_plus = dataclasses.replace(catheter, delta_2_rad=delta_2 + h)
    c_minus = dataclasses.replace(catheter, delta_2_rad=delta_2 - h)
    expected_J_2 = [
        numerical(distal, catheter, catheter, q + step[2], q - step[2]),
        numerical(distal, c_plus, c_minus, q, q),
    ]
    np.testing.assert_allclose(jac["J_1"], np.stack(expected_J_1, -1), atol=1e-6)
    np.testing.assert_allclose(jac["J_2"], np.stack(expected_J_2, -1), atol=1e-6)

    frames = catheter.frames(q, delta_L)
    R_b_2 = frames.R_b_2
    zero = np.zeros_like(R_b_2)
    np.testing.assert_allclose(
        jac["S_2"], np.block([[R_b_2, zero], [zero, R_b_2]]), rtol=0, atol=1e-15
    )
    # S_1 moves a twist of {2} to the tip: v_4 = v_2 + w x (o_4_b - o_2_b).
    w = np.random.default_rng(13).normal(size=(25, 3))
    moved = (jac["S_1"] @ np.concatenate([np.zeros_like(w), w], -1)[..., None])[..., 0]
    np.testing.assert_allclose(moved[:, :3], np.cross(w, frames.o_4_b - frames.o_2_b), atol=1e-12)
    np.testing.assert_allclose(moved[:, 3:], w, atol=1e-15)


@DELTA_2
def test_shape_vectors_rotate_into_tip_markers_and_tip_velocity(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2, marker_arclengths_mm=(4.0, 13.0, 20.5, 28.0))
    q, q_dot, delta_L = _random_configurations(np.random.default_rng(14), 25)
    vectors = catheter.shape_vectors(q, q_dot)
    Rz = rot_z(q[:, 0] + delta_L)
    np.testing.assert_allclose(vectors.q_r_rad, q[:, 0])
    np.testing.assert_allclose(
        (Rz @ vectors.c_tip_mm[..., None])[..., 0], catheter.tip(q, delta_L), atol=1e-12
    )
    markers = (Rz[:, None] @ vectors.c_markers_mm[..., None])[..., 0]
    np.testing.assert_allclose(
        markers, catheter.backbone(q, delta_L, catheter.marker_arclengths_mm), atol=1e-12
    )
    twist = catheter.tip_twist(q, q_dot, delta_L)
    np.testing.assert_allclose(
        (Rz @ vectors.u_tip_mm_s[..., None])[..., 0], twist[:, :3], atol=1e-10
    )
    assert catheter.shape_vectors(q).u_tip_mm_s is None


@DELTA_2
def test_default_marker_is_frame_2(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    assert catheter.marker_arclengths_mm == (13.0,)
    q, _, delta_L = _random_configurations(np.random.default_rng(15), 5)
    frames = catheter.frames(q, delta_L)
    points = catheter.backbone(q, delta_L, catheter.marker_arclengths_mm)
    np.testing.assert_allclose(points[:, 0], frames.o_2_b, atol=1e-12)
    np.testing.assert_allclose(catheter.tip(q, delta_L), frames.o_4_b, atol=1e-12)


# ---------------------------------------------------------------------------- closed forms
def _arc(kappa: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Circular arc leaving the origin along z and bending toward +x: (x, 0, z), mm."""
    kappa, s = np.broadcast_arrays(np.asarray(kappa, float), np.asarray(s, float))
    small = np.abs(kappa) < 1e-12
    k = np.where(small, 1.0, kappa)
    x = np.where(small, 0.0, (1 - np.cos(k * s)) / k)
    z = np.where(small, s, np.sin(k * s) / k)
    return np.stack([x, np.zeros_like(x), z], -1)


def _constant_curvature_segment(length_mm: float, k: float) -> ModalSegment:
    # theta(s) = pi/2 - k q s / L: curvature kappa = k q / L.
    return ModalSegment(
        length_mm=length_mm,
        A=np.array([[np.pi / 2, 0.0], [0.0, -k]]),
        psi=PowerBasis(2),
        eta=PowerBasis(2),
    )


@DELTA_2
def test_constant_curvature_segments_follow_circular_arcs(delta_2):
    L1, L2, k1, k2 = 13.0, 16.0, 2.0, 2.5
    catheter = Catheter(
        proximal=_constant_curvature_segment(L1, k1),
        distal=_constant_curvature_segment(L2, k2),
        delta_2_rad=delta_2,
    )
    q = np.array(
        [[0.3, 0.8, -0.6], [-2.0, -1.0, 0.9], [1.1, 0.0, 0.5], [0.0, 0.4, 0.0], [2.9, 1.0, 1.0]]
    )
    delta_L = np.array([0.2, -1.3, 0.0, 3.0, -2.5])
    kappa_1, kappa_2 = k1 * q[:, 1] / L1, k2 * q[:, 2] / L2
    Rz = rot_z(q[:, 0] + delta_L)

    s = np.array([0.0, 2.5, 6.5, 10.0, 13.0])
    expected = (Rz[:, None] @ _arc(kappa_1[:, None], s[None, :])[..., None])[..., 0]
    np.testing.assert_allclose(catheter.backbone(q, delta_L, s), expected, rtol=0, atol=1e-12)

    # Tip of {2} bends by kappa_1 L1 about y; the distal arc lies in Rz(delta_2) of its x-z plane.
    R_b_2 = Rz @ rot_y(kappa_1 * L1)
    o_2_b = (Rz @ _arc(kappa_1, L1)[..., None])[..., 0]
    R_2_4 = rot_z(delta_2) @ rot_y(kappa_2 * L2)
    o_4_2 = (rot_z(delta_2) @ _arc(kappa_2, L2)[..., None])[..., 0]
    frames = catheter.frames(q, delta_L)
    np.testing.assert_allclose(frames.R_b_2, R_b_2, atol=1e-12)
    np.testing.assert_allclose(frames.o_2_b, o_2_b, atol=1e-12)
    np.testing.assert_allclose(frames.R_b_4, R_b_2 @ R_2_4, atol=1e-12)
    tip = o_2_b + (R_b_2 @ o_4_2[..., None])[..., 0]
    np.testing.assert_allclose(frames.o_4_b, tip, atol=1e-12)
    np.testing.assert_allclose(catheter.tip(q, delta_L), tip, atol=1e-12)

    s_distal = np.array([3.0, 8.0])
    inner = (rot_z(delta_2) @ _arc(kappa_2[:, None], s_distal[None, :])[..., None])[..., 0]
    expected = o_2_b[:, None] + (R_b_2[:, None] @ inner[..., None])[..., 0]
    np.testing.assert_allclose(
        catheter.backbone(q, delta_L, L1 + s_distal), expected, rtol=0, atol=1e-12
    )


@DELTA_2
def test_straight_catheter_lies_on_the_axis(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    q = np.array([0.7, 0.0, 0.0])
    np.testing.assert_allclose(catheter.tip(q, -2.0), [0.0, 0.0, 29.0], atol=1e-12)
    s = np.array([0.0, 5.0, 13.0, 29.0])
    np.testing.assert_allclose(
        catheter.backbone(q, 1.0, s), np.column_stack([0 * s, 0 * s, s]), atol=1e-12
    )
    # A pure base rotation spins the straight tip about its own axis: no linear velocity.
    twist = catheter.tip_twist(q, np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(twist, [0, 0, 0, 0, 0, 1.0], atol=1e-12)


# ---------------------------------------------------------------------------- batching
def _outputs(catheter: Catheter, q: np.ndarray, q_dot: np.ndarray, delta_L) -> dict:
    frames = catheter.frames(q, delta_L)
    vectors = catheter.shape_vectors(q, q_dot)
    out = {
        "tip": catheter.tip(q, delta_L),
        "backbone": catheter.backbone(q, delta_L, [0.0, 6.0, 13.0, 22.0, 29.0]),
        "backbone_scalar": catheter.backbone(q, delta_L, 17.0),
        "tip_twist": catheter.tip_twist(q, q_dot, delta_L),
        "c_tip": vectors.c_tip_mm,
        "c_markers": vectors.c_markers_mm,
        "u_tip": vectors.u_tip_mm_s,
        "q_r": vectors.q_r_rad,
    }
    out.update({f"frames.{f.name}": getattr(frames, f.name) for f in dataclasses.fields(frames)})
    out.update(catheter.segment_jacobians(q, delta_L))
    return out


@DELTA_2
@pytest.mark.parametrize("batch", [(7,), (2, 5)], ids=["N", "2x5"])
def test_batched_calls_match_a_loop_over_configurations(delta_2, batch):
    catheter = default_catheter(delta_2_rad=delta_2)
    n = int(np.prod(batch))
    q, q_dot, delta_L = _random_configurations(np.random.default_rng(16), n)
    batched = _outputs(
        catheter, q.reshape(batch + (3,)), q_dot.reshape(batch + (3,)), delta_L.reshape(batch)
    )
    singles = [_outputs(catheter, q[i], q_dot[i], float(delta_L[i])) for i in range(n)]
    for key, value in batched.items():
        single_shape = singles[0][key].shape
        assert value.shape == batch + single_shape, key
        looped = np.stack([s[key] for s in singles]).reshape(batch + single_shape)
        np.testing.assert_allclose(value, looped, rtol=0, atol=1e-12, err_msg=key)


@DELTA_2
def test_single_configuration_shapes(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    out = _outputs(catheter, np.array([0.1, 0.5, -0.3]), np.array([0.2, 0.1, 0.4]), 0.7)
    expected = {
        "tip": (3,),
        "backbone": (5, 3),
        "backbone_scalar": (3,),
        "tip_twist": (6,),
        "c_tip": (3,),
        "c_markers": (1, 3),
        "u_tip": (3,),
        "q_r": (),
        "frames.R_b_2": (3, 3),
        "frames.o_2_b": (3,),
        "frames.R_b_4": (3, 3),
        "frames.o_4_b": (3,),
        "J_1": (6, 2),
        "J_2": (6, 2),
        "S_1": (6, 6),
        "S_2": (6, 6),
    }
    assert {k: v.shape for k, v in out.items()} == expected


@DELTA_2
def test_delta_L_broadcasts(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    q, q_dot, delta_L = _random_configurations(np.random.default_rng(17), 6)
    s = np.array([4.0, 13.0, 25.0])
    # A scalar delta_L applies to every configuration.
    np.testing.assert_allclose(
        catheter.tip(q, 0.4), np.stack([catheter.tip(qi, 0.4) for qi in q]), atol=1e-12
    )
    np.testing.assert_allclose(
        catheter.tip_twist(q, q_dot, 0.4),
        np.stack([catheter.tip_twist(qi, qd, 0.4) for qi, qd in zip(q, q_dot, strict=True)]),
        atol=1e-12,
    )
    # One configuration against many delta_L (the estimators' scan over candidate planes).
    tips = catheter.tip(q[0], delta_L)
    assert tips.shape == (6, 3)
    np.testing.assert_allclose(tips, np.stack([catheter.tip(q[0], d) for d in delta_L]), atol=1e-12)
    points = catheter.backbone(q[0], delta_L, s)
    assert points.shape == (6, 3, 3)
    np.testing.assert_allclose(
        points, np.stack([catheter.backbone(q[0], d, s) for d in delta_L]), atol=1e-12
    )
    frames = catheter.frames(q[0], delta_L)
    np.testing.assert_allclose(
        frames.R_b_4, np.stack([catheter.frames(q[0], d).R_b_4 for d in delta_L]), atol=1e-12
    )
    # A (6, 1) grid of delta_L against (6,) configurations gives all pairs.
    grid = catheter.tip(q, delta_L[:, None])
    assert grid.shape == (6, 6, 3)
    np.testing.assert_allclose(grid[2, 4], catheter.tip(q[4], delta_L[2]), atol=1e-12)


@DELTA_2
@pytest.mark.parametrize("markers", [(), (4.0, 13.0, 20.5, 28.0)], ids=["default", "four"])
@pytest.mark.parametrize("with_rates", [True, False], ids=["q_dot", "no q_dot"])
def test_single_configuration_path_matches_the_batched_path(delta_2, markers, with_rates):
    # q of shape (3,) takes a separate fast path; a (1, 3) batch takes the batched one.
    catheter = default_catheter(delta_2_rad=delta_2, marker_arclengths_mm=markers)
    q, q_dot, _ = _random_configurations(np.random.default_rng(18), 20)
    for q_i, q_dot_i in zip(q, q_dot, strict=True):
        rates = q_dot_i if with_rates else None
        single = catheter.shape_vectors(q_i, rates)
        batched = catheter.shape_vectors(q_i[None], None if rates is None else rates[None])
        assert single.q_r_rad.shape == ()
        assert single.q_r_rad == q_i[0]
        np.testing.assert_allclose(single.c_tip_mm, batched.c_tip_mm[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(single.c_markers_mm, batched.c_markers_mm[0], rtol=0, atol=1e-12)
        if with_rates:
            np.testing.assert_allclose(single.u_tip_mm_s, batched.u_tip_mm_s[0], rtol=0, atol=1e-12)
        else:
            assert single.u_tip_mm_s is None


@DELTA_2
def test_delta_L_broadcasts_beyond_the_batch_of_q_for_every_method(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    q, q_dot, delta_L = _random_configurations(np.random.default_rng(19), 5)
    grid = delta_L[:4, None]  # (4, 1) against q's (5,): all 20 pairs
    s = np.array([4.0, 13.0, 25.0])
    calls = {
        "tip": lambda qq, dd, dL: catheter.tip(qq, dL),
        "backbone": lambda qq, dd, dL: catheter.backbone(qq, dL, s),
        "tip_twist": lambda qq, dd, dL: catheter.tip_twist(qq, dd, dL),
        "frames.R_b_4": lambda qq, dd, dL: catheter.frames(qq, dL).R_b_4,
        "J_1": lambda qq, dd, dL: catheter.segment_jacobians(qq, dL)["J_1"],
        "J_2": lambda qq, dd, dL: catheter.segment_jacobians(qq, dL)["J_2"],
        "S_1": lambda qq, dd, dL: catheter.segment_jacobians(qq, dL)["S_1"],
        "S_2": lambda qq, dd, dL: catheter.segment_jacobians(qq, dL)["S_2"],
    }
    for key, call in calls.items():
        value = call(q, q_dot, grid)
        single_shape = call(q[0], q_dot[0], float(grid[0, 0])).shape
        assert value.shape == (4, 5) + single_shape, key
        for i in range(4):
            for j in range(5):
                np.testing.assert_allclose(
                    value[i, j], call(q[j], q_dot[j], float(grid[i, 0])), atol=1e-12, err_msg=key
                )
    # One configuration against many delta_L, for the methods that did not broadcast before.
    np.testing.assert_allclose(
        catheter.tip_twist(q[0], q_dot[0], delta_L),
        np.stack([catheter.tip_twist(q[0], q_dot[0], d) for d in delta_L]),
        atol=1e-12,
    )
    jac = catheter.segment_jacobians(q[0], delta_L)
    assert {k: v.shape for k, v in jac.items()} == {
        "J_1": (5, 6, 2),
        "J_2": (5, 6, 2),
        "S_1": (5, 6, 6),
        "S_2": (5, 6, 6),
    }


@DELTA_2
def test_repeated_and_unsorted_arclengths_give_the_same_points(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    q, _, delta_L = _random_configurations(np.random.default_rng(20), 4)
    s = np.array([29.0, 13.0, 29.0, 0.0, 6.0, 13.0, 20.0])
    points = catheter.backbone(q, delta_L, s)
    for k, s_k in enumerate(s):
        np.testing.assert_allclose(points[:, k], catheter.backbone(q, delta_L, s_k), atol=1e-12)
    np.testing.assert_allclose(points[:, 3], 0.0, atol=0)
    np.testing.assert_allclose(points[:, 0], catheter.tip(q, delta_L), atol=1e-12)


@pytest.mark.parametrize("size", [1, 2, 3, 6])
def test_power_basis_values_and_derivatives(size):
    x = np.random.default_rng(21).uniform(-2.0, 2.0, (4, 5))
    basis = PowerBasis(size)
    k = np.arange(size)
    np.testing.assert_allclose(basis.values(x), x[..., None] ** k, rtol=1e-15, atol=0)
    expected = k * x[..., None] ** np.maximum(k - 1, 0)
    np.testing.assert_allclose(basis.derivatives(x), expected, rtol=1e-15, atol=0)
    assert basis.values(0.5).shape == (size,)


def test_models_compare_and_hash_by_identity():
    # Field-wise == on the array fields would raise; identity semantics make models usable as
    # dict keys and in sets.
    catheter = default_catheter()
    copy = dataclasses.replace(catheter)
    assert catheter == catheter
    assert catheter != copy
    assert catheter.proximal == catheter.proximal
    assert catheter.proximal != dataclasses.replace(catheter.proximal)
    assert len({catheter, copy, catheter}) == 2
    assert len({catheter.proximal, catheter.distal}) == 2


# ---------------------------------------------------------------------------- bad input
def _call(method: str, **kwargs):
    catheter = default_catheter(delta_2_rad=kwargs.pop("delta_2"))
    q = kwargs.pop("q", np.array([0.1, 0.5, -0.3]))
    q_dot = kwargs.pop("q_dot", np.array([0.2, 0.1, 0.4]))
    delta_L = kwargs.pop("delta_L", 0.3)
    s = kwargs.pop("s", np.array([1.0, 20.0]))
    calls = {
        "tip": lambda: catheter.tip(q, delta_L),
        "frames": lambda: catheter.frames(q, delta_L),
        "backbone": lambda: catheter.backbone(q, delta_L, s),
        "shape_vectors": lambda: catheter.shape_vectors(q, q_dot),
        "tip_twist": lambda: catheter.tip_twist(q, q_dot, delta_L),
        "segment_jacobians": lambda: catheter.segment_jacobians(q, delta_L),
    }
    return calls[method]()


ALL_METHODS = ["tip", "frames", "backbone", "shape_vectors", "tip_twist", "segment_jacobians"]
DELTA_L_METHODS = ["tip", "frames", "backbone", "tip_twist", "segment_jacobians"]
RATE_METHODS = ["shape_vectors", "tip_twist"]


@DELTA_2
@pytest.mark.parametrize("method", ALL_METHODS)
@pytest.mark.parametrize(
    "q, message",
    [
        (np.zeros(2), r"q must have shape \(\.\.\., 3\)"),
        (np.zeros((4, 2)), r"q must have shape \(\.\.\., 3\)"),
        (np.float64(0.5), r"q must have shape \(\.\.\., 3\)"),
        (np.array([0.0, np.nan, 0.0]), "q contains non-finite"),
        (np.array([[0.0, 0.1, 0.2], [np.inf, 0.0, 0.0]]), "q contains non-finite"),
    ],
    ids=["(2,)", "(4,2)", "scalar", "NaN", "inf"],
)
def test_bad_joints_raise(delta_2, method, q, message):
    with pytest.raises(ValueError, match=message):
        _call(method, delta_2=delta_2, q=q)


@DELTA_2
@pytest.mark.parametrize("method", RATE_METHODS)
@pytest.mark.parametrize(
    "q_dot, message",
    [
        (np.zeros(4), r"q_dot must have shape \(\.\.\., 3\)"),
        (np.array([0.0, 0.0, -np.inf]), "q_dot contains non-finite"),
    ],
    ids=["(4,)", "inf"],
)
def test_bad_joint_rates_raise(delta_2, method, q_dot, message):
    with pytest.raises(ValueError, match=message):
        _call(method, delta_2=delta_2, q_dot=q_dot)


@DELTA_2
@pytest.mark.parametrize("method", DELTA_L_METHODS)
def test_non_finite_delta_L_raises(delta_2, method):
    with pytest.raises(ValueError, match="delta_L contains non-finite"):
        _call(method, delta_2=delta_2, delta_L=np.nan)


@DELTA_2
@pytest.mark.parametrize("method", DELTA_L_METHODS)
def test_delta_L_that_does_not_broadcast_raises(delta_2, method):
    q = np.zeros((6, 3))
    with pytest.raises(ValueError, match=r"delta_L has batch shape \(4,\), which does not"):
        _call(method, delta_2=delta_2, q=q, q_dot=q, delta_L=np.zeros(4))


@DELTA_2
@pytest.mark.parametrize("method", RATE_METHODS)
def test_joint_rates_that_do_not_broadcast_raise(delta_2, method):
    with pytest.raises(ValueError, match=r"q_dot has batch shape \(4,\), which does not"):
        _call(method, delta_2=delta_2, q=np.zeros((6, 3)), q_dot=np.zeros((4, 3)))


@DELTA_2
@pytest.mark.parametrize(
    "s, message",
    [
        (-0.1, "arclength outside the catheter"),
        (29.000001, "arclength outside the catheter"),
        (np.array([1.0, 30.0]), "arclength outside the catheter"),
        (np.array([1.0, np.nan]), "arclength_mm contains non-finite"),
        (np.ones((2, 2)), "arclength_mm must be a scalar or 1-D"),
    ],
    ids=["negative", "beyond tip", "array beyond tip", "NaN", "2-D"],
)
def test_bad_arclengths_raise(delta_2, s, message):
    with pytest.raises(ValueError, match=message):
        _call("backbone", delta_2=delta_2, s=s)


@pytest.mark.parametrize("length_mm", [0.0, -13.0, np.nan, np.inf])
def test_non_positive_segment_length_raises(length_mm):
    with pytest.raises(ValueError, match="segment length must be positive and finite"):
        ModalSegment(length_mm=length_mm, A=np.zeros((3, 3)))


@pytest.mark.parametrize(
    "A, message",
    [
        (np.zeros((3, 2)), r"modal matrix A has shape \(3, 2\), expected \(3, 3\)"),
        (np.zeros(9), r"modal matrix A has shape \(9,\), expected \(3, 3\)"),
        (np.full((3, 3), np.nan), "modal matrix A contains non-finite"),
    ],
    ids=["(3,2)", "flat", "NaN"],
)
def test_bad_modal_matrix_raises(A, message):
    with pytest.raises(ValueError, match=message):
        ModalSegment(length_mm=13.0, A=A)


@DELTA_2
@pytest.mark.parametrize("marker_mm", [0.0, -1.0, 29.0, 29.5, np.nan], ids=["0", "-1", "tip", "29.5", "NaN"])
def test_marker_outside_the_catheter_raises(delta_2, marker_mm):
    with pytest.raises(ValueError, match="marker arclength .* is outside the catheter"):
        default_catheter(delta_2_rad=delta_2, marker_arclengths_mm=(5.0, marker_mm))


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"delta_2_rad": np.nan}, "delta_2_rad must be finite"),
        ({"quadrature_order": 1}, "quadrature_order must be >= 2"),
    ],
)
def test_bad_catheter_settings_raise(overrides, message):
    catheter = default_catheter()
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(catheter, **overrides)


@DELTA_2
def test_valid_extremes_never_give_nan(delta_2):
    catheter = default_catheter(delta_2_rad=delta_2)
    edges = np.array([-1.0, 0.0, 1.0])
    q = np.stack(np.meshgrid([-np.pi, 0.0, np.pi], edges, edges, indexing="ij"), -1).reshape(-1, 3)
    q_dot = np.ones_like(q)
    for value in _outputs(catheter, q, q_dot, np.pi).values():
        assert np.all(np.isfinite(value))
    assert np.all(np.isfinite(catheter.backbone(q, 0.0, np.linspace(0.0, 29.0, 30))))


def test_points_of_a_few_configurations_are_the_single_configuration_points():
    catheter = default_catheter()
    q = np.random.default_rng(5).uniform(-0.9, 0.9, (6, 3))
    expected = np.array([catheter.points(row) for row in q])
    np.testing.assert_allclose(catheter.points_of(q), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(catheter.points_of(q), catheter.points(q), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        catheter.points_of(q[0])


class _OtherPowers(PowerBasis):
    """The power basis under another type: the model's general path, not the compiled one."""


def test_the_compiled_points_of_power_bases_are_those_of_the_general_path():
    """A model with power bases makes its basis rows in the compiled kernel; the same model
    whose basis is another type goes the general way (rows made by the basis): the same
    points, one configuration or several."""
    catheter = default_catheter(0.4)
    other = dataclasses.replace(
        catheter, proximal=dataclasses.replace(catheter.proximal, eta=_OtherPowers(
            catheter.proximal.eta.size)),
    )  # fmt: skip
    assert catheter._power_sizes is not None and other._power_sizes is None
    q = np.random.default_rng(6).uniform(-1.2, 1.2, (7, 3))
    np.testing.assert_array_equal(catheter.points_of(q), other.points_of(q))
    for row in q:
        np.testing.assert_array_equal(catheter.points(row), other.points(row))


def test_the_outline_of_one_configuration_is_its_backbone_to_rounding():
    """``outline`` (the compiled path of ``points`` for the default model's power bases)
    gives ``backbone``'s points to rounding, at arclengths in either segment, at their joint
    and at both ends; arclengths off the catheter and non-finite joints are refused alike,
    and a batch or a non-finite delta_L goes through ``backbone``."""
    catheter = default_catheter()
    rng = np.random.default_rng(11)
    L1, L = catheter.proximal.length_mm, catheter.length_mm
    arclengths = [(0.0, L1, L), tuple(np.linspace(0.0, L, 12).tolist()),
                  tuple(np.sort(rng.uniform(0, L, 7)).tolist())]
    q, _, delta_L = _random_configurations(rng, 50)
    for k in range(50):
        for s in arclengths:
            outline = catheter.outline(q[k], float(delta_L[k]), s)
            assert outline.shape == (len(s), 3)
            np.testing.assert_allclose(
                outline, catheter.backbone(q[k], float(delta_L[k]), np.array(s)),
                rtol=0, atol=1e-12,
            )
    with pytest.raises(ValueError, match="arclength outside the catheter"):
        catheter.outline(q[0], 0.0, (0.0, L + 1.0))
    with pytest.raises(ValueError):
        catheter.outline(np.array([0.0, np.nan, 0.0]), 0.0, (0.0, L))
    with pytest.raises(ValueError):
        catheter.outline(q[0], float("nan"), (0.0, L))
