"""Registration of the catheter base {B} in the world frame {W} (docs/design.md section 2).

The robot steps through a short routine of joint configurations (:func:`registration_routine`)
while the rig images the catheter; :func:`register_base` finds the pose ``T_w_b`` whose model
points ``R_w_b p_b(q) + o_b_w``, projected into each view, best match the segmented points.
It starts from the closed-form rigid fit (Kabsch) of the model points to their two-view
reconstructions and refines by Gauss-Newton on the image residuals; the inverse Hessian
``s^2 (J^T J)^-1`` is the covariance of the pose.

The convention that fixes the rotation about z_b
------------------------------------------------
``delta_L`` enters the model only as a rotation about ``z_b`` (section 3), so a constant
torsional loss during the routine cannot be told apart from a rotation of {B} about its own
axis. The registration takes ``delta_L = 0`` during the routine: run it right after the
catheter is placed, with its body straight and untwisted, turning the base only through the
routine's ``q_r`` steps. Then ``x_b`` is, by definition, the direction in which the proximal
segment bends for ``q_r = 0`` and ``q_p > 0`` in that state, and every ``delta_L`` estimated
later is the torsional loss relative to it. (If the body was twisted by ``d`` during the
routine, the registered {B} is the true one turned by ``d`` about ``z_b``, and the tracked
``delta_L`` is the true one minus ``d``; the bending plane ``q_r + delta_L`` in {W} is right
either way.)

Pure maths: arrays in, a :class:`Registration` out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial.transform import Rotation

from models.catheter import Catheter, check_joints
from models.imaging import Rig
from models.pose import Pose
from models.rotations import skew

Array = np.ndarray

DEFAULT_BENDS_MM = ((0.5, 0.0), (0.8, 0.8))
"""(q_p, q_d) of the routine's bends in every plane: the proximal segment alone, then both."""
UNDETERMINED = (
    "the routine cannot determine the base pose (bend the catheter in at least one plane,"
    " with points seen in every view)"
)
MAX_CONDITION = 1e8
"""Largest condition number of the Gauss-Newton Hessian: beyond it the pose is not
determined (e.g. a routine that never bends the catheter leaves the rotation about z_b free)."""


def registration_routine(planes: int = 4, bends_mm=DEFAULT_BENDS_MM) -> Array:
    """The joint configurations of the routine: straight, then each bend in each plane.

    Parameters
    ----------
    planes : int
        Bending planes, ``q_r = 2 pi k / planes`` for k = 0..planes-1 (at least 1; 4 gives
        0, 90, 180 and 270 deg).
    bends_mm : sequence of (q_p, q_d)
        The bends made in every plane, mm.

    Returns
    -------
    q : array, shape (1 + planes * len(bends_mm), 3)
        (q_r [rad], q_p [mm], q_d [mm]) in the order to run them.
    """
    if int(planes) != planes or planes < 1:
        raise ValueError(f"the routine needs at least one bending plane, got {planes}")
    bends = np.asarray(bends_mm, dtype=float).reshape(-1, 2)
    if bends.size == 0 or not np.all(np.isfinite(bends)) or np.any(np.all(bends == 0.0, -1)):
        raise ValueError("the routine's bends must be finite (q_p, q_d) pairs, not all zero")
    rows = [np.zeros(3)]
    for k in range(int(planes)):
        q_r = 2.0 * np.pi * k / planes
        rows += [np.array([q_r, q_p, q_d]) for q_p, q_d in bends]
    return np.array(rows)


