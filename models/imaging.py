"""Bi-plane imaging geometry: orthographic planes, pinhole views, reconstruction and noise.

Two view models share one interface (``project``, ``projection_jacobian``):

- :class:`OrthographicPlane`, the paper's model: a plane with unit normal ``n`` in {W}, the
  projector ``P = I - n n^T`` and the rotation ``R_w_view`` from in-plane coordinates (mm) to {W}.
- :class:`PinholeView`, a calibrated camera in OpenCV's conventions (camera x right, y down,
  z along the optical axis; distortion k1, k2, p1, p2, k3), images in px.

:class:`Rig` holds two or more named views of the same kind (the paper's bi-plane rig: front
and side), reconstructs points (and,
orthographic only, difference vectors such as tip minus base) and propagates 2-D segmentation
noise to the 3-D covariance of the reconstruction. World units are mm; arrays are batch-first.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from models import _imaging_kernels

Array = np.ndarray

MIN_PLANE_ANGLE_RAD = np.deg2rad(1.0)
"""Smallest angle between the two plane normals that still allows reconstruction."""
MIN_BASELINE_MM = 1.0
"""Camera centres closer than this are treated as coincident (real rigs: hundreds of mm)."""

_ROTATION_TOL = 1e-6
_PARALLEL = (
    "cannot triangulate {} point(s): their viewing rays are parallel (a point on the line"
    " through the camera centres?)"
)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)  # px


# ---------------------------------------------------------------------------------- checks
def _checked(x, name: str, shape: tuple[int, ...], batched: bool = True) -> Array:
    """Float array of shape (..., *shape) (or exactly ``shape``), all finite, or ValueError."""
    x = np.asarray(x, dtype=float)
    if x.shape[max(x.ndim - len(shape), 0) :] != shape or (not batched and x.ndim != len(shape)):
        want = ", ".join(["..."] * batched + [str(n) for n in shape])
        raise ValueError(f"{name} must have shape ({want}), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    return x


def _frozen(x: Array) -> Array:
    x = np.array(x, dtype=float)
    x.flags.writeable = False
    return x


def _rotation(R, name: str) -> Array:
    R = _checked(R, name, (3, 3), batched=False)
    if np.abs(R.T @ R - np.eye(3)).max() > _ROTATION_TOL or np.linalg.det(R) < 0.0:
        raise ValueError(f"{name} must be a rotation matrix (orthonormal, det +1), got\n{R}")
    return _frozen(R)


def _unit(v: Array, name: str) -> Array:
    norm = np.linalg.norm(v)
    if norm < 1e-12:
        raise ValueError(f"{name} must be a non-zero vector, got {v}")
    return v / norm


def _covariance_problem(C: Array, scale) -> str | None:
    """Why covariances C (..., 2, 2) are not symmetric positive semi-definite, to a tolerance
    relative to ``scale`` (which broadcasts against ``C[..., 0, 0]``); None if they are."""
    a, b, c, d = C[..., 0, 0], C[..., 0, 1], C[..., 1, 0], C[..., 1, 1]
    if (np.abs(b - c) > 1e-9 * scale).any():
        return "must be symmetric"
    # The smaller eigenvalue of each 2x2 in closed form, from its lower triangle as eigvalsh
    # would read it: a tenth of eigvalsh's cost, on every frame of the live loop.
    if (0.5 * (a + d) - np.hypot(0.5 * (a - d), c) < -1e-12 * scale).any():
        return (
            "must be positive semi-definite (a scalar sigma goes through"
            " isotropic_covariance(sigma))"
        )
    return None


def _covariance(cov, name: str) -> Array:
    C = _checked(cov, name, (2, 2))
    problem = _covariance_problem(C, np.abs(C).max(initial=1e-300))
    if problem is not None:
        raise ValueError(f"{name} {problem}")
    return C


def isotropic_covariance(sigma, dim: int = 2) -> Array:
    """Covariance ``sigma**2 * I`` of isotropic noise.

    Parameters
    ----------
    sigma : float or array, shape (...)
        Standard deviation per axis (mm or px), finite and >= 0.
    dim : int
        Dimension of the noise.

    Returns
    -------
    cov : array, shape (..., dim, dim)
        Covariance, in the square of the unit of ``sigma``.
    """
    s = np.asarray(sigma, dtype=float)
    if not np.all(np.isfinite(s)) or np.any(s < 0.0):
        raise ValueError(f"sigma must be finite and >= 0, got {sigma}")
    if int(dim) != dim or dim < 1:
        raise ValueError(f"dim must be a positive integer, got {dim}")
    return s[..., None, None] ** 2 * np.eye(int(dim))


# ----------------------------------------------------------------------------------- views
@dataclass(frozen=True, eq=False)
class OrthographicPlane:
    """Orthographic imaging plane (the paper's model).

    Parameters
    ----------
    R_w_view : array, shape (3, 3)
        Rotation from view coordinates to {W}. Its columns are, in {W}, the in-plane axis u
        (image right), the in-plane axis v (image up) and the normal ``n = u x v``, which points
        toward the viewer. The in-plane coordinates of a world point x are
        ``(R_w_view^T x)[:2]``, mm.
    """

    R_w_view: Array

    def __post_init__(self) -> None:
        object.__setattr__(self, "R_w_view", _rotation(self.R_w_view, "R_w_view"))

    @classmethod
    def from_normal(cls, normal_w, in_plane_rotation_rad: float = 0.0) -> OrthographicPlane:
        """Plane with the given normal and image "up" as close to world z as possible.

        Parameters
        ----------
        normal_w : array, shape (3,)
            Plane normal in {W} (any non-zero length), pointing toward the viewer.
        in_plane_rotation_rad : float
            Rotation of the in-plane axes about the normal, rad (u turns toward v).

        Notes
        -----
        v is world z projected onto the plane (world y when the normal is within about 26
        degrees of z, i.e. for views from above or below), then ``u = v x n``.
        """
        n = _unit(_checked(normal_w, "normal_w", (3,), batched=False), "normal_w")
        angle = float(_checked(in_plane_rotation_rad, "in_plane_rotation_rad", (), False))
        up = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        v = _unit(up - (up @ n) * n, "in-plane up axis")
        u = np.cross(v, n)
        c, s = np.cos(angle), np.sin(angle)
        return cls(np.column_stack([c * u + s * v, c * v - s * u, n]))

    @property
    def normal_w(self) -> Array:
        """Unit normal n of the plane in {W}, shape (3,)."""
        return self.R_w_view[:, 2].copy()

    @property
    def projector_w(self) -> Array:
        """Orthogonal projector onto the plane, ``P = I - n n^T``, shape (3, 3)."""
        n = self.R_w_view[:, 2]
        return np.eye(3) - np.outer(n, n)

    def project(self, points_w) -> Array:
        """In-plane coordinates (u, v), mm, shape (..., 2), of points (..., 3) in {W}, mm."""
        return _checked(points_w, "points_w", (3,)) @ self.R_w_view[:, :2]

    def projection_jacobian(self, points_w) -> Array:
        """d(u, v)/dx, shape (..., 2, 3), dimensionless (mm/mm), of points (..., 3) in {W}."""
        x = _checked(points_w, "points_w", (3,))
        return np.broadcast_to(self.R_w_view[:, :2].T, x.shape[:-1] + (2, 3)).copy()


@dataclass(frozen=True, eq=False)
class PinholeView:
    """Calibrated pinhole camera in OpenCV's conventions: ``x_cam = R_cam_w @ x_w + t_cam_w``.

    Parameters
    ----------
    K : array, shape (3, 3)
        Intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, px (no skew: OpenCV ignores it).
    R_cam_w : array, shape (3, 3)
        Rotation from {W} to the camera frame (x right, y down, z along the optical axis).
    t_cam_w : array, shape (3,)
        Origin of {W} in the camera frame, mm.
    dist : array, shape (5,), optional
        OpenCV distortion coefficients (k1, k2, p1, p2, k3); None or omitted means zero.
    image_size : tuple of int
        (width, height), px.
    """

    K: Array
    R_cam_w: Array
    t_cam_w: Array
    dist: Array | None = None
    image_size: tuple[int, int] = (640, 480)
    _rvec: Array = field(init=False, repr=False)
    _distorted: bool = field(init=False, repr=False)  # any non-zero distortion coefficient

    def __post_init__(self) -> None:
        K = _checked(self.K, "K", (3, 3), batched=False)
        if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
            raise ValueError(f"K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
        if K[0, 1] != 0.0 or np.any(K[2] != (0.0, 0.0, 1.0)) or K[1, 0] != 0.0:
            raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got\n{K}")
        dist = np.zeros(5) if self.dist is None else _checked(self.dist, "dist", (5,), False)
        size = tuple(int(n) for n in self.image_size)
        if len(size) != 2 or min(size) < 1 or size != tuple(self.image_size):
            raise ValueError(f"image_size must be (width, height) in px, got {self.image_size}")
        R = _rotation(self.R_cam_w, "R_cam_w")
        object.__setattr__(self, "K", _frozen(K))
        object.__setattr__(self, "R_cam_w", R)
        object.__setattr__(self, "t_cam_w", _frozen(_checked(self.t_cam_w, "t_cam_w", (3,), False)))
        object.__setattr__(self, "dist", _frozen(dist))
        object.__setattr__(self, "image_size", size)
        object.__setattr__(self, "_rvec", cv2.Rodrigues(np.array(R))[0])
        object.__setattr__(self, "_distorted", bool(np.any(dist)))

    @classmethod
    def look_at(
        cls, center_w, target_w, up_w, focal_px: float, image_size=(640, 480), dist=None
    ) -> PinholeView:
        """Camera at ``center_w`` looking at ``target_w`` with ``up_w`` pointing up in the image.

        Parameters
        ----------
        center_w, target_w : array, shape (3,)
            Optical centre and a point on the optical axis, in {W}, mm.
        up_w : array, shape (3,)
            World direction that appears as image up; must not be parallel to the optical axis.
        focal_px : float
            Focal length fx = fy, px; the principal point is the image centre.
        image_size : tuple of int
            (width, height), px.
        dist : array, shape (5,), optional
            OpenCV distortion coefficients.
        """
        c = _checked(center_w, "center_w", (3,), batched=False)
        forward = _checked(target_w, "target_w", (3,), batched=False) - c
        if np.linalg.norm(forward) < 1e-9:
            raise ValueError("center_w and target_w coincide: the viewing direction is undefined")
        z = forward / np.linalg.norm(forward)
        up = _checked(up_w, "up_w", (3,), batched=False)
        down = -(up - (up @ z) * z)
        if np.linalg.norm(down) <= 1e-9 * max(np.linalg.norm(up), 1e-300):
            raise ValueError("up_w is zero or parallel to the viewing direction")
        y = down / np.linalg.norm(down)
        R_cam_w = np.stack([np.cross(y, z), y, z])
        f = float(_checked(focal_px, "focal_px", (), False))
        width, height = image_size
        K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(K, R_cam_w, -R_cam_w @ c, dist, tuple(image_size))

    @property
    def center_w(self) -> Array:
        """Optical centre in {W}, mm, shape (3,)."""
        return -self.R_cam_w.T @ self.t_cam_w

    def _project(self, x: Array) -> tuple[Array, Array]:
        """Pixels (..., 2) and d pixel / d x_cam (..., 2, 3), px/mm, of points (..., 3) in
        {W} that went through ``_checked`` already."""
        _check_in_front(x @ self.R_cam_w[2] + self.t_cam_w[2])
        batch = x.shape[:-1]
        if x.size == 0:
            return np.zeros(batch + (2,)), np.zeros(batch + (2, 3))
        pixels, jac = cv2.projectPoints(
            np.ascontiguousarray(x.reshape(-1, 3)), self._rvec, self.t_cam_w, self.K, self.dist
        )
        # OpenCV's Jacobian columns 3:6 are d pixel / d tvec, which is d pixel / d x_cam.
        return pixels.reshape(batch + (2,)), jac[:, 3:6].reshape(batch + (2, 3))

    def project(self, points_w) -> Array:
        """Distorted pixels, shape (..., 2), of points (..., 3) in {W}, mm.

        Raises ValueError if a point is not strictly in front of the camera.
        """
        return self._project(_checked(points_w, "points_w", (3,)))[0]

    def projection_jacobian(self, points_w) -> Array:
        """d pixel / d x_w, shape (..., 2, 3), px/mm, analytic (distortion included)."""
        return self._project(_checked(points_w, "points_w", (3,)))[1] @ self.R_cam_w

    def undistort(self, pixels) -> Array:
        """Ideal (distortion-free) pixels in the px of K, shape (..., 2), of observed pixels."""
        p = _checked(pixels, "pixels", (2,))
        if not self._distorted or p.size == 0:
            return p.copy()
        ideal = cv2.undistortPoints(
            np.ascontiguousarray(p.reshape(-1, 1, 2)),
            np.array(self.K),
            np.array(self.dist),
            P=np.array(self.K),
            criteria=_UNDISTORT_CRITERIA,
        )
        return ideal.reshape(p.shape)


View = OrthographicPlane | PinholeView


def _check_in_front(depth_mm: Array) -> None:
    """ValueError unless every depth along a camera's optical axis is positive, mm."""
    if (depth_mm <= 0.0).any():
        raise ValueError(
            f"{np.count_nonzero(depth_mm <= 0.0)} point(s) behind the camera (smallest depth"
            f" {depth_mm.min():.6g} mm); a pinhole view needs depth > 0"
        )


def _stack_views(arrays: list[Array], core: tuple[int, ...]) -> Array:
    """Per-view arrays (..., *core) on one views axis before ``core``: (..., V, *core), their
    batch shapes broadcast (or ValueError)."""
    batch = arrays[0].shape[: -len(core)]
    if any(a.shape[: -len(core)] != batch for a in arrays):
        arrays = np.broadcast_arrays(*arrays)
        batch = arrays[0].shape[: -len(core)]
    stacked = np.concatenate(arrays, axis=-len(core))  # (..., V * core[0], *core[1:])
    return stacked.reshape(batch + (len(arrays), *core))


@dataclass(frozen=True, eq=False)
class _Cameras:
    """The cameras of a pinhole rig stacked view by view, for reconstruction vectorised over
    the views."""

    principal: Array  # (V, 2): cx, cy, px
    focal: Array  # (V, 2): fx, fy, px
    inverse_focal: Array  # (V, 2, 2): diag(1 / fx, 1 / fy), 1/px
    R_cam_w: Array  # (V, 3, 3)
    t_cam_w: Array  # (V, 3), mm
    distorted: tuple[int, ...]  # the views with distortion
    # Pieces of R_cam_w and t_cam_w in the shapes the DLT rows are made of: the first two
    # rows (V, 2, 3) and the third (V, 1, 3); the first two entries (V, 2), the third (V, 1).
    R_12: Array = field(init=False)
    r_3: Array = field(init=False)
    t_12: Array = field(init=False)
    t_3: Array = field(init=False)

    def __post_init__(self) -> None:
        for name, value in (
            ("R_12", self.R_cam_w[:, :2]),
            ("r_3", self.R_cam_w[:, 2:]),
            ("t_12", self.t_cam_w[:, :2]),
            ("t_3", self.t_cam_w[:, 2:]),
        ):
            object.__setattr__(self, name, value)

    @classmethod
    def of(cls, views: tuple[PinholeView, ...]) -> _Cameras:
        focal = np.stack([np.diag(v.K)[:2] for v in views])
        return cls(
            principal=_frozen(np.stack([v.K[:2, 2] for v in views])),
            focal=_frozen(focal),
            inverse_focal=_frozen(np.eye(2) / focal[:, None, :]),
            R_cam_w=_frozen(np.stack([v.R_cam_w for v in views])),
            t_cam_w=_frozen(np.stack([v.t_cam_w for v in views])),
            distorted=tuple(i for i, v in enumerate(views) if v._distorted),
        )


# ------------------------------------------------------------------------------------- rig
DEFAULT_VIEW_NAMES = ("front", "side")
"""Names of the views of a two-view rig: the paper's bi-plane case ({F} and {S})."""


def default_view_names(n_views: int) -> tuple[str, ...]:
    """``("front", "side")`` for two views, ``("view0", "view1", ...)`` otherwise."""
    return DEFAULT_VIEW_NAMES if n_views == 2 else tuple(f"view{i}" for i in range(n_views))


class Rig:
    """Two or more named views of the same kind, and reconstruction from any two or more.

    Parameters
    ----------
    *views : OrthographicPlane or PinholeView
        The views, all orthographic or all pinhole; the paper's bi-plane rig is
        ``Rig(front, side)``.
    names : sequence of str, optional
        One distinct name per view (:func:`default_view_names` by default). Every per-view
        sequence in the data flow (image points, covariances, images, recording channels)
        follows this order.
    """

    __slots__ = ("views", "names", "_M", "_M_views", "_cameras", "_subsets")

    def __init__(self, *views: View, names=None) -> None:
        if len(views) == 1 and isinstance(views[0], list | tuple):
            views = tuple(views[0])
        names = default_view_names(len(views)) if names is None else tuple(names)
        if len(views) < 2:
            raise ValueError(f"a rig needs at least two views, got {len(views)}")
        if len(names) != len(views) or len(set(names)) != len(names):
            raise ValueError(f"a rig needs one distinct name per view, got {names!r}")
        for name, view in zip(names, views, strict=True):
            if not isinstance(name, str) or not name.isidentifier():
                raise ValueError(f"view name {name!r} must be a non-empty identifier")
            if not isinstance(view, OrthographicPlane | PinholeView):
                raise TypeError(f"{name} must be an OrthographicPlane or a PinholeView")
        kinds = {type(v) for v in views}
        if len(kinds) > 1:
            kinds = [f"{n}: {type(v).__name__}" for n, v in zip(names, views, strict=True)]
            raise ValueError("all views must be of the same kind, got " + " and ".join(kinds))
        object.__setattr__(self, "views", tuple(views))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "_subsets", {})
        if isinstance(views[0], OrthographicPlane):
            normals = [v.normal_w for v in views]
            angle = max(
                np.arctan2(np.linalg.norm(np.cross(a, b)), abs(a @ b))
                for i, a in enumerate(normals)
                for b in normals[i + 1 :]
            )
            if angle < MIN_PLANE_ANGLE_RAD:
                raise ValueError(
                    f"cannot reconstruct: imaging planes are parallel (normals"
                    f" {np.degrees(angle):.3g} deg apart, need at least"
                    f" {np.degrees(MIN_PLANE_ANGLE_RAD):.3g} deg)"
                )
            # eq. estDK: [P_1; ...; P_n]^+ = (sum P_v)^-1 [P_1, ..., P_n], and P U = U for the
            # in-plane axes U of each plane.
            U = np.concatenate([v.R_w_view[:, :2] for v in views], axis=1)
            M = np.linalg.solve(sum(v.projector_w for v in views), U)
            object.__setattr__(self, "_M", _frozen(M))
            # M_v = M[:, 2v:2v+2], the columns of M of view v, shape (V, 3, 2).
            object.__setattr__(self, "_M_views", _frozen(M.reshape(3, -1, 2).swapaxes(0, 1)))
            object.__setattr__(self, "_cameras", None)
        else:
            centres = [v.center_w for v in views]
            baseline_mm = max(
                np.linalg.norm(a - b) for i, a in enumerate(centres) for b in centres[i + 1 :]
            )
            if baseline_mm < MIN_BASELINE_MM:
                raise ValueError(
                    f"cannot reconstruct: camera centres are {baseline_mm:.3g} mm apart"
                    f" (coincident, or baseline below {MIN_BASELINE_MM} mm)"
                )
            object.__setattr__(self, "_M", None)
            object.__setattr__(self, "_M_views", None)
            object.__setattr__(self, "_cameras", _Cameras.of(views))
            _imaging_kernels.warm_up()

    def __setattr__(self, name, value):
        raise AttributeError("a Rig is immutable")

    def __reduce__(self):
        # Pickled (to another process) as its views and names, rebuilt through __init__.
        return (_rig_of, (self.views, self.names))

    def __repr__(self) -> str:
        inner = ", ".join(f"{n}={v!r}" for n, v in zip(self.names, self.views, strict=True))
        return f"Rig({inner})"

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, name: str) -> View:
        """The view called ``name``."""
        return self.views[self.index(name)]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            views = ", ".join(self.names)
            raise KeyError(f"no view {name!r} in the rig (views: {views})") from None

    @property
    def n_views(self) -> int:
        return len(self.views)

    @property
    def kind(self) -> str:
        """``"orthographic"`` or ``"pinhole"``."""
        return "orthographic" if isinstance(self.views[0], OrthographicPlane) else "pinhole"

    def subset(self, indices) -> Rig:
        """The rig of the views ``indices`` (two or more), cached."""
        key = tuple(int(i) for i in indices)
        if key == tuple(range(len(self.views))):
            return self
        if key not in self._subsets:
            self._subsets[key] = Rig(
                *(self.views[i] for i in key), names=[self.names[i] for i in key]
            )
        return self._subsets[key]

    def project(self, points_w) -> tuple[Array, ...]:
        """Images, one (..., 2) array per view in mm or px, of points (..., 3) in {W}, mm."""
        return tuple(view.project(points_w) for view in self.views)

    def reconstruction_matrix(self) -> Array:
        """The linear map ``[u_1, v_1, ..., u_n, v_n] -> x`` of eq. estDK, shape (3, 2n).

        It is ``[P_1; ...; P_n]^+ blockdiag(R_w_1[:, :2], ..., R_w_n[:, :2])``; because it is
        linear it applies to difference vectors too. Orthographic rigs only.
        """
        if self._M is None:
            raise ValueError(
                "reconstruction_matrix is only defined for orthographic rigs: pinhole"
                " reconstruction is not linear (use reconstruction_covariance for noise)"
            )
        return np.array(self._M)

    def reconstruct(self, *uv) -> Array:
        """Points in {W} from their images in every view.

        Parameters
        ----------
        *uv : arrays, shape (..., 2)
            One per view, in the rig's order: image points, mm in the plane (orthographic)
            or distorted px (pinhole); their batch shapes broadcast.

        Returns
        -------
        points_w : array, shape (..., 3)
            Reconstructed points in {W}, mm. Orthographic: eq. estDK,
            ``x = [P_1; ...; P_n]^+ [R_w_1 (u_1, v_1, 0); ...]``, which also maps difference
            vectors (tip minus base). Pinhole: undistortion, then linear triangulation (the
            least-squares solution of the 2n DLT equations in x).
        """
        if len(uv) != len(self.views):
            raise ValueError(f"expected image points for {len(self.views)} views, got {len(uv)}")
        uv = [_checked(u, f"uv_{n}", (2,)) for u, n in zip(uv, self.names, strict=True)]
        try:
            stacked = _stack_views(uv, (2,))
        except ValueError:
            shapes = ", ".join(f"{n} {u.shape}" for n, u in zip(self.names, uv, strict=True))
            raise ValueError(f"image point batch shapes do not broadcast: {shapes}") from None
        return self._triangulate(stacked)

    def reconstruction_covariance(self, points_w, *covs) -> Array:
        """3-D covariance of reconstructed points from the 2-D noise of each view.

        Parameters
        ----------
        points_w : array, shape (..., 3)
            Points in {W} (true or reconstructed), mm.
        *covs : arrays, shape (2, 2) or (..., 2, 2)
            One per view: segmentation-noise covariances in each image, mm^2 (orthographic)
            or px^2 (pinhole); see :func:`isotropic_covariance` for a scalar sigma.
            Independent between the views; may be singular.

        Returns
        -------
        cov_w : array, shape (..., 3, 3)
            Covariance of ``reconstruct``'s output, mm^2, symmetric.

        Notes
        -----
        Every reconstruction is, to first order, the unweighted least-squares solution of
        ``A_v dx = e_v`` over the views v, so ``Sigma = H^-1 (sum_v A_v^T C_v A_v) H^-1``
        with ``H = sum_v A_v^T A_v`` and C_v the covariance of e_v. For a plane e is the
        in-plane error, mm (A = U^T, C the image noise): this is exact and equals
        ``M blockdiag(C_1, ..., C_n) M^T`` with M the :meth:`reconstruction_matrix`, which is
        how it is computed. For a camera the linear triangulation minimises
        ``Z (m - x_cam[:2] / Z)``: the offset in the fronto-parallel plane at the point's
        depth, mm, ``L^-1 dp`` for a pixel error dp, L the lateral block of the projection
        Jacobian ``J = d pixel / d x_cam``. As ``J = K_2 D [I | -n] / Z`` (n = x_cam[:2] / Z,
        D the distortion's Jacobian, K_2 the focal lengths), ``L^-1 J = [I | -n]``: A is
        ``[I | -n] R_cam_w`` whatever the distortion, and ``L^-1 = Z K_2^-1`` without
        distortion (OpenCV's Jacobian is needed only for the noise of a distorted camera).
        This is first order in the noise; it equals ``(J^T W J)^-1`` (J the stacked pixel
        Jacobians, W the inverse noise covariance, i.e. the bound of the optimal estimator)
        only when the noise is the same in every view in the sense of the lateral error, and
        is never smaller.
        """
        if len(covs) != len(self.views):
            raise ValueError(f"expected covariances for {len(self.views)} views, got {len(covs)}")
        x = _checked(points_w, "points_w", (3,))
        covs = [_covariance(c, f"cov_{n}") for c, n in zip(covs, self.names, strict=True)]
        return self._propagate(x, _stack_views(covs, (2, 2)))

    def reconstruct_with_covariance(self, uv, cov) -> tuple[Array, Array]:
        """:meth:`reconstruct`, then :meth:`reconstruction_covariance` of the points, from
        the views' image points and noise stacked view by view (the live loop's path: one
        check and one vectorised computation for all views).

        Parameters
        ----------
        uv : array, shape (..., n_views, 2)
            Image points of every view, in the rig's order.
        cov : array, shape (..., n_views, 2, 2)
            Their noise covariances (each view checked against its own scale, as
            :meth:`reconstruction_covariance` does).

        Returns
        -------
        points_w : array, shape (..., 3)
        cov_w : array, shape (..., 3, 3)
        """
        n_views = len(self.views)
        uv = _checked(uv, "uv", (n_views, 2))
        cov = _checked(cov, "cov", (n_views, 2, 2))
        scale = np.abs(cov).max(axis=(*range(cov.ndim - 3), -2, -1), initial=1e-300)  # per view
        if _covariance_problem(cov, scale) is not None:
            for v, name in enumerate(self.names):  # raises for the first bad view
                _covariance(cov[..., v, :, :], f"cov_{name}")
        points_w = self._triangulate(uv)
        return points_w, self._propagate(points_w, cov)

    def _triangulate(self, uv: Array) -> Array:
        """Points (..., 3) in {W} from checked image points (..., V, 2) of every view."""
        batch = uv.shape[:-2]
        if self._M is not None:
            return uv.reshape(batch + (-1,)) @ self._M.T
        cams = self._cameras
        if not cams.distorted:
            # One compiled call (the same arithmetic as below, point by point).
            V = len(self.views)
            points, parallel = _imaging_kernels.triangulate(
                np.array(uv.reshape(-1, V, 2), dtype=float, order="C"), cams.principal, cams.focal,
                cams.R_cam_w, cams.t_cam_w,
            )  # fmt: skip
            if parallel.any():
                raise ValueError(_PARALLEL.format(np.count_nonzero(parallel)))
            return points.reshape(batch + (3,))
        uv = uv.copy()
        for v in cams.distorted:
            uv[..., v, :] = self.views[v].undistort(uv[..., v, :])
        m = (uv - cams.principal) / cams.focal  # normalised coordinates
        # x_cam[:2] = m x_cam[2] is linear in x: (m r_3 - R_12) x = t_12 - m t_3, two rows of
        # A x = b per view.
        A = (m[..., None] * cams.r_3 - cams.R_12).reshape(batch + (-1, 3))
        b = (cams.t_12 - m * cams.t_3).reshape(batch + (-1,))
        U, s, Vt = np.linalg.svd(A, full_matrices=False)
        parallel = s[..., -1] <= 1e-12 * s[..., 0]
        if parallel.any():
            raise ValueError(_PARALLEL.format(np.count_nonzero(parallel)))
        y = (U.mT @ b[..., None])[..., 0] / s
        return (Vt.mT @ y[..., None])[..., 0]

    def _propagate(self, x: Array, cov: Array) -> Array:
        """Covariances (..., 3, 3) of the reconstruction of checked points (..., 3) from the
        checked noise covariances (..., V, 2, 2) of every view (the Notes of
        :meth:`reconstruction_covariance`)."""
        if self._M is not None:
            M_v = self._M_views
            cov_w = np.zeros(x.shape[:-1] + (3, 3)) + (M_v @ cov @ M_v.mT).sum(axis=-3)
        elif not self._cameras.distorted:
            # One compiled call (the same arithmetic as below, point by point).
            cams, V = self._cameras, len(self.views)
            batch = np.broadcast_shapes(x.shape[:-1], cov.shape[:-3])
            cov_w, behind = _imaging_kernels.propagate(
                np.array(np.broadcast_to(x, batch + (3,)).reshape(-1, 3), dtype=float,
                         order="C"),
                np.array(np.broadcast_to(cov, batch + (V, 2, 2)).reshape(-1, V, 2, 2),
                         dtype=float, order="C"),
                cams.R_cam_w, cams.t_cam_w, cams.inverse_focal,
            )  # fmt: skip
            if behind.any():
                x_cam = (x[..., None, None, :] @ cams.R_cam_w.mT)[..., 0, :] + cams.t_cam_w
                for v in range(V):  # raises for the first view concerned
                    _check_in_front(x_cam[..., v, 2])
            return cov_w.reshape(batch + (3, 3))
        else:
            cams = self._cameras
            x_cam = (x[..., None, None, :] @ cams.R_cam_w.mT)[..., 0, :] + cams.t_cam_w
            depth = x_cam[..., 2:]  # (..., V, 1)
            if (depth <= 0.0).any():
                for v in range(len(self.views)):  # raises for the first view concerned
                    _check_in_front(depth[..., v, 0])
            n = x_cam[..., :2] / depth
            A = cams.R_12 - n[..., None] * cams.r_3  # [I | -n] R_cam_w, (..., V, 2, 3)
            L_inv = depth[..., None] * cams.inverse_focal
            for v in cams.distorted:
                L_inv[..., v, :, :] = np.linalg.inv(self.views[v]._project(x)[1][..., :2])
            C = L_inv @ cov @ L_inv.mT  # of the lateral errors, mm^2
            H = (A.mT @ A).sum(axis=-3)
            N = (A.mT @ C @ A).sum(axis=-3)
            H_inv = np.linalg.inv(H)  # H, N symmetric: H^-1 N H^-1 = solve(H, solve(H, N)^T)
            cov_w = H_inv @ N @ H_inv
        return 0.5 * (cov_w + cov_w.mT)


