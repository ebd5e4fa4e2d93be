"""The joint-equivalent deviation of the shape: the model error both filters estimate.

A contact or a miscalibrated model changes the catheter's shape as a deviation of its
bending joints would (the paper made its deflections that way), so the filters carry that
deviation ``dq = (dq_p, dq_d)`` (mm) in their state (docs/design.md section 5). This module
holds its measurement side, the shape's second-order expansion ``c(q + dq) = c + J dq + K
[dq_p^2, dq_p dq_d, dq_d^2]`` (:class:`ShapeExpansion`), and its process side, a prior that
grows with the bending (:func:`deviation_prior`) and a decorrelation with the joint travel
and time (:func:`deviation_decay`).
"""

from __future__ import annotations

import contextlib

import numpy as np

from models import _shape_kernels as shape_kernels
from models.catheter import Catheter
from tracker.estimators import measurement_kernels

Array = np.ndarray

# Step of the central differences of the shape in the joints, mm.
DEVIATION_STEP_MM = 1e-3


def _difference_weights(h: float) -> Array:
    """The central differences as weights of the six shape evaluations (at q, q +- h e_p,
    q +- h e_d, q + h (e_p + e_d)), one column per term of ``[J K]``: (6, 5)."""
    a, b = 1 / (2 * h), 1 / h**2
    return np.array(
        [
            # J_p, J_d, K_pp (half the second difference), K_pd, K_dd
            [0.0, 0.0, -b, b, -b],
            [a, 0.0, 0.5 * b, -b, 0.0],
            [-a, 0.0, 0.5 * b, 0.0, 0.0],
            [0.0, a, 0.0, -b, 0.5 * b],
            [0.0, -a, 0.0, 0.0, 0.5 * b],
            [0.0, 0.0, 0.0, b, 0.0],
        ]
    )


_STEPS = DEVIATION_STEP_MM * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1]], float)
_WEIGHTS = _difference_weights(DEVIATION_STEP_MM)


def _expansion(catheter: Catheter, q: Array) -> tuple[Array, Array]:
    """c (P, 3) and ``[J K]`` (P, 3, 5) at q by central differences (six shape evaluations,
    through the single-configuration path: fewer numpy calls than the batched one)."""
    joints = np.repeat(q[None], 6, axis=0)
    joints[:, 1:] += _STEPS
    points = catheter.points_of(joints)
    JK = (points.reshape(6, -1).T @ _WEIGHTS).reshape(points.shape[1:] + (5,))
    return points[0], JK


