"""Two-segment steerable catheter: direct and instantaneous kinematics (docs/design.md section 3).

``delta_L`` enters the model only through a rotation about ``z_b``::

    o_4_b(q, delta_L) = Rz(q_r + delta_L) c(q_p, q_d)

so :meth:`Catheter.shape_vectors` computes, once per configuration, the delta_L-independent
vectors ``c`` of the tip and of every marker and ``u`` of the tip velocity; every estimator
then only rotates fixed vectors about one axis.

Joint vectors are ``q = (q_r [rad], q_p [mm], q_d [mm])`` with shape (..., 3); every
function is vectorised over the leading batch axes, and ``delta_L`` broadcasts against the
batch shape of ``q``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from models._shape_kernels import (
    points_and_tip_velocity_at_powers,
    points_at_powers,
    points_from_basis,
)
from models.modal import Basis, ModalSegment, PowerBasis, SegmentQuadrature
from models.rotations import rot_y, rot_z, rotate_z, skew

Array = np.ndarray

# Gauss-Legendre nodes per piece of every integral. Measured against order 40 for the default
# model on an 81 x 81 grid of q_p, q_d in [-1, 1] mm, delta_2 = 0 and pi/2: the tip (one piece
# per segment, the worst case) is off by at most 3e-14 mm and the tip twist by 8e-14 mm/s at
# order 10 (round-off, as at orders 12 and 16), 8e-14 mm and 1e-12 mm/s at order 8,
# 2e-11 mm and 2e-10 mm/s at order 7. With twice the default bending (A's q terms doubled,
# up to 4.1 rad at L1) order 10 stays at 9e-14 mm where order 8 reaches 4e-10 mm. So order 10
# keeps a margin of over 1e7 to the 1e-6 mm reference tolerance, at 10/16 of the
# trigonometry of order 16.
DEFAULT_QUADRATURE_ORDER = 10

# Configurations per block in Catheter._shape times the nodes per configuration: blocks of
# 4096 configurations of the tip (20 nodes) keep each temporary near 640 kB, in cache.
_BLOCK_NODE_VALUES = 81_920

_NON_FINITE = "{} contains non-finite values (NaN or inf)"


def check_joints(q: Array, name: str = "q") -> Array:
    """Joint values as a float array of shape (..., 3), finite, or a ValueError naming the fault."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 3:
        raise ValueError(
            f"{name} must have shape (..., 3) = (q_r [rad], q_p [mm], q_d [mm]), got {q.shape}"
        )
    if not np.all(np.isfinite(q)):
        raise ValueError(_NON_FINITE.format(name))
    return q


def _check_finite(x: Array, name: str) -> Array:
    x = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(x)):
        raise ValueError(_NON_FINITE.format(name))
    return x


def _joint_floats(q: Array, name: str) -> list[float]:
    """One configuration, shape (3,), as Python floats, or a ValueError if not finite."""
    values = q.tolist()
    if not all(map(math.isfinite, values)):
        raise ValueError(_NON_FINITE.format(name))
    return values


def _batch_shape(q: Array, **shapes: tuple[int, ...]) -> tuple[int, ...]:
    """Broadcast the batch shape of q with the named batch shapes, or a ValueError naming them.

    Parameters
    ----------
    q : array, shape (..., 3)
        Checked joint values.
    **shapes : tuple of int
        Batch shapes of the other arguments, e.g. ``delta_L=delta_L.shape``.
    """
    batch, against = q.shape[:-1], "q"
    for name, shape in shapes.items():
        try:
            batch = np.broadcast_shapes(batch, shape)
        except ValueError:
            raise ValueError(
                f"{name} has batch shape {shape}, which does not broadcast against the batch"
                f" shape {batch} of {against}"
            ) from None
        against += f" and {name}"
    return batch


