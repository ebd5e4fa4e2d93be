"""Two-segment steerable catheter: direct and instantaneous kinematics (DESIGN.md section 3).

``delta_L`` enters the model only through a rotation about ``z_b``::

    o_4_b(q, delta_L) = Rz(q_r + delta_L) c(q_p, q_d)

so :meth:`Catheter.shape_vectors` computes, once per configuration, the delta_L-independent
vectors ``c`` of the tip and of every marker and ``u`` of the tip velocity; every estimator
then only rotates fixed vectors about one axis.

Joint vectors are ``q = (q_r [rad], q_p [mm], q_d [mm])`` with shape (..., 3); every
function is vectorised over the leading batch axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models.modal import ModalSegment, PowerBasis, SegmentQuadrature
from models.rotations import rot_y, rot_z, rotate_z, skew

Array = np.ndarray

DEFAULT_QUADRATURE_ORDER = 16


def check_joints(q: Array, name: str = "q") -> Array:
    """Joint values as a float array of shape (..., 3), finite, or a ValueError naming the fault."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 3:
        raise ValueError(
            f"{name} must have shape (..., 3) = (q_r [rad], q_p [mm], q_d [mm]), got {q.shape}"
        )
    if not np.all(np.isfinite(q)):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    return q


def _check_finite(x: Array, name: str) -> Array:
    x = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    return x


@dataclass(frozen=True)
class Frames:
    """Frames {2} and {4} relative to the base {B}, batch shape (...)."""

    R_b_2: Array  # (..., 3, 3)
    o_2_b: Array  # (..., 3), mm
    R_b_4: Array  # (..., 3, 3)
    o_4_b: Array  # (..., 3), mm


@dataclass(frozen=True)
class ShapeVectors:
    """The delta_L-independent part of the model for a batch of configurations.

    For bending-plane angle ``delta_1 = q_r + delta_L``: tip ``o_4_b = Rz(delta_1) c_tip``,
    marker k ``Rz(delta_1) c_markers[..., k, :]`` and tip velocity ``Rz(delta_1) u_tip``.
    """

    q_r_rad: Array  # (...)
    c_tip_mm: Array  # (..., 3)
    c_markers_mm: Array  # (..., n_markers, 3)
    u_tip_mm_s: Array | None = None  # (..., 3), present when joint rates were given


@dataclass(frozen=True)
class _Plan:
    """Quadrature for a fixed set of arclengths, split over the two segments."""

    quad_1: SegmentQuadrature
    quad_2: SegmentQuadrature
    in_proximal: Array  # (n,) bool, arclength <= L1
    index: Array  # (n,) column of each arclength in its segment's integrals


def _axis_y_batch(shape: tuple[int, ...]) -> Array:
    out = np.zeros(shape + (3,))
    out[..., 1] = 1.0
    return out