class ShapeExpansion:
    """Model vectors of the tip and the markers and their second-order expansion in a joint
    deviation: ``c(q + dq) = c + J dq + K [dq_p^2, dq_p dq_d, dq_d^2]``.

    A deviation of 0.2 mm already turns the tip by about 20 degrees: the linear term alone
    errs by 0.5 mm there, with the quadratic term by 0.05 mm (default model). ``c`` is the
    model's own (the single-configuration path of
    :meth:`~models.catheter.Catheter.shape_vectors`, once per distinct configuration, so that
    a noise-free frame is fitted exactly); J and K are computed by central differences (step
    ``DEVIATION_STEP_MM``, six shape evaluations) at the nodes of a grid of ``GRID_MM`` in
    (q_p, q_d), kept, and carried to q (J by the expansion itself; K changes by about 1 % over
    a grid step). A deterministic function of q: the live filter and the batched one get the
    same numbers.

    Parameters
    ----------
    catheter : Catheter
    """

    GRID_MM = 0.02
    MAX_NODES = 50_000

    def __init__(self, catheter: Catheter) -> None:
        self.catheter = catheter
        # The model's points are compiled: loaded (or compiled) now, not at the first frame.
        shape_kernels.warm_up()
        measurement_kernels.warm_up()
        self._nodes: dict[tuple[int, int], tuple[Array, Array]] = {}
        self._prepared: tuple | None = None  # (q, c, [J K]) of the last prepare, once

    @property
    def held(self) -> tuple | None:
        """What the last :meth:`prepare` computed, until :meth:`expanded` takes it (None:
        nothing); set it back to put it in place again."""
        return self._prepared

    @held.setter
    def held(self, value: tuple | None) -> None:
        self._prepared = value

    def _node(self, key: tuple[int, int]) -> tuple[Array, Array]:
        """c and ``[J K]`` (P, 3, 5) at the grid node ``key``."""
        found = self._nodes.get(key)
        if found is None:
            if len(self._nodes) >= self.MAX_NODES:
                self._nodes.clear()
            q = np.array([0.0, key[0] * self.GRID_MM, key[1] * self.GRID_MM])
            found = self._nodes[key] = _expansion(self.catheter, q)
        return found

    def prepare(self, q: Array) -> None:
        """Compute the expansion at joint values q (3,) now, its node too if it is new: the
        live loop does it while it waits for a frame, with the joints moved on to the
        frame's time (the joints of a moving catheter reach a new node at most frames, six
        shape evaluations that would otherwise be part of the frame's latency), and again
        with the frame's joints while the worker segments its other view. The next
        :meth:`expanded` of exactly these q (one configuration) takes it instead of
        computing it again (the same numbers)."""
        q = np.array(q, dtype=float)
        held, self._prepared = self._prepared, None
        if q.shape == (3,) and np.isfinite(q).all():
            if held is not None and held[0] == q.tolist():
                self._prepared = held  # a catheter held still: primed at these joints already
                return
            with contextlib.suppress(ValueError):  # out of the model's range: step says so
                self._prepared = (q.tolist(), *self.expanded(q[None]))

    def node(self, key: tuple[int, int]) -> tuple[Array, Array, Array]:
        """c, J and K at the grid node ``key`` (its indices in steps of ``GRID_MM``)."""
        c, JK = self._node(key)
        return c, JK[..., :2], JK[..., 2:]

    def points(self, q: Array) -> Array:
        """Model vectors of the tip and the markers at one q (3,): (P, 3), mm."""
        return self.catheter.points(q)

    def __call__(self, q: Array) -> tuple[Array, Array, Array]:
        """c (B, P, 3), J (B, P, 3, 2) and K (B, P, 3, 3) at joint values q (B, 3)."""
        c, JK = self.expanded(q)
        return c, JK[..., :2], JK[..., 2:]

    def expanded(self, q: Array) -> tuple[Array, Array]:
        """c (B, P, 3) and ``[J K]`` (B, P, 3, 5) at joint values q (B, 3).

        J is carried from the node to q by the expansion itself, ``J + K dquad/ddq``
        (:func:`deviation_jacobian`; :func:`~tracker.estimators.measurement_kernels.
        carry_expansion`). Each configuration of a batch gets the numbers it gets alone.
        """
        q = np.asarray(q, dtype=float)
        if q.shape[0] == 1:
            prepared, self._prepared = self._prepared, None  # taken once at most
            if prepared is not None and prepared[0] == q[0].tolist():
                return prepared[1], prepared[2]
            # One configuration in Python floats (round() rounds half to even, as np.rint).
            q_p, q_d = float(q[0, 1]), float(q[0, 2])
            key = (round(q_p / self.GRID_MM), round(q_d / self.GRID_MM))
            JK = self._node(key)[1]
            p, d = q_p - key[0] * self.GRID_MM, q_d - key[1] * self.GRID_MM
            return self.points(q[0])[None], measurement_kernels.carry_expansion(JK, p, d)
        # Every configuration as the one above: the same numbers, in two compiled calls.
        keys = np.rint(q[:, 1:] / self.GRID_MM).astype(np.int64)
        delta = q[:, 1:] - keys * self.GRID_MM
        distinct, index = np.unique(keys, axis=0, return_inverse=True)
        nodes = np.array([self._node((int(a), int(b)))[1] for a, b in distinct])
        JK = measurement_kernels.carry_expansions(
            nodes, index.ravel().astype(np.intp), delta[:, 0].copy(), delta[:, 1].copy()
        )
        return self.catheter.points_of(q), JK


# The factors of the quadratic terms of expansion_basis.
_FIRST, _SECOND = np.array([0, 0, 1]), np.array([0, 1, 1])


