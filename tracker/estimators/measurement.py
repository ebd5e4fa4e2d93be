"""The measurement and process models shared by the UKF and the grid filter.

Both filters estimate the single angle delta_L from frames whose 3-D data are vectors
``y = Rz(q_r + delta_L) c + noise`` (docs/design.md section 3): the tip, each backbone marker
and the tip velocity, each a *group* with its own noise. This module says, once, what such a
frame is worth when the model is not exact.

Likelihood of a group
---------------------
The residual of a group in the model frame (the catheter's own frame at delta_1 = 0) is
``e(delta_1) = Rz(delta_1)^T y - c``. A contact or a miscalibrated model changes the shape
as a joint deviation would (the paper made its deflections that way), so

    e = J dq + K [dq_p^2, dq_p dq_d, dq_d^2] + noise,   noise ~ N(0, R_bar + M),

- ``J = dc/d(q_p, q_d)`` of each point (mm/mm: the error grows with the arclength) and the
  second-order term K (a deviation of 0.2 mm already turns the tip by 20 degrees);
- ``dq``: the joint-equivalent deviation (mm), a *state* of both filters, estimated online
  (:mod:`tracker.estimators.deviation`): its prior is ``N(0, sigma_q^2 + (gain_error
  q_j)^2)`` per joint (the second term: a bending gain that is off grows with the bending)
  and it decorrelates as the joints move. Persistent, unlike noise: a deflected, nearly
  straight configuration cannot pile up evidence for the opposite plane frame after frame;
- ``R_bar``: the segmentation noise, reduced to its part that is invariant under rotations
  about z_b (the mean of the horizontal variances, the vertical variance). A bi-plane
  reconstruction whose views share the z_b axis has exactly this form; otherwise it is the
  rotation average of the noise (both filters use it, so that their likelihoods are one);
- ``M``: a small white model error ``J diag(sigma_w^2) J^T`` (what a joint deviation does not
  describe exactly).

For a planar catheter J lies in the bending plane, so the model error costs no information
about the plane's angle where the catheter is bent, and takes its sign where the catheter is
nearly straight (a deviation then moves the tip across the axis).

For a given ``dq``, ``d^2 = e^T Sigma^-1 e`` is a trigonometric polynomial of degree two in
the angle (:func:`group_coefficients`), the structure the closed forms use
(:mod:`models.rotation_fit`); :func:`fit_frame` finds its global minimum. Gross errors (a
wrong marker) are a heavy-tailed component: each group is, with probability
``outlier_probability``, drawn from the same Gaussian widened ``outlier_scale`` times
(:func:`mixture_log_likelihood`), so that data the model cannot explain lower the
information of a frame instead of moving the estimate.

The velocity group is the finite-difference or measured tip velocity ``v``, decorrelated
from this frame's tip: ``v - K tip`` with ``K = cov(v, tip) cov(tip)^-1`` (for a finite
difference ``K = I/dt``, and ``v - tip/dt = -tip_{t-1}/dt``: it measures the previous tip).
Its deviation Jacobian is ``-K J_tip``; its own white model error: that of the tip it
repeats, a relative error of the modelled velocity (``velocity_relative_error``), and the
torsion change over the frame interval, which the velocity model leaves out (tangential,
``process variance / dt^2``).

Process model
-------------
A random walk of delta_L whose variance grows with time (``process_noise_rad2_s``) and with
the base rotation (``rotation_noise_gain_rad`` per rad turned): torsion changes when the base
turns and slowly otherwise. With probability :func:`jump_probability` (a rate per second and
per rad turned) the torsion jumps to anywhere on the circle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from models.imaging import OrthographicPlane, PinholeView
from tracker.estimators import measurement_kernels, ukf_kernels

Array = np.ndarray
_EYE3 = np.eye(3)
# Angles at which a frame's cost is evaluated before Newton's method polishes the minimum.
_FIT_ANGLES = np.linspace(-np.pi, np.pi, 64, endpoint=False)
_FIT_TABLE = np.stack(
    [np.ones(64), np.cos(_FIT_ANGLES), np.sin(_FIT_ANGLES), np.cos(2 * _FIT_ANGLES),
     np.sin(2 * _FIT_ANGLES)]
)  # fmt: skip
_TWO_PI = 2.0 * math.pi


def wrap(angle: Array) -> Array:
    """Angles wrapped to [-pi, pi)."""
    return (angle + math.pi) % _TWO_PI - math.pi


def is_every_trial(b: Array | slice, n: int) -> bool:
    """Whether the trial indices b are 0, 1, ..., n - 1 (then no gather is needed; a slice
    stands for every trial)."""
    if isinstance(b, slice):
        return True
    return b.size == n and (n == 1 or bool(b[-1] == n - 1 and np.all(np.diff(b) == 1)))


@dataclass(frozen=True)
class FrameGroups:
    """One frame's 3-D measurement groups for B trials (a leading batch axis).

    Groups ``0 .. n_positions - 1`` are the tip and the catheter's markers; with
    ``has_velocity_group`` the last group is the decorrelated velocity. Groups a trial lacks
    (not segmented, NaN) are not ``present``; their arrays hold harmless placeholders.

    Attributes
    ----------
    q : array, shape (B, 3)
        Joint values (rad, mm, mm).
    y : array, shape (B, G, 3)
        Measured vectors in {B}: mm (positions), mm/s (velocity).
    c : array, shape (B, G, 3)
        Model vectors at delta_1 = 0: the model predicts ``Rz(q_r + delta_L) c``.
    R, R_bar : arrays, shape (B, G, 3, 3)
        Segmentation-noise covariance of each group in {B}, and its rotation-invariant part
        (``diag((R_xx + R_yy) / 2, (R_xx + R_yy) / 2, R_zz)`` plus the antisymmetric horizontal
        part, the noise both filters use).
    JK : array, shape (B, G, 3, 5)
        ``[J K]``, the shape's expansion in the deviation, ``c + JK expansion_basis(dq)``
        (:class:`~tracker.estimators.deviation.ShapeExpansion`; the velocity's is minus the
        decorrelation gain times the tip's).
    present : array of bool, shape (B, G)
    K_bar : array, shape (B, 3, 3)
        Rotation-invariant part of the decorrelation gain of the velocity, 1/s.
    u_norm_mm_s : array, shape (B,)
        Magnitude of the modelled tip velocity, mm/s.
    """

    q: Array
    y: Array
    c: Array
    R: Array
    JK: Array
    present: Array
    R_bar: Array
    n_positions: int
    has_velocity_group: bool
    K_bar: Array
    u_norm_mm_s: Array

    @property
    def n_trials(self) -> int:
        return int(self.y.shape[0])

    @property
    def J(self) -> Array:
        return self.JK[..., :2]

    @property
    def K(self) -> Array:
        return self.JK[..., 2:]

    @property
    def q_r(self) -> Array:
        return self.q[:, 0]

    def select(self, idx: Array) -> FrameGroups:
        """The groups of the trials ``idx`` only."""
        arrays = ("q", "y", "c", "R", "JK", "present", "R_bar", "K_bar", "u_norm_mm_s")
        return replace(self, **{name: getattr(self, name)[idx] for name in arrays})

    dim = 3

    @property
    def z(self) -> Array:
        return self.y

    def radius_mm(self) -> Array:
        """Horizontal radius of the present positions' model vectors, mm (B,)."""
        return measurement_kernels.horizontal_radius(
            np.ascontiguousarray(self.c), self.present, self.n_positions
        )

    def is_tip_group(self, g: int) -> bool:
        """Group 0 is the tip."""
        return g == 0

    def noise(self, b: Array) -> Array:
        """The noise covariance the filters use (model frame), (r, G, 3, 3)."""
        return self.R_bar[b]

    def without_velocity(self, mask: Array) -> FrameGroups:
        """The same groups with the velocity group removed where ``mask`` (B,) is True."""
        if not self.has_velocity_group or not np.any(mask):
            return self
        present = self.present.copy()
        present[mask, -1] = False
        return replace(self, present=present)


def behind_camera(least_depth_mm: float) -> ValueError:
    """The error of a single view's point predicted at or behind its camera."""
    return ValueError(
        f"a predicted point is behind a camera (smallest depth {least_depth_mm:.6g} mm); a"
        " pinhole view needs depth > 0"
    )


@lru_cache(maxsize=64)
def _camera_constants(view) -> tuple[Array, Array, Array, Array, bool] | None:
    """What :func:`measurement_kernels.view_projections` needs of a view: the rotation it
    projects with (OpenCV's, of the camera's Rodrigues vector, for a pinhole camera; the
    plane's axes as rows for an orthographic plane), its translation, fx, fy, cx, cy, the
    distortion and whether it is a pinhole camera; None for another kind of view."""
    if isinstance(view, PinholeView):
        rotation = cv2.Rodrigues(cv2.Rodrigues(np.array(view.R_cam_w))[0])[0]
        K = view.K
        intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        return rotation, np.array(view.t_cam_w, float), intrinsics, np.array(view.dist), True
    if isinstance(view, OrthographicPlane):
        rotation = np.zeros((3, 3))
        rotation[:2] = view.R_w_view[:, :2].T
        return rotation, np.zeros(3), np.ones(4), np.zeros(5), False
    return None


def _view_cameras(parts: tuple) -> tuple[Array, ...] | None:
    """The points' model vectors and cameras, point by point, as
    :func:`measurement_kernels.view_projections` takes them (None if a view is of a kind it
    does not know)."""
    G = sum(C.shape[0] for _, C, _, _ in parts)
    C_all, A, t_all = np.empty((G, 3)), np.empty((G, 3, 3)), np.empty((G, 3))
    intrinsics_all, dist_all = np.empty((G, 4)), np.empty((G, 5))
    pinhole_all = np.empty(G, dtype=np.bool_)
    start = 0
    for view, C, R_w_b, o_b_w in parts:
        constants = _camera_constants(view)
        if constants is None:
            return None
        rotation, t, intrinsics, dist, pinhole = constants
        rows = slice(start, start + C.shape[0])
        C_all[rows] = C
        A[rows] = rotation @ R_w_b
        t_all[rows] = rotation @ o_b_w + t
        intrinsics_all[rows] = intrinsics
        dist_all[rows] = dist
        pinhole_all[rows] = pinhole
        start = rows.stop
    return C_all, A, t_all, intrinsics_all, dist_all, pinhole_all


@dataclass(frozen=True)
class ViewGroups:
    """One trial's points segmented in single views (unsynchronised views), 2-D groups.

    ``parts`` holds, per view, ``(view, C, R_w_b, o_b_w_mm)`` with C the model vectors of its
    points; the groups are the points of every part in order. ``cameras``: the points' model
    vectors and cameras for the compiled projection (made from ``parts``).
    """

    q: Array  # (1, 3)
    z: Array  # (1, G, 2)
    R: Array  # (1, G, 2, 2)
    present: Array  # (1, G)
    parts: tuple
    cameras: tuple | None = None

    dim = 2
    n_positions = 0
    has_velocity_group = False

    def __post_init__(self) -> None:
        if self.cameras is None:
            object.__setattr__(self, "cameras", _view_cameras(self.parts))

    @property
    def q_r(self) -> Array:
        return self.q[:, 0]

    def radius_mm(self) -> Array:
        r2 = sum(float(np.sum(C[:, :2] ** 2)) for _, C, _, _ in self.parts)
        return np.array([math.sqrt(r2)])

    def is_tip_group(self, g: int) -> bool:
        return False

    def noise(self, b: Array) -> Array:
        return self.R[b]

    def predict(
        self,
        b: Array,
        sigmas: Array,
        rate: int | None = None,
        deviation: int | None = None,
        about: Array | None = None,
    ) -> Array:
        """Projections of ``R_w_b Rz(q_r + x_0) c + o_b_w`` in each view: (r, S, G, 2).

        (Image coordinates: ``about`` does not apply; single views carry no deviation
        Jacobian, so ``rate`` and ``deviation`` are unused.)
        """
        angle = self.q[0, 0] + sigmas[..., 0]
        if self.cameras is not None:
            points, least_depth = measurement_kernels.view_projections(
                np.ascontiguousarray(angle, dtype=float).reshape(-1), *self.cameras
            )
            if least_depth <= 0.0:
                raise behind_camera(least_depth)
            return points.reshape(angle.shape + points.shape[1:])
        c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
        parts = []
        for view, C, R_w_b, o_b_w in self.parts:
            points_b = np.stack(
                [c * C[:, 0] - s * C[:, 1], s * C[:, 0] + c * C[:, 1],
                 np.broadcast_to(C[:, 2], c.shape[:-1] + (C.shape[0],))], -1
            )  # fmt: skip
            parts.append(np.asarray(view.project(points_b @ R_w_b.T + o_b_w), dtype=float))
        return np.concatenate(parts, axis=-2)

    def select(self, idx: Array) -> ViewGroups:
        return self

    def innovation(
        self, b: Array, x: Array, factor: Array, spread: float, scale: Array, M: None,
        Wm: Array, Wc: Array, rate: int, deviation: int,
    ) -> tuple[Array, Array, Array, Array, Array]:
        """The UKF's innovation statistics of hypotheses x (r, n) of trials b in image
        coordinates, with the lower Cholesky factors of their covariances: ``S`` (r, m, m)
        with the noise blocks ``scale R`` (no model error: it is defined for 3-D data), the
        residual (r, m), ``Pxz`` (r, n, m), each point's squared residual under its block of
        S (r, G) and the sigma points' offsets (3-D frames:
        :func:`~tracker.estimators.ukf_gate.update_3d`)."""
        noise = self.R[b] * np.asarray(scale, dtype=float)[:, None, None, None]
        sigmas, offsets = ukf_kernels.sigma_rows(x, factor, spread)
        r = x.shape[0]
        hs = np.ascontiguousarray(self.predict(b, sigmas).reshape(r, sigmas.shape[1], -1))
        z = np.ascontiguousarray(self.z[b].reshape(r, -1))
        return ukf_kernels.innovation_stats(hs, z, offsets, noise, Wm, Wc, 2) + (offsets,)


def check_measurement_covariance(noise: Array, present: Array) -> None:
    """ValueError naming the problem if a present group's noise is not usable (its
    rotation-invariant part, which the filters use, must be positive definite)."""
    d = noise.shape[-1]
    diagonal = noise.reshape(noise.shape[:-2] + (d * d,))[..., :: d + 1]
    # (not positive) < present: a present group with a variance that is not positive.
    if ((diagonal > 0) < present[..., None]).any():
        raise ValueError(
            "measurement covariance of the frame is not positive definite (or not finite): "
            "check tip_cov_b, markers_cov_b, velocity_cov_b, velocity_tip_cov_b or the view "
            "covariances"
        )


def velocity_offered(settings, tip_fused: Array) -> Array:
    """Which of B filters fuse a velocity in their next step (``settings``: UKFSettings).

    A finite-difference velocity decorrelated from its frame's tip measures the previous
    tip: it is offered only where the previous step did not use a tip (``tip_fused`` (B,):
    the previous tip was there and no outlier, even if the frame was too uninformative to
    update; a velocity would repeat it with as little information).
    """
    if not settings.use_velocity:
        return np.zeros(tip_fused.shape, dtype=bool)
    if settings.velocity_is_finite_difference:
        return ~tip_fused
    return np.ones(tip_fused.shape, dtype=bool)


def offered_velocity(frame, settings, tip_fused: Array):
    """The frame without the velocity where :func:`velocity_offered` says no."""
    if not isinstance(frame, FrameGroups) or not frame.has_velocity_group:
        return frame
    return frame.without_velocity(~velocity_offered(settings, tip_fused))


# Placeholders of absent tips or markers for the assembling kernel (one trial, unused).
_NO_POINTS, _NO_MARKERS = np.zeros((1, 3)), np.zeros((1, 1, 3))
_NO_COVARIANCES, _NO_MARKER_COVARIANCES = np.zeros((1, 3, 3)), np.zeros((1, 1, 3, 3))


def _finite_rows(a: Array, axes: tuple[int, ...]) -> Array:
    return np.isfinite(a).all(axis=axes)


def assemble_expanded(
    q: Array,
    q_dot: Array | None,
    c: Array,
    JK: Array,
    tip: Array | None,
    tip_cov: Array | None,
    markers: Array | None,
    markers_cov: Array | None,
    velocity: Array | None = None,
    velocity_cov: Array | None = None,
    cross: Array | None = None,
) -> FrameGroups:
    """The groups of one frame of B trials from reconstructed 3-D data, with the shape
    expansion as ``JK = [J K]`` (B, P, 3, 5), as
    :meth:`~tracker.estimators.deviation.ShapeExpansion.expanded` gives it (held, not copied,
    without a velocity group).

    Parameters
    ----------
    q, q_dot : arrays (B, 3)
        Joint values and rates (``q_dot`` None or NaN: no velocity).
    c, JK : arrays (B, P, 3), (B, P, 3, 5)
        :class:`~tracker.estimators.deviation.ShapeExpansion` of every trial: c, then J
        (the deviation's slope) and K (its quadratic term) side by side.
    tip, tip_cov : arrays (B, 3), (B, 3, 3), or None
    markers, markers_cov : arrays (B, P - 1, 3), (B, P - 1, 3, 3), or None
        NaN rows: markers not found.
    velocity, velocity_cov, cross : arrays (B, 3), (B, 3, 3), (B, 3, 3), optional
        Tip velocity (mm/s), its covariance and its cross-covariance with the tip; a
        velocity group exists when ``velocity`` is given (present where finite).
    """
    B, P = c.shape[:2]
    has_v = velocity is not None
    G = P + has_v
    has_tip = tip is not None and tip_cov is not None
    has_markers = markers is not None and markers_cov is not None and P > 1
    contiguous = np.ascontiguousarray
    y, R, R_bar, present = measurement_kernels.assemble_positions(
        contiguous(tip, dtype=float) if has_tip else _NO_POINTS,
        contiguous(tip_cov, dtype=float) if has_tip else _NO_COVARIANCES,
        contiguous(markers, dtype=float) if has_markers else _NO_MARKERS,
        contiguous(markers_cov, dtype=float) if has_markers else _NO_MARKER_COVARIANCES,
        B, P, G, has_tip, has_markers,
    )  # fmt: skip
    C = c
    K_bar = np.zeros((B, 3, 3))
    u_norm = np.zeros(B)
    if has_v:
        C = np.zeros((B, G, 3))
        C[:, :P] = c
        JK_all = np.zeros((B, G, 3, 5))
        JK_all[:, :P] = JK
        JK = JK_all
        rates = np.full((B, 3), np.nan) if q_dot is None else np.asarray(q_dot, dtype=float)
        ok = (
            _finite_rows(velocity, (-1,))
            & _finite_rows(velocity_cov, (-2, -1))
            & _finite_rows(rates, (-1,))
        )
        present[:, -1] = ok
        if ok.any():
            v_bar, cov_bar, gain = decorrelated_velocity(
                np.where(ok[:, None], velocity, 0.0),
                np.where(ok[:, None, None], velocity_cov, _EYE3),
                None if cross is None else np.where(ok[:, None, None], cross, np.nan),
                y[:, 0], R[:, 0], present[:, 0],
            )  # fmt: skip
            contiguous = np.ascontiguousarray
            K_bar, u_norm = measurement_kernels.velocity_group(
                contiguous(c, dtype=float), contiguous(JK_all[:, :P]), contiguous(rates),
                contiguous(v_bar), contiguous(cov_bar), contiguous(gain), ok, y, R, R_bar, C,
                JK_all,
            )  # fmt: skip
    return FrameGroups(
        q=np.asarray(q, dtype=float), y=y, c=C, R=R, JK=JK, present=present,
        R_bar=R_bar, n_positions=P,
        has_velocity_group=has_v, K_bar=K_bar, u_norm_mm_s=u_norm,
    )  # fmt: skip


def decorrelated_velocity(
    velocity: Array, velocity_cov: Array, cross: Array | None, tip: Array, tip_cov: Array,
    has_tip: Array,
) -> tuple[Array, Array, Array]:
    """``v - K tip`` and its covariance, with ``K = cov(v, tip) cov(tip)^-1`` (B trials).

    Returns the decorrelated velocity (B, 3), its covariance ``cov(v) - K cov(v, tip)^T``
    (B, 3, 3) and K (B, 3, 3); trials without a tip or a finite cross-covariance keep the
    velocity (K = 0).
    """
    B = velocity.shape[0]
    K = np.zeros((B, 3, 3))
    if cross is None:
        return velocity, velocity_cov, K
    usable = has_tip & _finite_rows(cross, (-2, -1))
    if not usable.any():
        return velocity, velocity_cov, K
    C = np.where(usable[:, None, None], cross, 0.0)
    # K = C S^-1, i.e. K^T = S^-1 C^T (S symmetric): one solve per trial.
    S = np.where(usable[:, None, None], tip_cov, _EYE3)
    K = np.linalg.solve(S, C.mT).mT
    v_bar = velocity - (K @ tip[..., None])[..., 0]
    cov = velocity_cov - K @ C.mT
    return v_bar, 0.5 * (cov + cov.mT), K


def model_error_covariance(
    groups: FrameGroups,
    white_mm: float,
    velocity_relative_error: float,
    process_var_rad2: Array,
    dt_s: Array,
) -> Array:
    """White model-error covariance ``M`` of every group in the model frame, (B, G, 3, 3).

    Parameters
    ----------
    white_mm : float
        Joint-equivalent white model error sigma_w, mm.
    velocity_relative_error : float
        Relative error of the modelled tip velocity.
    process_var_rad2 : array, shape (B,)
        Variance of the torsion change over this frame interval, rad^2 (0 when the state
        carries the rate).
    dt_s : array, shape (B,)
        The frame interval, s.
    """
    return measurement_kernels.model_error(
        np.ascontiguousarray(groups.JK), float(white_mm), groups.has_velocity_group,
        np.ascontiguousarray(groups.c), np.ascontiguousarray(groups.u_norm_mm_s, dtype=float),
        float(velocity_relative_error), np.ascontiguousarray(process_var_rad2, dtype=float),
        np.ascontiguousarray(dt_s, dtype=float),
    )  # fmt: skip


def group_coefficients(y: Array, c: Array, W: Array, q_r: Array) -> Array:
    """``d^2(delta_L) = e^T W e`` of every group as a trigonometric polynomial.

    ``e = Rz(q_r + delta_L)^T y - c`` is affine in (cos, sin) of the angle, so ``d^2 = k +
    a1 cos(delta_L) + b1 sin(delta_L) + a2 cos(2 delta_L) + b2 sin(2 delta_L)``.

    Parameters
    ----------
    y, c : arrays, shape (B, G, 3)
    W : array, shape (B, G, 3, 3)
        Inverse of the model-frame covariance of each group.
    q_r : array, shape (B,)

    Returns
    -------
    coefficients : array, shape (B, G, 5)
        ``[k, a1, b1, a2, b2]``.
    """
    zero = np.zeros_like(y[..., 0])
    p = np.stack([y[..., 0], y[..., 1], zero], -1)  # cos(delta_1) part of Rz^T y
    s = np.stack([y[..., 1], -y[..., 0], zero], -1)  # sin(delta_1) part
    r0 = np.stack([-c[..., 0], -c[..., 1], y[..., 2] - c[..., 2]], -1)
    Wp = np.einsum("bgij,bgj->bgi", W, p)
    Ws = np.einsum("bgij,bgj->bgi", W, s)
    pWp = np.sum(p * Wp, -1)
    sWs = np.sum(s * Ws, -1)
    pWs = np.sum(s * Wp, -1)
    a1 = 2 * np.sum(r0 * Wp, -1)
    b1 = 2 * np.sum(r0 * Ws, -1)
    k = 0.5 * (pWp + sWs) + np.einsum("bgi,bgij,bgj->bg", r0, W, r0)
    a2 = 0.5 * (pWp - sWs)
    b2 = pWs
    # From delta_1 = q_r + delta_L to delta_L: rotate each (cos, sin) pair by q_r or 2 q_r.
    c1, s1 = np.cos(q_r)[:, None], np.sin(q_r)[:, None]
    c2, s2 = c1 * c1 - s1 * s1, 2 * s1 * c1
    return np.stack(
        [k, a1 * c1 + b1 * s1, b1 * c1 - a1 * s1, a2 * c2 + b2 * s2, b2 * c2 - a2 * s2], -1
    )


def trig_table(angles: Array) -> Array:
    """Rows ``1, cos, sin, cos 2x, sin 2x`` of angles (N,): (5, N)."""
    return np.stack(
        [np.ones_like(angles), np.cos(angles), np.sin(angles), np.cos(2 * angles),
         np.sin(2 * angles)]
    )  # fmt: skip


@dataclass(frozen=True)
class FrameFit:
    """Global fit of one frame's summed cost ``f = sum_g d_g^2`` (B trials).

    Attributes
    ----------
    delta_L_rad : array (B,)
        Minimiser.
    cost : array (B,)
        ``f`` at the minimiser (chi-square with ``dof - 1`` degrees of freedom).
    information : array (B,)
        ``f'' / 2`` at the minimiser, 1/rad^2 (``1/std^2``).
    sign_evidence : array (B,)
        ``min f`` over the half circle away from the minimiser minus ``cost``: how much
        better the fit is than any fit on the opposite side (0 for a straight catheter).
    dof : array of int (B,)
        Measurement dimension.
    """

    delta_L_rad: Array
    cost: Array
    information: Array
    sign_evidence: Array
    dof: Array

    @property
    def std_rad(self) -> Array:
        with np.errstate(divide="ignore"):
            return np.where(self.information > 0, 1.0 / np.sqrt(self.information), np.inf)


def fit_frame(
    coefficients: Array, dof: Array, information: Array | None = None, newton_steps: int = 4
) -> FrameFit:
    """Global minimum of ``f(delta) = coefficients . [1, cos, sin, cos 2, sin 2]`` (B, 5).

    A degree-two trigonometric polynomial has at most two minima; 64 samples find the basin of
    the global one and Newton's method polishes it. ``information`` (B,): the Fisher
    information to report (default: the observed one, ``f''/2`` at the minimum).
    """
    f = coefficients @ _FIT_TABLE  # (B, 64)
    best = np.argmin(f, axis=1)
    x = _FIT_ANGLES[best]
    k, a1, b1, a2, b2 = np.moveaxis(coefficients, -1, 0)
    for _ in range(newton_steps):
        c1, s1, c2, s2 = np.cos(x), np.sin(x), np.cos(2 * x), np.sin(2 * x)
        d1 = -a1 * s1 + b1 * c1 - 2 * a2 * s2 + 2 * b2 * c2
        d2 = -a1 * c1 - b1 * s1 - 4 * a2 * c2 - 4 * b2 * s2
        x = np.where(d2 > 0, x - d1 / np.where(d2 > 0, d2, 1.0), x)
    c1, s1, c2, s2 = np.cos(x), np.sin(x), np.cos(2 * x), np.sin(2 * x)
    cost = k + a1 * c1 + b1 * s1 + a2 * c2 + b2 * s2
    curvature = -a1 * c1 - b1 * s1 - 4 * a2 * c2 - 4 * b2 * s2
    far = np.abs(wrap(_FIT_ANGLES[None, :] - x[:, None])) > 0.5 * math.pi
    other = np.min(np.where(far, f, np.inf), axis=1)
    if information is None:
        information = np.maximum(0.5 * curvature, 0.0)
    return FrameFit(
        delta_L_rad=wrap(x),
        cost=np.maximum(cost, 0.0),
        information=information,
        sign_evidence=np.maximum(other - cost, 0.0),
        dof=np.asarray(dof),
    )


def mixture_log_likelihood(
    d2: Array, dim: int, outlier_probability: float, outlier_scale: float
) -> Array:
    """log of ``(1 - p) exp(-d2/2) + p s^-dim exp(-d2 / (2 s^2))`` without the Gaussian's
    normalisation (add ``-0.5 log det(2 pi Sigma)``), stable for any ``d2 >= 0``.

    With ``p = 0`` it is the Gaussian ``-d2/2``.
    """
    if outlier_probability <= 0.0:
        return -0.5 * d2
    log_outlier = math.log(outlier_probability) - dim * math.log(outlier_scale)
    ratio = (1.0 - outlier_probability) / math.exp(log_outlier)
    shrink = 1.0 - outlier_scale**-2
    return log_outlier - 0.5 * d2 / outlier_scale**2 + np.log1p(ratio * np.exp(-0.5 * shrink * d2))


@lru_cache(maxsize=64)
def outlier_threshold(dim: int, outlier_probability: float, outlier_scale: float) -> float:
    """The squared residual beyond which a group is more likely an outlier than not: where
    :func:`inlier_probability` falls to one half (inf without outliers)."""
    if outlier_probability <= 0.0:
        return math.inf
    odds = math.log((1.0 - outlier_probability) / outlier_probability)
    return 2.0 * (odds + dim * math.log(outlier_scale)) / (1.0 - outlier_scale**-2)


def inlier_probability(
    d2: Array, dim: int, outlier_probability: float, outlier_scale: float
) -> Array:
    """Posterior probability that a group with squared Mahalanobis residual d2 is no outlier."""
    if outlier_probability <= 0.0:
        return np.ones_like(d2)
    log_ratio = (
        math.log(outlier_probability / (1.0 - outlier_probability))
        - dim * math.log(outlier_scale)
        + 0.5 * (1.0 - outlier_scale**-2) * np.minimum(d2, 1e4)
    )
    return 1.0 / (1.0 + np.exp(np.minimum(log_ratio, 700.0)))


def process_variance(
    noise_rad2_s: float, rotation_gain_rad: float, dt_s: Array, base_turn_rad: Array
) -> Array:
    """Variance of the torsion change over dt with the base turned by ``base_turn_rad``."""
    return noise_rad2_s * dt_s + rotation_gain_rad * np.abs(base_turn_rad)


def jump_probability(
    rate_per_s: float, per_rad: float, dt_s: Array, base_turn_rad: Array
) -> Array:
    """Probability that the torsion jumped (anywhere on the circle) over the interval."""
    hazard = rate_per_s * dt_s + per_rad * np.abs(base_turn_rad)
    return -np.expm1(-hazard)


__all__ = [
    "FrameFit",
    "FrameGroups",
    "ViewGroups",
    "behind_camera",
    "decorrelated_velocity",
    "fit_frame",
    "group_coefficients",
    "inlier_probability",
    "is_every_trial",
    "assemble_expanded",
    "check_measurement_covariance",
    "jump_probability",
    "mixture_log_likelihood",
    "offered_velocity",
    "outlier_threshold",
    "velocity_offered",
    "model_error_covariance",
    "process_variance",
    "trig_table",
    "wrap",
]