def _joint_basis_rows(
    basis: Basis, q_mm: float, derivatives: bool = True
) -> tuple[list[float], list[float] | None]:
    """eta(q) and d eta / dq (None without ``derivatives``) for one joint value as Python
    floats (single-configuration path)."""
    if type(basis) is PowerBasis:
        # The same products in the same order as PowerBasis.values: both paths agree exactly.
        values = [1.0]
        for _ in range(basis.size - 1):
            values.append(values[-1] * q_mm)
        if not derivatives:
            return values, None
        return values, [0.0] + [k * values[k - 1] for k in range(1, basis.size)]
    x = np.array(q_mm)
    return basis.values(x).tolist(), basis.derivatives(x).tolist() if derivatives else None


def _block_diag(a: Array, b: Array) -> Array:
    """The block-diagonal matrix [[a, 0], [0, b]]."""
    out = np.zeros((a.shape[0] + b.shape[0], a.shape[1] + b.shape[1]), dtype=np.result_type(a, b))
    out[: a.shape[0], : a.shape[1]] = a
    out[a.shape[0] :, a.shape[1] :] = b
    return out


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


@dataclass(frozen=True, eq=False)
class _Plan:
    """Quadrature of both segments for a fixed tuple of arclengths, as a few matrices.

    With the stacked joint basis ``eta = [eta_1(q_p), eta_2(q_d)]`` the tangent angles at the
    nodes of both segments are ``eta @ G_nodes``. ``G_nodes`` is block diagonal, so the stacked
    derivatives ``[eta_1'(q_p), eta_2'(q_d)] @ G_nodes`` are dtheta_1/dq_p on segment 1's
    nodes and dtheta_2/dq_d on segment 2's. ``cos(theta) @ weights`` and
    ``sin(theta) @ weights`` are then the in-plane coordinates (x, z) of p_1 and p_2 at every
    integral limit (columns: segment 1's limits, then segment 2's).

    Arclength k uses p_1 at column ``column_1[k]`` (p_1(L1) for a distal point) and p_2 at
    column ``column_2[k]`` (the zero limit for a proximal point), so that the single formula
    ``c = p_1 + Ry(pi/2 - theta_1(L1)) Rz(delta_2) p_2`` serves every point without masks.
    """

    G_nodes: Array  # (n_eta_1 + n_eta_2, n_nodes)
    G_ends: Array  # (n_eta_1 + n_eta_2, 2): theta_1(L1), theta_2(L2)
    weights: Array  # (n_nodes, n_columns), mm
    column_1: Array  # (n_points,) int
    column_2: Array  # (n_points,) int
    end_1: int  # column of p_1(L1)
    end_2: int  # column of p_2(L2)

    # The single-configuration path's matrices are built on first use: most plans (backbone
    # calls) never need them, and the expanded weights are four times the size of weights.
    @cached_property
    def G_single(self) -> Array:
        """theta at the nodes and at L1, shape (n_eta_1 + n_eta_2, n_nodes + 1)."""
        G = np.concatenate([self.G_nodes, self.G_ends[:, :1]], axis=1)
        G.setflags(write=False)
        return G

    @cached_property
    def weights_single(self) -> Array:
        """Weights for the (cos, sin) float pairs of exp(i theta) at the G_single nodes.

        One more column copies the L1 node, and kron(., I_2) acts on interleaved pairs, so the
        product returns the (x, z) pairs of every limit and then (cos, sin)(theta_1(L1)).
        Shape (2 (n_nodes + 1), 2 (n_columns + 1)).
        """
        W = np.kron(_block_diag(self.weights, np.ones((1, 1))), np.eye(2))
        W.setflags(write=False)
        return W

    @cached_property
    def tip_first_columns(self) -> tuple[Array, Array]:
        """column_1 and column_2 with the last point (the tip) first."""
        order = np.roll(np.arange(self.column_1.size), 1)
        return self.column_1[order].copy(), self.column_2[order].copy()

    @cached_property
    def point_columns_array(self) -> tuple[Array, Array]:
        """column_1 and column_2 as writable copies (the compiled kernels' argument type)."""
        return self.column_1.copy(), self.column_2.copy()

    @cached_property
    def point_columns(self) -> tuple[tuple[int, int], ...]:
        """(column_1[k], column_2[k]) for every arclength, as Python ints."""
        return tuple(zip(self.column_1.tolist(), self.column_2.tolist(), strict=True))