# -------------------------------------------------------------------------------- defaults
def _rig_of(views, names) -> Rig:
    """A Rig of views and names (what a pickled Rig is rebuilt from)."""
    return Rig(*views, names=names)


def default_orthographic_rig() -> Rig:
    """Front (AP) plane with normal -y and side (lateral) plane with normal +x; v = world z.

    The normals point toward the viewers of :func:`default_pinhole_rig`, so both default rigs
    show the same images up to scale and the flip of v (image rows grow downward).
    Front: u = world x; side: u = world y.
    """
    return Rig(
        OrthographicPlane.from_normal([0.0, -1.0, 0.0]),
        OrthographicPlane.from_normal([1.0, 0.0, 0.0]),
    )


def default_pinhole_rig(distance_mm: float = 400.0, focal_px: float = 1000.0) -> Rig:
    """Two undistorted 640x480 cameras aimed at the origin from -y (front) and +x (side).

    Parameters
    ----------
    distance_mm : float
        Distance of each optical centre from the world origin, mm.
    focal_px : float
        Focal length of both cameras, px. Image up is world z.
    """
    d = float(_checked(distance_mm, "distance_mm", (), False))
    if d <= 0.0:
        raise ValueError(f"distance_mm must be positive, got {distance_mm}")
    origin, up = np.zeros(3), np.array([0.0, 0.0, 1.0])
    return Rig(
        PinholeView.look_at([0.0, -d, 0.0], origin, up, focal_px),
        PinholeView.look_at([d, 0.0, 0.0], origin, up, focal_px),
    )