def expansion_basis(dq: Array) -> Array:
    """``[dq_p, dq_d, dq_p^2, dq_p dq_d, dq_d^2]`` of deviations (..., 2): (..., 5), the
    basis of ``[J K]``."""
    return np.concatenate((dq, dq.take(_FIRST, -1) * dq.take(_SECOND, -1)), -1)


def quadratic_terms(dq: Array) -> Array:
    """``[dq_p^2, dq_p dq_d, dq_d^2]`` of deviations (..., 2): (..., 3)."""
    return expansion_basis(dq)[..., 2:]


def quadratic_moments(K: Array, Sigma: Array) -> tuple[Array, Array]:
    """Mean (..., 3) and covariance (..., 3, 3) of ``K quadratic_terms(dq)`` for a zero-mean
    Gaussian dq of covariance Sigma (..., 2, 2), K (..., 3, 3) (Isserlis' theorem)."""
    if Sigma.shape == (2, 2):
        # One covariance (the grid filter's, every frame): the same numbers from floats.
        a, b, d = float(Sigma[0, 0]), float(Sigma[0, 1]), float(Sigma[1, 1])
        cov = np.array(
            [[2 * a * a, 2 * a * b, 2 * b * b], [2 * a * b, a * d + b * b, 2 * b * d],
             [2 * b * b, 2 * b * d, 2 * d * d]]
        )  # fmt: skip
        return K @ np.array([a, b, d]), K @ cov @ np.swapaxes(K, -1, -2)
    a, b, d = Sigma[..., 0, 0], Sigma[..., 0, 1], Sigma[..., 1, 1]
    moments = np.stack([a, b, d], -1)
    cov = np.zeros(Sigma.shape[:-2] + (3, 3))
    cov[..., 0, 0], cov[..., 2, 2] = 2 * a * a, 2 * d * d
    cov[..., 1, 1] = a * d + b * b
    cov[..., 0, 1] = cov[..., 1, 0] = 2 * a * b
    cov[..., 1, 2] = cov[..., 2, 1] = 2 * b * d
    cov[..., 0, 2] = cov[..., 2, 0] = 2 * b * b
    mean = (K @ moments[..., None])[..., 0]
    return mean, K @ cov @ np.swapaxes(K, -1, -2)


def deviation_jacobian(J: Array, K: Array, dq: Array) -> Array:
    """Jacobian of ``J dq + K quadratic_terms(dq)`` at dq: ``J + K dquad/ddq`` (..., 3, 2).

    ``dq`` (..., 2) broadcasts against the leading axes of J (..., 3, 2) and K (..., 3, 3),
    which give the shape of the result.
    """
    p, d = dq[..., 0, None], dq[..., 1, None]
    out = J.copy()
    out[..., 0] += 2 * p * K[..., 0] + d * K[..., 1]
    out[..., 1] += p * K[..., 1] + 2 * d * K[..., 2]
    return out


def deviation_prior(q: Array, joint_error_mm: float, gain_error: float) -> Array:
    """Prior variance of the joint-equivalent deviation of (q_p, q_d), mm^2, (B, 2)."""
    bend = gain_error * q[:, 1:]
    return joint_error_mm * joint_error_mm + bend * bend


def deviation_decay(
    moved_mm: Array, length_mm: float, dt_s: Array = 0.0, rate_per_s: float = 0.0
) -> Array:
    """Correlation of the deviation across a frame in which the joints moved ``moved_mm``.

    An Ornstein-Uhlenbeck process in the joint travel and in time: ``exp(-moved / length -
    rate dt)``, so that the deviation forgets over ``length_mm`` of joint motion (a new
    configuration, a new contact) and, slowly, while the joints hold (a contact made or
    released).
    """
    return np.exp(-np.abs(moved_mm) / length_mm - rate_per_s * dt_s)


__all__ = [
    "DEVIATION_STEP_MM",
    "ShapeExpansion",
    "deviation_decay",
    "deviation_jacobian",
    "deviation_prior",
    "expansion_basis",
    "quadratic_moments",
    "quadratic_terms",
]