@dataclass(frozen=True, eq=False)
class Registration:
    """A registered base pose, how well it fits and how well it is determined.

    Attributes
    ----------
    pose : Pose
        ``T_w_b``.
    covariance : array, shape (6, 6)
        Covariance of ``(w, o)``: the rotation vector ``w`` (rad, world axes) of the error
        ``R_true = exp(w^) R_w_b`` and the origin (mm).
    residual_rms : tuple of float
        RMS image residual per view (px or mm, the rig's image unit).
    residual_3d_rms_mm : float
        RMS distance of the two-view reconstructions of the points seen in every view from
        the registered model points, mm.
    n_points : tuple of int
        Image points used per view.
    n_configurations : int
    """

    pose: Pose
    covariance: Array
    residual_rms: tuple[float, ...]
    residual_3d_rms_mm: float
    n_points: tuple[int, ...]
    n_configurations: int

    @property
    def std_origin_mm(self) -> Array:
        """Standard deviation of the origin along the world axes, mm, shape (3,)."""
        return np.sqrt(np.diag(self.covariance)[3:])

    @property
    def std_rotation_base_rad(self) -> Array:
        """Standard deviation of the rotation about ``x_b``, ``y_b``, ``z_b``, rad, shape (3,).

        The one about ``z_b`` adds directly to every tracked ``delta_L``.
        """
        R = self.pose.R_w_b
        return np.sqrt(np.diag(R.T @ self.covariance[:3, :3] @ R))


def fit_rigid(points_b: Array, points_w: Array) -> Pose:
    """The rigid motion ``T_w_b`` minimising ``sum |R p_b + o - p_w|^2`` (Kabsch), closed form.

    Parameters
    ----------
    points_b, points_w : array, shape (n, 3)
        Corresponding points, n >= 3 and not all on a line, mm.
    """
    a, b = np.asarray(points_b, float), np.asarray(points_w, float)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 3:
        raise ValueError(f"need n >= 3 corresponding 3-D points, got {a.shape} and {b.shape}")
    mean_a, mean_b = a.mean(axis=0), b.mean(axis=0)
    H = (a - mean_a).T @ (b - mean_b)
    U, s, Vt = np.linalg.svd(H)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise ValueError("the points lie on a line: their rotation about it is not determined")
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return Pose(R, mean_b - R @ mean_a)


def _check_observations(
    catheter: Catheter, rig: Rig, q: Array, uv: Sequence
) -> tuple[Array, list[Array]]:
    q = check_joints(q)
    if q.ndim != 2 or q.shape[0] == 0:
        raise ValueError(f"q must have shape (n, 3) with n >= 1, got {q.shape}")
    if len(uv) != rig.n_views:
        raise ValueError(f"need image points of each of the {rig.n_views} views, got {len(uv)}")
    n_points = 1 + len(catheter.marker_arclengths_mm)
    out = []
    for name, points in zip(rig.names, uv, strict=True):
        points = np.asarray(points, dtype=float)
        if points.shape != (q.shape[0], n_points, 2):
            raise ValueError(
                f"{name} points must have shape ({q.shape[0]}, {n_points}, 2): the tip and"
                f" {n_points - 1} marker(s) per configuration, got {points.shape}"
            )
        out.append(points)
    return q, out