@dataclass(frozen=True, eq=False)
class Catheter:
    """Two-segment catheter: proximal segment (driven by q_p), distal segment (by q_d).

    Equality and hashing are by identity (``eq=False``): the segments hold arrays, and the
    field-wise comparison of a frozen dataclass would raise on them.

    Parameters
    ----------
    proximal, distal : ModalSegment
        Segment models.
    delta_2_rad : float
        Fixed angle of the distal bending plane about z_2.
    marker_arclengths_mm : tuple of float
        Arclengths of the backbone markers that Body Positions uses together with the tip,
        mm from the base of the proximal segment, each in (0, L1 + L2). The tip is always
        measured on its own, so a marker at the tip would count the same point twice.
        Default: one marker at frame {2} (s = L1).
    quadrature_order : int
        Gauss-Legendre nodes per piece of every integral.
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
            markers = (self.proximal.length_mm,)
        for s in markers:
            if not (0.0 < s < self.length_mm):
                raise ValueError(
                    f"marker arclength {s} mm is outside the catheter body (0, {self.length_mm})"
                    " mm (the tip is always measured on its own)"
                )
        object.__setattr__(self, "marker_arclengths_mm", markers)
        # The tip is always the last point of the marker plan.
        self._plan(markers + (self.length_mm,))

    @property
    def length_mm(self) -> float:
        """Total length L1 + L2 of the bending section, mm."""
        return self.proximal.length_mm + self.distal.length_mm

    # ------------------------------------------------------------------ plans and shapes
    def _plan(self, arclengths: tuple[float, ...]) -> _Plan:
        """The (cached) quadrature plan for points at these arclengths, mm, in [0, L1 + L2]."""
        plan = self._plans.get(arclengths)
        if plan is not None:
            return plan
        s = np.asarray(arclengths, dtype=float)
        L1, L2 = self.proximal.length_mm, self.distal.length_mm
        distal = s > L1
        s_1 = np.where(distal, L1, s)
        s_2 = np.where(distal, s - L1, 0.0)
        # (L1 + L2) - L1 need not equal L2 in floating point: snap, so that the tip shares the
        # nodes of p_2(L2) instead of adding a piece one ulp long.
        s_2[np.abs(s_2 - L2) <= 4 * np.finfo(float).eps * self.length_mm] = L2
        limits_1 = np.unique(np.append(s_1, L1))
        limits_2 = np.unique(np.concatenate([s_2, [0.0, L2]]))
        quad_1 = SegmentQuadrature.build(self.proximal, limits_1, self.quadrature_order)
        quad_2 = SegmentQuadrature.build(self.distal, limits_2, self.quadrature_order)
        A_1, A_2 = self.proximal.A, self.distal.A
        # theta(s_n, q) = psi(s_n)^T A eta(q) = eta(q)^T (A^T psi(s_n)).
        G_nodes = _block_diag(A_1.T @ quad_1.psi_nodes.T, A_2.T @ quad_2.psi_nodes.T)
        G_ends = _block_diag(A_1.T @ quad_1.psi_end[:, None], A_2.T @ quad_2.psi_end[:, None])
        weights = _block_diag(quad_1.weights, quad_2.weights)
        column_1 = np.searchsorted(limits_1, s_1)
        column_2 = limits_1.size + np.searchsorted(limits_2, s_2)
        plan = _Plan(
            G_nodes=G_nodes,
            G_ends=G_ends,
            weights=weights,
            column_1=column_1,
            column_2=column_2,
            end_1=limits_1.size - 1,
            end_2=weights.shape[1] - 1,
        )
        for array in (G_nodes, G_ends, weights, column_1, column_2):
            array.setflags(write=False)
        if len(self._plans) < 64:
            self._plans[arclengths] = plan
        return plan

    @cached_property
    def _marker_plan(self) -> _Plan:
        """The plan of the markers and the tip (the tip last), looked up once per catheter."""
        return self._plan(self.marker_arclengths_mm + (self.length_mm,))

    def _check_arclengths(self, arclength_mm: Array) -> Array:
        s = _check_finite(arclength_mm, "arclength_mm")
        if np.any(s < 0.0) or np.any(s > self.length_mm):
            raise ValueError(
                f"arclength outside the catheter: values must lie in [0, {self.length_mm}] mm,"
                f" got min {s.min():.6g}, max {s.max():.6g}"
            )
        return s

    def _shape(self, plan: _Plan, q_p: Array, q_d: Array, rates: bool) -> dict[str, Array]:
        """Shape vectors c(s) at delta_1 = 0 for the plan's arclengths, batch shape of q_p.

        Returns a dict with ``c`` (..., n, 3); the segment ends ``c_end_1`` = p_1(L1) and
        ``p_2`` = p_2(L2) (..., 3), each in its own segment's bending plane; the tip angles
        ``theta_1`` = theta_1(L1), ``theta_2`` = theta_2(L2) (...). With ``rates`` also
        ``dc_dq_p``, ``dc_dq_d`` (..., n, 3), ``dc_end_1_dq_p``, ``dp_2_dq_d`` (..., 3) and
        ``dtheta_1``, ``dtheta_2`` (...). The segment ends serve :meth:`frames` and
        :meth:`segment_jacobians` without integrating again.
        """
        batch = q_p.shape
        q_p, q_d = q_p.ravel(), q_d.ravel()
        # Blocks of configurations keep the (block, n_nodes) temporaries in cache; one pass
        # over 100,000 configurations was measured twice as slow, mostly in memory traffic.
        step = max(1, _BLOCK_NODE_VALUES // plan.G_nodes.shape[1])
        if q_p.size <= step:
            out = self._shape_block(plan, q_p, q_d, rates)
        else:
            blocks = [
                self._shape_block(plan, q_p[i : i + step], q_d[i : i + step], rates)
                for i in range(0, q_p.size, step)
            ]
            out = {key: np.concatenate([b[key] for b in blocks]) for key in blocks[0]}
        return {key: value.reshape(batch + value.shape[1:]) for key, value in out.items()}

    def _shape_block(self, plan: _Plan, q_p: Array, q_d: Array, rates: bool) -> dict[str, Array]:
        """:meth:`_shape` for joint values of shape (n,): the same dict with batch shape (n,)."""
        eta = np.concatenate([self.proximal.eta.values(q_p), self.distal.eta.values(q_d)], -1)
        theta = eta @ plan.G_nodes
        theta_end = eta @ plan.G_ends
        cos, sin = np.cos(theta), np.sin(theta)
        x, z = cos @ plan.weights, sin @ plan.weights
        # Trailing axis of length 1 so that the end rotation broadcasts over the points.
        c1, s1 = np.cos(theta_end[..., :1]), np.sin(theta_end[..., :1])
        cd2, sd2 = np.cos(self.delta_2_rad), np.sin(self.delta_2_rad)
        x1, z1 = x[..., plan.column_1], z[..., plan.column_1]
        x2, z2 = x[..., plan.column_2], z[..., plan.column_2]
        # Paper eq. DKfull at delta_1 = 0: c = p_1 + Ry(pi/2 - theta_1(L1)) Rz(delta_2) p_2.
        c = np.stack(
            [x1 + s1 * cd2 * x2 + c1 * z2, sd2 * x2, z1 - c1 * cd2 * x2 + s1 * z2], axis=-1
        )
        zero = np.zeros_like(x[..., 0])
        out = {
            "c": c,
            "c_end_1": np.stack([x[..., plan.end_1], zero, z[..., plan.end_1]], -1),
            "p_2": np.stack([x[..., plan.end_2], zero, z[..., plan.end_2]], -1),
            "theta_1": theta_end[..., 0],
            "theta_2": theta_end[..., 1],
        }
        if not rates:
            return out
        eta_rate = np.concatenate(
            [self.proximal.eta.derivatives(q_p), self.distal.eta.derivatives(q_d)], -1
        )
        dtheta = eta_rate @ plan.G_nodes
        dtheta_end = eta_rate @ plan.G_ends
        # Columns of segment 1 are derivatives by q_p, those of segment 2 by q_d.
        dx, dz = (-sin * dtheta) @ plan.weights, (cos * dtheta) @ plan.weights
        dth1 = dtheta_end[..., :1]
        dx1, dz1 = dx[..., plan.column_1], dz[..., plan.column_1]
        dx2, dz2 = dx[..., plan.column_2], dz[..., plan.column_2]
        out.update(
            dc_dq_p=np.stack(
                [
                    dx1 + (c1 * cd2 * x2 - s1 * z2) * dth1,
                    np.zeros_like(dx1),
                    dz1 + (s1 * cd2 * x2 + c1 * z2) * dth1,
                ],
                axis=-1,
            ),
            dc_dq_d=np.stack(
                [s1 * cd2 * dx2 + c1 * dz2, sd2 * dx2, -c1 * cd2 * dx2 + s1 * dz2], axis=-1
            ),
            dc_end_1_dq_p=np.stack([dx[..., plan.end_1], zero, dz[..., plan.end_1]], -1),
            dp_2_dq_d=np.stack([dx[..., plan.end_2], zero, dz[..., plan.end_2]], -1),
            dtheta_1=dtheta_end[..., 0],
            dtheta_2=dtheta_end[..., 1],
        )
        return out

    def _single(
        self, plan: _Plan, joints: list[float], joint_rates: list[float] | None
    ) -> tuple[Array, Array | None]:
        """The plan's points c (in its order, (P, 3)) and the tip velocity u (None without
        ``joint_rates``) for one configuration.

        The tracker calls it every frame, where the dozens of numpy calls of the batched path
        on arrays of a few elements cost far more than the arithmetic: the points are
        compiled (:func:`models._shape_kernels.points_from_basis`); the velocity's
        derivatives come from one product, ``exp(i theta) @ weights = x + i z``, assembled
        from Python floats.
        """
        if joint_rates is not None and self._power_sizes is not None:
            j1, j2 = plan.point_columns[-1]
            cd2, sd2 = self._delta_2_cos_sin
            return points_and_tip_velocity_at_powers(
                np.array(joints), np.array(joint_rates), *self._power_sizes, plan.G_single,
                plan.weights_single, plan.column_1, plan.column_2, j1, j2, cd2, sd2,
            )  # fmt: skip
        _, q_p, q_d = joints
        rates = joint_rates is not None
        eta_p, deta_p = _joint_basis_rows(self.proximal.eta, q_p, rates)
        eta_d, deta_d = _joint_basis_rows(self.distal.eta, q_d, rates)
        cd2, sd2 = self._delta_2_cos_sin
        points = points_from_basis(
            np.array([eta_p + eta_d]), plan.G_single, plan.weights_single, plan.column_1,
            plan.column_2, cd2, sd2,
        )[0]  # fmt: skip
        if joint_rates is None:
            return points, None
        # Rows i theta and i dtheta/dq at every node (and at L1) become exp(i theta) and its
        # derivative i dtheta/dq exp(i theta).
        e = 1j * (np.array([eta_p + eta_d, deta_p + deta_d]) @ plan.G_single)
        np.exp(e[0], out=e[0])
        e[1] *= e[0]
        # The complex values viewed as (cos, sin) float pairs keep the product real: a
        # complex BLAS product (zgemm) was measured to slow every later np.exp ten times.
        integrals = (e.view(float) @ plan.weights_single).view(complex).tolist()
        p = integrals[0]  # x + i z of p_1 and p_2 at every limit; last: exp(i theta_1(L1))
        c1, s1 = p[-1].real, p[-1].imag
        # The tip velocity.
        dp = integrals[1]  # d/dq_p on segment 1's columns, d/dq_d on segment 2's
        dc1, ds1 = dp[-1].real, dp[-1].imag  # d(cos, sin)(theta_1(L1)) / dq_p
        j1, j2 = plan.point_columns[-1]
        x2, z2 = p[j2].real, p[j2].imag
        dx1, dz1, dx2, dz2 = dp[j1].real, dp[j1].imag, dp[j2].real, dp[j2].imag
        dc_p = (dx1 + ds1 * cd2 * x2 + dc1 * z2, 0.0, dz1 - dc1 * cd2 * x2 + ds1 * z2)
        dc_d = (s1 * cd2 * dx2 + c1 * dz2, sd2 * dx2, -c1 * cd2 * dx2 + s1 * dz2)
        r_dot, p_dot, d_dot = joint_rates
        c_x, c_y, _ = points[-1]
        # d/dt [Rz(delta_1) c] = Rz(delta_1) [q_r_dot z x c + dc/dq_p q_p_dot + dc/dq_d q_d_dot]
        u = np.array(
            [
                -r_dot * c_y + dc_p[0] * p_dot + dc_d[0] * d_dot,
                r_dot * c_x + dc_p[1] * p_dot + dc_d[1] * d_dot,
                dc_p[2] * p_dot + dc_d[2] * d_dot,
            ]
        )
        return points, u

    def points_of(self, q: Array) -> Array:
        """:meth:`points` of configurations q (k, 3) at once: the same numbers as one by one
        (the single-configuration path, in one call), (k, 1 + n_markers, 3), mm."""
        q = check_joints(q)
        if q.ndim != 2:
            raise ValueError(f"q must have shape (k, 3), got {q.shape}")
        if self._power_sizes is not None:
            return self._points_at_powers(np.array(q[:, 1]), np.array(q[:, 2]))
        return self._points_single(q.tolist())

    @cached_property
    def _power_sizes(self) -> tuple[int, int] | None:
        """The sizes of the joint bases when both are power bases (the default model's: their
        rows are then made in the compiled kernel), else None."""
        bases = (self.proximal.eta, self.distal.eta)
        if all(type(basis) is PowerBasis for basis in bases):
            return bases[0].size, bases[1].size
        return None

    def _points_at_powers(self, q_p: Array, q_d: Array) -> Array:
        """The points of configurations (q_p, q_d) (writable float arrays (k,)) of a model
        with power bases, in one compiled call (the same numbers as the rows made in Python,
        :func:`models._shape_kernels.points_at_powers`), (k, P, 3)."""
        plan = self._marker_plan
        column_1, column_2 = plan.tip_first_columns
        cd2, sd2 = self._delta_2_cos_sin
        return points_at_powers(
            q_p, q_d, *self._power_sizes, plan.G_single, plan.weights_single, column_1,
            column_2, cd2, sd2,
        )  # fmt: skip

    def _points_single(self, joints: list[list[float]]) -> Array:
        """The tip's and the markers' points (tip first) of configurations given as float
        triples, (k, P, 3)."""
        if self._power_sizes is not None:
            return self._points_at_powers(
                np.array([q[1] for q in joints]), np.array([q[2] for q in joints])
            )
        rows = [
            _joint_basis_rows(self.proximal.eta, q_p, False)[0]
            + _joint_basis_rows(self.distal.eta, q_d, False)[0]
            for _, q_p, q_d in joints
        ]
        return self._points_from_rows(np.array(rows))

    def _points_from_rows(self, eta: Array) -> Array:
        """The tip's and the markers' points (tip first) from the joint bases' rows (k, m),
        compiled (:func:`models._shape_kernels.points_from_basis`), (k, P, 3)."""
        plan = self._marker_plan
        column_1, column_2 = plan.tip_first_columns
        cd2, sd2 = self._delta_2_cos_sin
        return points_from_basis(
            eta, plan.G_single, plan.weights_single, column_1, column_2, cd2, sd2
        )

    @cached_property
    def _delta_2_cos_sin(self) -> tuple[float, float]:
        return math.cos(self.delta_2_rad), math.sin(self.delta_2_rad)

    # ------------------------------------------------------------------ public API
    def shape_vectors(self, q: Array, q_dot: Array | None = None) -> ShapeVectors:
        """The delta_L-independent vectors of the tip, every marker and the tip velocity.

        Parameters
        ----------
        q : array, shape (..., 3)
            Joint values (q_r [rad], q_p [mm], q_d [mm]).
        q_dot : array, shape (..., 3), optional
            Joint rates (rad/s, mm/s, mm/s), broadcasting against q; when given,
            ``u_tip_mm_s`` is filled.

        Returns
        -------
        ShapeVectors
            With batch shape (...) of q (of q and q_dot broadcast for ``u_tip_mm_s``).
        """
        q = np.asarray(q, dtype=float)
        if q_dot is not None:
            q_dot = np.asarray(q_dot, dtype=float)
        plan = self._marker_plan
        if q.shape == (3,) and (q_dot is None or q_dot.shape == (3,)):
            joints = _joint_floats(q, "q")
            rates = None if q_dot is None else _joint_floats(q_dot, "q_dot")
            c, u = self._single(plan, joints, rates)
            return ShapeVectors(q_r_rad=q[0], c_tip_mm=c[-1], c_markers_mm=c[:-1], u_tip_mm_s=u)
        q = check_joints(q)
        if q_dot is not None:
            q_dot = check_joints(q_dot, "q_dot")
            _batch_shape(q, q_dot=q_dot.shape[:-1])
        shape = self._shape(plan, q[..., 1], q[..., 2], rates=q_dot is not None)
        c = shape["c"]
        u = None
        if q_dot is not None:
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

    def points(self, q: Array) -> Array:
        """The delta_L-independent vectors c of the tip, then of every marker, mm.

        The same numbers as :meth:`shape_vectors` (``c_tip_mm`` first, then
        ``c_markers_mm``) in one array of shape (..., 1 + n_markers, 3), with fewer calls for
        one configuration (the filters' case, every frame).
        """
        q = np.asarray(q, dtype=float)
        if q.shape == (3,):
            return self._points_single([_joint_floats(q, "q")])[0]
        shape = self.shape_vectors(q)
        return np.concatenate([shape.c_tip_mm[..., None, :], shape.c_markers_mm], axis=-2)

    def tip(self, q: Array, delta_L: Array | float = 0.0) -> Array:
        """Tip position o_4_b, mm, shape (..., 3) with q's batch shape broadcast with delta_L's."""
        q = check_joints(q)
        delta_L = _check_finite(delta_L, "delta_L")
        _batch_shape(q, delta_L=delta_L.shape)
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
        _batch_shape(q, delta_L=delta_L.shape)
        s = self._check_arclengths(arclength_mm)
        scalar = s.ndim == 0
        s = np.atleast_1d(s)
        if s.ndim != 1:
            raise ValueError(f"arclength_mm must be a scalar or 1-D, got shape {s.shape}")
        shape = self._shape(self._plan(tuple(s.tolist())), q[..., 1], q[..., 2], rates=False)
        points = rotate_z(shape["c"], (q[..., 0] + delta_L)[..., None])
        return points[..., 0, :] if scalar else points

    def outline(self, q: Array, delta_L: float, arclength_mm: tuple[float, ...]) -> Array:
        """:meth:`backbone` of one configuration at arclengths given as a tuple, (n, 3) mm in
        {B}: the same points to rounding (not bit for bit), in a compiled call for a model
        with power bases (the live loop's region of interest, twice a frame: a third of
        :meth:`backbone`'s time); through :meth:`backbone` otherwise."""
        q = check_joints(q)
        if q.shape != (3,) or self._power_sizes is None or not math.isfinite(delta_L):
            return self.backbone(q, delta_L, np.array(arclength_mm, float))
        if arclength_mm not in self._plans:
            self._check_arclengths(np.array(arclength_mm, float))
        plan = self._plan(arclength_mm)
        c = points_at_powers(
            q[1:2].copy(), q[2:3].copy(), *self._power_sizes, plan.G_single,
            plan.weights_single, *plan.point_columns_array, *self._delta_2_cos_sin,
        )[0]  # fmt: skip
        return rotate_z(c, float(q[0]) + float(delta_L))

    def frames(self, q: Array, delta_L: Array | float = 0.0) -> Frames:
        """Frames {2} and {4} in {B} (paper eqs. dk1, DKfull)."""
        q = check_joints(q)
        delta_L = _check_finite(delta_L, "delta_L")
        _batch_shape(q, delta_L=delta_L.shape)
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
        Twists are [v (mm/s); w (rad/s)]; the batch shape (...) is q's broadcast with delta_L's.
        """
        q = check_joints(q)
        delta_L = _check_finite(delta_L, "delta_L")
        batch = _batch_shape(q, delta_L=delta_L.shape)
        delta_1 = q[..., 0] + delta_L
        shape = self._shape(self._plan((self.length_mm,)), q[..., 1], q[..., 2], rates=True)
        R_b_2 = rot_z(delta_1) @ rot_y(np.pi / 2 - shape["theta_1"])
        Rzd2 = rot_z(self.delta_2_rad)
        e_y, e_z = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
        # Segment 1 in {B}: d(o_2_b)/dq_p and the rotation about y_1 by -dtheta_1/dq_p.
        J_1 = np.zeros(batch + (6, 2))
        J_1[..., :3, 0] = rotate_z(shape["dc_end_1_dq_p"], delta_1)
        J_1[..., 3:, 0] = rotate_z(e_y, delta_1) * -shape["dtheta_1"][..., None]
        J_1[..., :3, 1] = np.cross(e_z, rotate_z(shape["c_end_1"], delta_1))
        J_1[..., 3:, 1] = e_z
        # Segment 2 in {2}: p_2 at delta_2, tip angle rate, and rotation about z_2.
        o_4_2 = shape["p_2"] @ Rzd2.T
        J_2 = np.zeros(batch + (6, 2))
        J_2[..., :3, 0] = shape["dp_2_dq_d"] @ Rzd2.T
        J_2[..., 3:, 0] = (Rzd2 @ e_y) * -shape["dtheta_2"][..., None]
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

    def tip_twist(self, q: Array, q_dot: Array, delta_L: Array | float = 0.0) -> Array:
        """Tip twist [v (mm/s); w (rad/s)] of frame {4} in {B} for joint rates q_dot.

        xi = [S_1 J_1 | S_2 J_2] [q_p_dot, q_r_dot, q_d_dot, 0]^T (paper eq. IKfinal), with
        delta_L held constant. The batch shapes of q, delta_L and q_dot broadcast.
        """
        q = check_joints(q)
        q_dot = check_joints(q_dot, "q_dot")
        delta_L = _check_finite(delta_L, "delta_L")
        _batch_shape(q, delta_L=delta_L.shape, q_dot=q_dot.shape[:-1])
        jac = self.segment_jacobians(q, delta_L)
        rates_1 = np.stack([q_dot[..., 1], q_dot[..., 0]], -1)[..., None]
        rates_2 = np.stack([q_dot[..., 2], np.zeros_like(q_dot[..., 2])], -1)[..., None]
        xi = jac["S_1"] @ (jac["J_1"] @ rates_1) + jac["S_2"] @ (jac["J_2"] @ rates_2)
        return xi[..., 0]


def default_catheter(delta_2_rad: float = 0.0, **overrides) -> Catheter:
    """The default model of docs/design.md section 3 (L1 = 13 mm, L2 = 16 mm, quadratic bases)."""
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