@dataclass(frozen=True)
class Catheter:
    """Two-segment catheter: proximal segment (driven by q_p), distal segment (by q_d).

    Parameters
    ----------
    proximal, distal : ModalSegment
        Segment models.
    delta_2_rad : float
        Fixed angle of the distal bending plane about z_2.
    marker_arclengths_mm : tuple of float
        Arclengths of the backbone markers used by the Body Positions estimator, mm from the
        base of the proximal segment, each in (0, L1 + L2].
    quadrature_order : int
        Gauss-Legendre nodes per integral.
    """

    proximal: ModalSegment
    distal: ModalSegment
    delta_2_rad: float = 0.0
    marker_arclengths_mm: tuple[float, ...] = ()
    quadrature_order: int = DEFAULT_QUADRATURE_ORDER
    _plans: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not np.isfinite(self.delta_2_rad):
            raise ValueError(f"delta_2_rad must be finite, got {self.delta_2_rad}")
        if self.quadrature_order < 2:
            raise ValueError(f"quadrature_order must be >= 2, got {self.quadrature_order}")
        markers = tuple(float(s) for s in self.marker_arclengths_mm)
        if not markers:
            markers = (self.proximal.length_mm, self.length_mm)
        for s in markers:
            if not (0.0 < s <= self.length_mm):
                raise ValueError(
                    f"marker arclength {s} mm is outside the catheter (0, {self.length_mm}] mm"
                )
        object.__setattr__(self, "marker_arclengths_mm", markers)
        # The tip is always the last column of the marker plan.
        self._plan(markers + (self.length_mm,))

    @property
    def length_mm(self) -> float:
        """Total length L1 + L2 of the bending section, mm."""
        return self.proximal.length_mm + self.distal.length_mm

    # ------------------------------------------------------------------ plans and shapes
    def _plan(self, arclengths: tuple[float, ...]) -> _Plan:
        plan = self._plans.get(arclengths)
        if plan is not None:
            return plan
        s = np.asarray(arclengths, dtype=float)
        L1 = self.proximal.length_mm
        in_proximal = s <= L1
        limits_1 = np.append(s[in_proximal], L1)
        limits_2 = np.append(s[~in_proximal] - L1, self.distal.length_mm)
        index = np.empty(s.size, dtype=int)
        index[in_proximal] = np.arange(in_proximal.sum())
        index[~in_proximal] = np.arange((~in_proximal).sum())
        plan = _Plan(
            quad_1=SegmentQuadrature.build(self.proximal, limits_1, self.quadrature_order),
            quad_2=SegmentQuadrature.build(self.distal, limits_2, self.quadrature_order),
            in_proximal=in_proximal,
            index=index,
        )
        if len(self._plans) < 64:
            self._plans[arclengths] = plan
        return plan

    def _check_arclengths(self, arclength_mm: Array) -> Array:
        s = _check_finite(arclength_mm, "arclength_mm")
        if np.any(s < 0.0) or np.any(s > self.length_mm):
            raise ValueError(
                f"arclength outside the catheter: values must lie in [0, {self.length_mm}] mm,"
                f" got min {s.min():.6g}, max {s.max():.6g}"
            )
        return s

    def _shape(self, plan: _Plan, q_p: Array, q_d: Array, rates: bool) -> dict[str, Array]:
        """Shape vectors c(s) at delta_1 = 0 for the plan's arclengths (last column: segment end).

        Returns c (..., n, 3) and, with rates, dc/dq_p and dc/dq_d (..., n, 3), with the tip
        angles theta_1(L1), theta_2(L2) and their derivatives.
        """
        seg1, seg2 = self.proximal, self.distal
        q1, q2 = plan.quad_1, plan.quad_2
        a1, a2 = seg1.coefficients(q_p), seg2.coefficients(q_d)
        th1 = a1 @ q1.psi_nodes.T
        th2 = a2 @ q2.psi_nodes.T
        cos1, sin1, cos2, sin2 = np.cos(th1), np.sin(th1), np.cos(th2), np.sin(th2)
        x1, z1 = cos1 @ q1.weights, sin1 @ q1.weights
        x2, z2 = cos2 @ q2.weights, sin2 @ q2.weights
        th1_end = a1 @ q1.psi_end
        th2_end = a2 @ q2.psi_end
        c1, s1 = np.cos(th1_end)[..., None], np.sin(th1_end)[..., None]
        cd2, sd2 = np.cos(self.delta_2_rad), np.sin(self.delta_2_rad)
        # Distal points: p_1(L1) + Ry(pi/2 - theta_1(L1)) Rz(delta_2) p_2(s - L1).
        X1, Z1 = x1[..., -1:], z1[..., -1:]
        c_dist = np.stack(
            [X1 + s1 * cd2 * x2 + c1 * z2, sd2 * x2 + 0.0 * X1, Z1 - c1 * cd2 * x2 + s1 * z2], -1
        )
        c_prox = np.stack([x1, np.zeros_like(x1), z1], -1)
        n = plan.in_proximal.size
        c = np.empty(c_prox.shape[:-2] + (n, 3))
        c[..., plan.in_proximal, :] = c_prox[..., plan.index[plan.in_proximal], :]
        c[..., ~plan.in_proximal, :] = c_dist[..., plan.index[~plan.in_proximal], :]
        out = {"c": c, "c_end_1": c_prox[..., -1, :], "c_end_2": c_dist[..., -1, :]}
        out.update(theta_1=th1_end, theta_2=th2_end)
        if not rates:
            return out
        b1, b2 = seg1.coefficient_rates(q_p), seg2.coefficient_rates(q_d)
        dth1 = b1 @ q1.psi_nodes.T
        dth2 = b2 @ q2.psi_nodes.T
        dx1, dz1 = (-sin1 * dth1) @ q1.weights, (cos1 * dth1) @ q1.weights
        dx2, dz2 = (-sin2 * dth2) @ q2.weights, (cos2 * dth2) @ q2.weights
        dth1_end = (b1 @ q1.psi_end)[..., None]
        dX1, dZ1 = dx1[..., -1:], dz1[..., -1:]
        zero2 = np.zeros_like(x2)
        dc_dist_p = np.stack(
            [
                dX1 + (c1 * cd2 * x2 - s1 * z2) * dth1_end,
                zero2,
                dZ1 + (s1 * cd2 * x2 + c1 * z2) * dth1_end,
            ],
            -1,
        )
        dc_dist_d = np.stack(
            [s1 * cd2 * dx2 + c1 * dz2, sd2 * dx2, -c1 * cd2 * dx2 + s1 * dz2], -1
        )
        dc_prox_p = np.stack([dx1, np.zeros_like(dx1), dz1], -1)
        dc_p = np.empty_like(c)
        dc_d = np.zeros_like(c)
        dc_p[..., plan.in_proximal, :] = dc_prox_p[..., plan.index[plan.in_proximal], :]
        dc_p[..., ~plan.in_proximal, :] = dc_dist_p[..., plan.index[~plan.in_proximal], :]
        dc_d[..., ~plan.in_proximal, :] = dc_dist_d[..., plan.index[~plan.in_proximal], :]
        out.update(
            dc_dq_p=dc_p,
            dc_dq_d=dc_d,
            dc_end_1_dq_p=dc_prox_p[..., -1, :],
            dtheta_1=b1 @ q1.psi_end,
            dtheta_2=b2 @ q2.psi_end,
        )
        return out

    # ------------------------------------------------------------------ public API
    def shape_vectors(self, q: Array, q_dot: Array | None = None) -> ShapeVectors:
        """The delta_L-independent vectors of the tip, every marker and the tip velocity.

        Parameters
        ----------
        q : array, shape (..., 3)
            Joint values (q_r [rad], q_p [mm], q_d [mm]).
        q_dot : array, shape (..., 3), optional
            Joint rates (rad/s, mm/s, mm/s); when given, ``u_tip_mm_s`` is filled.
        """
        q = check_joints(q)
        markers = self.marker_arclengths_mm + (self.length_mm,)
        shape = self._shape(self._plan(markers), q[..., 1], q[..., 2], rates=q_dot is not None)
        c = shape["c"]
        u = None
        if q_dot is not None:
            q_dot = check_joints(q_dot, "q_dot")
            c_tip = c[..., -1, :]
            # d/dt [Rz(delta_1) c] = Rz(delta_1) [q_r_dot z x c + dc/dq_p q_p_dot + dc/dq_d q_d_dot]
            u = (
                q_dot[..., 0:1] * np.stack([-c_tip[..., 1], c_tip[..., 0], 0.0 * c_tip[..., 2]], -1)
                + shape["dc_dq_p"][..., -1, :] * q_dot[..., 1:2]
                + shape["dc_dq_d"][..., -1, :] * q_dot[..., 2:3]
            )
        return ShapeVectors(
            q_r_rad=q[..., 0], c_tip_mm=c[..., -1, :], c_markers_mm=c[..., :-1, :], u_tip_mm_s=u
        )

    def tip(self, q: Array, delta_L: Array | float = 0.0) -> Array:
        """Tip position o_4_b, mm, shape (..., 3)."""
        q = check_joints(q)
        delta_L = _check_finite(delta_L, "delta_L")
        shape = self._shape(self._plan((self.length_mm,)), q[..., 1], q[..., 2], rates=False)
        return rotate_z(shape["c"][..., -1, :], q[..., 0] + delta_L)

    def backbone(self, q: Array, delta_L: Array | float, arclength_mm: Array | float) -> Array:
        """Backbone points at the given arclengths, mm, in {B}.

        Parameters
        ----------
        q : array, shape (..., 3)
        delta_L : float or array broadcastable to q's batch shape, rad
        arclength_mm : float or array, shape (n,)
            Arclengths in [0, L1 + L2] mm from the base of the proximal segment.

        Returns
        -------
        points_b : array, shape (..., 3) for a scalar arclength, else (..., n, 3)
        """
        q = check_joints(q)
        delta_L = _check_finite(delta_L, "delta_L")
        s = self._check_arclengths(arclength_mm)
        scalar = s.ndim == 0
        s = np.atleast_1d(s)
        if s.ndim != 1:
            raise ValueError(f"arclength_mm must be a scalar or 1-D, got shape {s.shape}")
        # Points at s = 0 are the base origin; give them a tiny positive limit for quadrature.
        shape = self._shape(self._plan(tuple(s.tolist())), q[..., 1], q[..., 2], rates=False)
        points = rotate_z(shape["c"], (q[..., 0] + delta_L)[..., None])
        return points[..., 0, :] if scalar else points

    def frames(self, q: Array, delta_L: Array | float = 0.0) -> Frames:
        """Frames {2} and {4} in {B} (paper eqs. dk1, DKfull)."""
        q = check_joints(q)
        delta_L = _check_finite(delta_L, "delta_L")
        delta_1 = q[..., 0] + delta_L
        shape = self._shape(self._plan((self.length_mm,)), q[..., 1], q[..., 2], rates=False)
        R_b_2 = rot_z(delta_1) @ rot_y(np.pi / 2 - shape["theta_1"])
        R_2_4 = rot_z(self.delta_2_rad) @ rot_y(np.pi / 2 - shape["theta_2"])
        return Frames(
            R_b_2=R_b_2,
            o_2_b=rotate_z(shape["c_end_1"], delta_1),
            R_b_4=R_b_2 @ R_2_4,
            o_4_b=rotate_z(shape["c"][..., -1, :], delta_1),
        )

    def segment_jacobians(self, q: Array, delta_L: Array | float = 0.0) -> dict[str, Array]:
        """Segment Jacobians and adjoints of the paper's instantaneous kinematics (IK1-IKfinal).

        Returns a dict with
        ``J_1`` (..., 6, 2): twist of frame {2} in {B} per (q_p_dot, q_r_dot);
        ``J_2`` (..., 6, 2): twist of frame {4} relative to {2}, in {2}, per (q_d_dot,
        delta_2_dot); ``S_1``, ``S_2`` (..., 6, 6): the adjoints that move them to the tip in {B}.
        Twists are [v (mm/s); w (rad/s)].
        """
        q = check_joints(q)
        delta_L = _check_finite(delta_L, "delta_L")
        batch = q.shape[:-1]
        delta_1 = q[..., 0] + delta_L
        plan = self._plan((self.length_mm,))
        shape = self._shape(plan, q[..., 1], q[..., 2], rates=True)
        Rz1 = rot_z(delta_1)
        R_b_2 = Rz1 @ rot_y(np.pi / 2 - shape["theta_1"])
        Rzd2 = rot_z(np.broadcast_to(self.delta_2_rad, batch))
        o_2_b = rotate_z(shape["c_end_1"], delta_1)
        e_y = _axis_y_batch(batch)
        e_z = np.zeros(batch + (3,))
        e_z[..., 2] = 1.0
        # Segment 1 in {B}: d(o_2_b)/dq_p and the rotation about y_1 by -dtheta_1/dq_p.
        J_1 = np.zeros(batch + (6, 2))
        J_1[..., :3, 0] = rotate_z(shape["dc_end_1_dq_p"], delta_1)
        J_1[..., 3:, 0] = (Rz1 @ e_y[..., None])[..., 0] * -shape["dtheta_1"][..., None]
        J_1[..., :3, 1] = np.cross(e_z, o_2_b)
        J_1[..., 3:, 1] = e_z
        # Segment 2 in {2}: p_2 at delta_2, tip angle rate, and rotation about z_2.
        x2, z2 = self._segment_end(self.distal, q[..., 2], rates=True)
        p2 = np.stack([x2[0], np.zeros_like(x2[0]), z2[0]], -1)
        dp2 = np.stack([x2[1], np.zeros_like(x2[1]), z2[1]], -1)
        o_4_2 = (Rzd2 @ p2[..., None])[..., 0]
        J_2 = np.zeros(batch + (6, 2))
        J_2[..., :3, 0] = (Rzd2 @ dp2[..., None])[..., 0]
        J_2[..., 3:, 0] = (Rzd2 @ e_y[..., None])[..., 0] * -shape["dtheta_2"][..., None]
        J_2[..., :3, 1] = np.cross(e_z, o_4_2)
        J_2[..., 3:, 1] = e_z
        S_1 = np.zeros(batch + (6, 6))
        S_1[..., :3, :3] = np.eye(3)
        S_1[..., 3:, 3:] = np.eye(3)
        S_1[..., :3, 3:] = skew(-(R_b_2 @ o_4_2[..., None])[..., 0])
        S_2 = np.zeros(batch + (6, 6))
        S_2[..., :3, :3] = R_b_2
        S_2[..., 3:, 3:] = R_b_2
        return {"J_1": J_1, "J_2": J_2, "S_1": S_1, "S_2": S_2}

    def _segment_end(self, segment: ModalSegment, q_mm: Array, rates: bool):
        key = ("segment-end", id(segment))
        quad = self._plans.get(key)
        if quad is None:
            limits = np.array([segment.length_mm])
            quad = SegmentQuadrature.build(segment, limits, self.quadrature_order)
            self._plans[key] = quad
        th = segment.coefficients(q_mm) @ quad.psi_nodes.T
        x, z = np.cos(th) @ quad.weights, np.sin(th) @ quad.weights
        dth = segment.coefficient_rates(q_mm) @ quad.psi_nodes.T
        dx, dz = (-np.sin(th) * dth) @ quad.weights, (np.cos(th) * dth) @ quad.weights
        return (x[..., 0], dx[..., 0]), (z[..., 0], dz[..., 0])

    def tip_twist(self, q: Array, q_dot: Array, delta_L: Array | float = 0.0) -> Array:
        """Tip twist [v (mm/s); w (rad/s)] of frame {4} in {B} for joint rates q_dot.

        xi = [S_1 J_1 | S_2 J_2] [q_p_dot, q_r_dot, q_d_dot, 0]^T (paper eq. IKfinal), with
        delta_L held constant.
        """
        q_dot = check_joints(q_dot, "q_dot")
        jac = self.segment_jacobians(q, delta_L)
        rates_1 = np.stack([q_dot[..., 1], q_dot[..., 0]], -1)[..., None]
        rates_2 = np.stack([q_dot[..., 2], np.zeros_like(q_dot[..., 2])], -1)[..., None]
        xi = jac["S_1"] @ (jac["J_1"] @ rates_1) + jac["S_2"] @ (jac["J_2"] @ rates_2)
        return xi[..., 0]


def default_catheter(delta_2_rad: float = 0.0, **overrides) -> Catheter:
    """The default model of DESIGN.md section 3 (L1 = 13 mm, L2 = 16 mm, quadratic bases)."""
    proximal = ModalSegment(
        length_mm=13.0,
        A=np.array([[np.pi / 2, 0.0, 0.0], [0.0, -2.2, 0.15], [0.0, 0.3, 0.0]]),
        psi=PowerBasis(3),
        eta=PowerBasis(3),
    )
    distal = ModalSegment(
        length_mm=16.0,
        A=np.array([[np.pi / 2, 0.0, 0.0], [0.0, -2.6, 0.20], [0.0, 0.4, 0.0]]),
        psi=PowerBasis(3),
        eta=PowerBasis(3),
    )
    return Catheter(proximal=proximal, distal=distal, delta_2_rad=delta_2_rad, **overrides)