def register_base(
    catheter: Catheter,
    rig: Rig,
    q: Array,
    uv: Sequence[Array],
    max_iterations: int = 50,
) -> Registration:
    """The base pose from points segmented at known joint values, with ``delta_L = 0``.

    Parameters
    ----------
    catheter : Catheter
    rig : Rig
        The calibrated views, any kind.
    q : array, shape (n, 3)
        Joint values of each observation (several observations of one configuration are
        welcome: they average the segmentation noise).
    uv : sequence of arrays, shape (n, 1 + n_markers, 2)
        Per view of the rig, in its order: the segmented tip and markers (rows as in
        :class:`tracker.types.Frame`), px or mm; NaN rows for points not found.
    max_iterations : int
        Gauss-Newton iterations at most.

    Returns
    -------
    Registration
        The pose, its covariance ``s^2 (J^T J)^-1`` with the noise variance ``s^2`` estimated
        from the residuals, and the residuals.

    Raises
    ------
    ValueError
        One line: inconsistent shapes, fewer than three points seen in every view, or a
        routine that cannot determine the pose.
    """
    q, uv = _check_observations(catheter, rig, q, uv)
    arclengths = np.array((catheter.length_mm, *catheter.marker_arclengths_mm))
    points_b = catheter.backbone(q, 0.0, arclengths)  # (n, P, 3), delta_L = 0
    seen = [np.all(np.isfinite(points), axis=-1) for points in uv]  # (n, P) per view
    everywhere = np.logical_and.reduce(seen)
    if np.count_nonzero(everywhere) < 3:
        raise ValueError(
            f"only {np.count_nonzero(everywhere)} point(s) were seen in every view; the"
            " registration needs at least 3 (and a routine that bends the catheter)"
        )
    points_w = rig.reconstruct(*(points[everywhere] for points in uv))
    try:
        pose = fit_rigid(points_b[everywhere], points_w)
    except ValueError:
        raise ValueError(f"{UNDETERMINED}: the points seen in every view lie on a line") from None
    used = [(points_b[mask], points[mask]) for mask, points in zip(seen, uv, strict=True)]
    R, o = pose.R_w_b, pose.o_b_w_mm
    for _ in range(max_iterations):
        residual, J = _residuals(rig, used, R, o)
        step = np.linalg.lstsq(J, -residual, rcond=None)[0]
        R = Rotation.from_rotvec(step[:3]).as_matrix() @ R
        o = o + step[3:]
        if np.linalg.norm(step[:3]) < 1e-12 and np.linalg.norm(step[3:]) < 1e-9:
            break
    residual, J = _residuals(rig, used, R, o)
    dof = residual.size - 6
    if dof <= 0:
        raise ValueError(f"{residual.size // 2} image points cannot determine a 6-dof pose")
    hessian = J.T @ J
    singular = np.linalg.svd(hessian, compute_uv=False)
    if singular[-1] <= singular[0] / MAX_CONDITION:
        raise ValueError(f"{UNDETERMINED}: its Gauss-Newton Hessian is singular")
    variance = float(residual @ residual) / dof
    covariance = variance * cho_solve(cho_factor(hessian), np.eye(6))
    pose = Pose(_orthonormal(R), o)
    per_view = []
    for (p_b, p_uv), view in zip(used, rig.views, strict=True):
        r = view.project(pose.world_from_base(p_b)) - p_uv
        per_view.append(float(np.sqrt(np.mean(np.sum(r**2, axis=-1)))))
    distance = np.linalg.norm(pose.world_from_base(points_b[everywhere]) - points_w, axis=-1)
    return Registration(
        pose=pose,
        covariance=0.5 * (covariance + covariance.T),
        residual_rms=tuple(per_view),
        residual_3d_rms_mm=float(np.sqrt(np.mean(distance**2))),
        n_points=tuple(int(mask.sum()) for mask in seen),
        n_configurations=int(np.unique(q, axis=0).shape[0]),
    )


def _residuals(rig: Rig, used, R: Array, o: Array) -> tuple[Array, Array]:
    """Stacked image residuals and their Jacobian by (w, o), ``R = exp(w^) R`` at w = 0."""
    residuals, jacobians = [], []
    for (p_b, p_uv), view in zip(used, rig.views, strict=True):
        rotated = p_b @ R.T
        p_w = rotated + o
        J_view = view.projection_jacobian(p_w)  # (m, 2, 3)
        # d(exp(w^) R p_b)/dw at w = 0 is -[R p_b]^.
        J_w = J_view @ -skew(rotated)
        residuals.append((view.project(p_w) - p_uv).ravel())
        jacobians.append(np.concatenate([J_w, J_view], axis=-1).reshape(-1, 6))
    return np.concatenate(residuals), np.concatenate(jacobians)


def _orthonormal(R: Array) -> Array:
    """The nearest rotation matrix (removes the round-off of many composed steps)."""
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt
