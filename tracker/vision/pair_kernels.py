"""The cross-view steps of a synchronised frame, compiled (numba; :mod:`tracker.vision.pair`).

:func:`tracker.vision.pair.combine_views` runs once per frame of the live loop, between the
views' segmentations and the reconstruction. Its arithmetic is a few points in two or three
views; written with numpy and OpenCV it was nearly all the cost of calling their routines (a
full Jacobian with every ``cv2.projectPoints``). Here it is two compiled calls:

- :func:`check_rows`: the frame's rows of every view (NaN where a point is missing), the
  epipolar check of every row seen in two or more views (triangulated from those views,
  reprojected into them, withheld where a reprojection misses its point by more than the
  gate) and, where two or more views see the tip band, the linear maps of the search of the
  tangent at the tip (:func:`tracker.vision.kernels.tip_tangent`, called in between from
  Python: a compiled caller would keep a stale copy of it in its cache);
- :func:`place_tip`: the tip half a band from the band's centre along that tangent, in every
  view that sees the band.

The arithmetic is that of what it replaces, operation for operation where that decides a
result: :meth:`models.imaging.Rig.reconstruct` (OpenCV's iterative undistortion,
``cv2.undistortPoints`` with the criteria of :meth:`models.imaging.PinholeView.undistort`,
then the least-squares triangulation of ``models._imaging_kernels.triangulate``) and
:meth:`models.imaging.PinholeView.project` (``cv2.projectPoints``: the rotation of the
camera's Rodrigues vector, the distortion model k1, k2, p1, p2, k3). The results agree with
the numpy and OpenCV ones to round-off (tests/tracker/test_combine_views.py).

The kernels follow the conventions of :mod:`tracker.vision.kernels`: ``njit(cache=True,
nogil=True)``, plain arrays of the dtypes given in each docstring (the camera arrays
read-only), and :func:`warm_up` compiles or loads them before the first frame.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from models._imaging_kernels import distorted_pixel as _distorted_pixel

# Rows of a view's tip band data (``band`` below), each of two numbers.
BAND_PX, BAND_DIRECTION, BAND_EXTENT_RADIUS, BAND_COV = 0, 1, 2, 3
BAND_ROWS = 5  # the covariance takes rows 3 and 4

# What check_rows finds wrong (0: nothing).
OK, PARALLEL_RAYS, BEHIND_CAMERA = 0, 1, 2

# OpenCV's criteria of models.imaging.PinholeView.undistort: 100 iterations or 1e-10 px.
_UNDISTORT_ITERATIONS = 100
_UNDISTORT_EPS_PX = 1e-10


@numba.njit(cache=True, nogil=True)
def _undistort(u, v, intrinsics, k):
    """The ideal pixel (distortion removed, in the px of K) of an observed one: OpenCV's
    ``undistortPoints`` with ``P = K`` (no tilt, no thin-prism or rational terms), step for
    step."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    ifx = 1.0 / fx
    ify = 1.0 / fy
    x0 = x = (u - cx) * ifx
    y0 = y = (v - cy) * ify
    error = np.inf
    for _ in range(_UNDISTORT_ITERATIONS):
        if error < _UNDISTORT_EPS_PX:
            break
        r2 = x * x + y * y
        icdist = 1.0 / (1.0 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2)
        if icdist < 0.0:
            x = (u - cx) * ifx
            y = (v - cy) * ify
            break
        delta_x = 2.0 * k[2] * x * y + k[3] * (r2 + 2.0 * x * x)
        delta_y = k[2] * (r2 + 2.0 * y * y) + 2.0 * k[3] * x * y
        x = (x0 - delta_x) * icdist
        y = (y0 - delta_y) * icdist
        r2 = x * x + y * y
        cdist = 1.0 + k[0] * r2 + k[1] * (r2 * r2) + k[4] * (r2 * r2 * r2)
        xd = x * cdist + k[2] * (2.0 * x * y) + k[3] * (r2 + 2.0 * x * x)
        yd = y * cdist + k[2] * (r2 + 2.0 * y * y) + k[3] * (2.0 * x * y)
        du = xd * fx + cx - u
        dv = yd * fy + cy - v
        error = math.sqrt(du * du + dv * dv)
    return fx * x + cx, fy * y + cy


@numba.njit(cache=True, nogil=True)
def _project(R, t, intrinsics, k, x0, x1, x2):
    """The pixel (u, v) of a world point, mm, as ``cv2.projectPoints`` computes it (R the
    rotation of the camera's Rodrigues vector)."""
    X = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2 + t[0]
    Y = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2 + t[1]
    Z = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2 + t[2]
    return _distorted_pixel(X, Y, Z, intrinsics, k)


@numba.njit(cache=True, nogil=True)
def _depth(R_cam_w, t_cam_w, x0, x1, x2):
    """A world point's depth along the camera's optical axis, mm."""
    return R_cam_w[2, 0] * x0 + R_cam_w[2, 1] * x1 + R_cam_w[2, 2] * x2 + t_cam_w[2]


@numba.njit(cache=True, nogil=True)
def _triangulate(ideal, row, seen, n_seen, intrinsics, R_cam_w, t_cam_w, out):
    """The least-squares point (into ``out`` (3,)) of the DLT equations of the views
    ``seen[:n_seen]`` for one row of ideal pixels ``ideal`` (V, R, 2); False if their rays
    are parallel."""
    A = np.empty((2 * n_seen, 3))
    b = np.empty(2 * n_seen)
    for i in range(n_seen):
        v = seen[i]
        for a in range(2):
            m = (ideal[v, row, a] - intrinsics[v, 2 + a]) / intrinsics[v, a]
            for j in range(3):
                A[2 * i + a, j] = m * R_cam_w[v, 2, j] - R_cam_w[v, a, j]
            b[2 * i + a] = t_cam_w[v, a] - m * t_cam_w[v, 2]
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    if s[2] <= 1e-12 * s[0]:
        return False
    y = np.empty(3)
    for k in range(3):
        total = 0.0
        for i in range(2 * n_seen):
            total += U[i, k] * b[i]
        y[k] = total / s[k]
    for j in range(3):
        total = 0.0
        for k in range(3):
            total += Vt[k, j] * y[k]
        out[j] = total
    return True


@numba.njit(cache=True, nogil=True)
def check_rows(uv, cov, found, band, R_cam_w, t_cam_w, R_project, intrinsics, dist, gate_px,
               half_band_mm, nudge_mm):  # fmt: skip
    """The frame's rows of every view, checked across the views; the tip band's geometry.

    Parameters
    ----------
    uv : float64 (V, R, 2)
        Each view's rows ``[tip, marker_0, ...]``, px; rows not found are set to NaN here.
    cov : float64 (V, R, 2, 2)
        Their covariances, px^2; NaN where ``uv`` is.
    found : bool (V + 1, R)
        Rows 0 .. V - 1: each view's markers found (column 0 is not read: the tip is found
        where it is finite); row V: the rows that are the tip (the tip and any marker there).
    band : float64 (V, 5, 2)
        Each view's tip band: its centroid (row :data:`BAND_PX`, NaN if not found), the
        image direction at the tip (:data:`BAND_DIRECTION`), the extent past the centroid
        and the tube's image radius (:data:`BAND_EXTENT_RADIUS`), its covariance (rows 3, 4).
    R_cam_w, t_cam_w : read-only float64 (V, 3, 3), (V, 3)
        The cameras' poses.
    R_project : read-only float64 (V, 3, 3)
        The rotations OpenCV projects with (of the Rodrigues vectors of ``R_cam_w``).
    intrinsics, dist : read-only float64 (V, 4), (V, 5)
        fx, fy, cx, cy, px; the distortion coefficients k1, k2, p1, p2, k3.
    gate_px, half_band_mm, nudge_mm : float
        The epipolar gate; half the band's length; the step of the finite-difference
        projection Jacobians at the band's centre.

    Every row seen in two or more views (the tip rows by the band centroids where two or
    more views see the band) is triangulated from those views and reprojected; it is
    rejected when a reprojection misses its point by more than the gate or four times the
    spread of the points (the root of the sum of the traces of their covariances; 0 if one
    is missing). Rejected rows are set to NaN in every view.

    Returns
    -------
    status : int
        :data:`OK`, :data:`PARALLEL_RAYS` or :data:`BEHIND_CAMERA` (a point triangulated at
        or behind a camera); the other results are then incomplete.
    rejected : bool (R,)
    refined : bool
        Two or more views see the tip band, its row is not rejected and every such view's
        extent and radius are finite: the tip is to be placed (:func:`place_tip`).
    centre_w : float64 (3,)
        The band's centre in {W}, mm (NaN unless its row was triangulated).
    geometry : float64 (V, 2, 4)
        Per view, for rows u and v: the projection Jacobian at the centre (columns 0-2,
        px/mm, finite differences) and the centre's pixel (column 3).
    linear, extent, cap_px : float64 (4 n, 3), (n,), (n,)
        The arguments of :func:`tracker.vision.kernels.tip_tangent` for the n views that see
        the band (empty unless refined).
    """
    V, R = uv.shape[0], uv.shape[1]
    for v in range(V):
        for r in range(R):
            if r == 0:
                missing = not (math.isfinite(uv[v, 0, 0]) and math.isfinite(uv[v, 0, 1]))
            else:
                missing = not found[v, r]
            if missing:
                uv[v, r, :] = np.nan
                cov[v, r, :, :] = np.nan
    banded = np.zeros(V, dtype=np.bool_)
    n_banded = 0
    for v in range(V):
        if math.isfinite(band[v, BAND_PX, 0]) and math.isfinite(band[v, BAND_PX, 1]):
            banded[v] = True
            n_banded += 1
    # The points checked: each row's own; the tip's by the band centroids where two or more
    # views see the band (a far end is half a band from a band's centre).
    check = uv.copy()
    if n_banded >= 2:
        for r in range(R):
            if found[V, r]:
                for v in range(V):
                    for a in range(2):
                        check[v, r, a] = band[v, BAND_PX, a] if banded[v] else np.nan
    # The ideal (undistorted) pixels the views' rays go through.
    ideal = check
    copied = False
    for v in range(V):
        distorted = False
        for i in range(5):
            distorted = distorted or dist[v, i] != 0.0
        if distorted:
            if not copied:
                ideal = check.copy()
                copied = True
            for r in range(R):
                if math.isfinite(check[v, r, 0]) and math.isfinite(check[v, r, 1]):
                    ideal[v, r, 0], ideal[v, r, 1] = _undistort(
                        check[v, r, 0], check[v, r, 1], intrinsics[v], dist[v]
                    )
    rejected = np.zeros(R, dtype=np.bool_)
    centre_w = np.full(3, np.nan)
    geometry = np.full((V, 2, 4), np.nan)
    empty, none = np.empty((0, 3)), np.empty(0)
    seen = np.empty(V, dtype=np.int64)
    x = np.empty(3)
    nudged = np.empty((4, 2))
    for r in range(R):
        n_seen = 0
        for v in range(V):
            if math.isfinite(check[v, r, 0]) and math.isfinite(check[v, r, 1]):
                seen[n_seen] = v
                n_seen += 1
        if n_seen < 2:
            continue
        if not _triangulate(ideal, r, seen, n_seen, intrinsics, R_cam_w, t_cam_w, x):
            return PARALLEL_RAYS, rejected, False, centre_w, geometry, empty, none, none
        residual = 0.0
        variance = 0.0
        for i in range(n_seen):
            v = seen[i]
            if not _depth(R_cam_w[v], t_cam_w[v], x[0], x[1], x[2]) > 0.0:
                return BEHIND_CAMERA, rejected, False, centre_w, geometry, empty, none, none
            pu, pv = _project(R_project[v], t_cam_w[v], intrinsics[v], dist[v], x[0], x[1], x[2])
            du = pu - check[v, r, 0]
            dv = pv - check[v, r, 1]
            residual = max(residual, math.sqrt(du * du + dv * dv))
            variance += cov[v, r, 0, 0] + cov[v, r, 1, 1]
            if r == 0:
                # The centre and three nudged copies: the projection Jacobian there.
                nudged[0, 0], nudged[0, 1] = pu, pv
                for j in range(3):
                    y0 = x[0] + (nudge_mm if j == 0 else 0.0)
                    y1 = x[1] + (nudge_mm if j == 1 else 0.0)
                    y2 = x[2] + (nudge_mm if j == 2 else 0.0)
                    if not _depth(R_cam_w[v], t_cam_w[v], y0, y1, y2) > 0.0:
                        return (BEHIND_CAMERA, rejected, False, centre_w, geometry, empty,
                                none, none)  # fmt: skip
                    nudged[j + 1, 0], nudged[j + 1, 1] = _project(
                        R_project[v], t_cam_w[v], intrinsics[v], dist[v], y0, y1, y2
                    )
                for a in range(2):
                    for j in range(3):
                        geometry[v, a, j] = (nudged[j + 1, a] - nudged[0, a]) / nudge_mm
                    geometry[v, a, 3] = nudged[0, a]
        if r == 0:
            centre_w[:] = x
        spread = math.sqrt(variance) if math.isfinite(variance) else 0.0
        limit = 4.0 * spread
        if not limit > gate_px:
            limit = gate_px
        rejected[r] = residual > limit
    for r in range(R):
        if rejected[r]:
            for v in range(V):
                uv[v, r, :] = np.nan
                cov[v, r, :, :] = np.nan
    refined = n_banded >= 2 and not rejected[0]
    for v in range(V):
        if banded[v] and not math.isfinite(
            band[v, BAND_EXTENT_RADIUS, 0] * band[v, BAND_EXTENT_RADIUS, 1]
        ):
            refined = False
    if not refined:
        return OK, rejected, False, centre_w, geometry, empty, none, none
    # For directions T (columns), linear @ T is, per view (in rows): p's x and y (the image
    # vector of half a band along T), p's part along the measured direction, and sin a (T's
    # part along the viewing ray).
    n = n_banded
    linear = np.empty((4 * n, 3))
    extent = np.empty(n)
    cap_px = np.empty(n)
    i = 0
    for v in range(V):
        if not banded[v]:
            continue
        d0, d1 = band[v, BAND_DIRECTION, 0], band[v, BAND_DIRECTION, 1]
        for j in range(3):
            a = half_band_mm * geometry[v, 0, j]
            b = half_band_mm * geometry[v, 1, j]
            linear[i, j] = a
            linear[n + i, j] = b
            linear[2 * n + i, j] = d0 * a + d1 * b
        ray = np.empty(3)
        for k in range(3):
            ray[k] = (R_cam_w[v, k, 0] * centre_w[0] + R_cam_w[v, k, 1] * centre_w[1]
                      + R_cam_w[v, k, 2] * centre_w[2]) + t_cam_w[v, k]  # fmt: skip
        norm = math.sqrt(ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2])
        for j in range(3):
            total = 0.0
            for k in range(3):
                total += (ray[k] / norm) * R_cam_w[v, k, j]
            linear[3 * n + i, j] = total
        extent[i] = band[v, BAND_EXTENT_RADIUS, 0]
        cap_px[i] = 0.25 * math.pi * band[v, BAND_EXTENT_RADIUS, 1]
        i += 1
    return OK, rejected, True, centre_w, geometry, linear, extent, cap_px


@numba.njit(cache=True, nogil=True)
def place_tip(uv, cov, found, band, rejected, centre_w, geometry, tangent, misfit, half_band_mm,
              direction_sigma_rad):  # fmt: skip
    """The tip half a band from the band's centre along ``tangent``, into the tip rows of
    ``uv`` and ``cov`` of every view that sees the band (rejected rows are left NaN).

    The arguments are those of :func:`check_rows` and its results, with the tangent (3,)
    and misfit (px^2) of :func:`tracker.vision.kernels.tip_tangent`. Each view's tip is the
    centre's pixel plus the projection Jacobian times the offset (first order is exact to
    far below a pixel half a band away); its covariance is the band's plus, isotropic, the
    tangent's uncertainty (``half band * px/mm * direction_sigma_rad``, squared) and half
    the misfit (what the views disagree on: 2 residuals per view for 2 unknowns).
    """
    V, R = uv.shape[0], uv.shape[1]
    offset = np.empty(3)
    for j in range(3):
        offset[j] = (centre_w[j] + half_band_mm * tangent[j]) - centre_w[j]
    for v in range(V):
        if not (math.isfinite(band[v, BAND_PX, 0]) and math.isfinite(band[v, BAND_PX, 1])):
            continue
        J = geometry[v]
        px_per_mm_sq = 0.0
        for a in range(2):
            px_per_mm_sq = max(px_per_mm_sq, J[a, 0] * J[a, 0] + J[a, 1] * J[a, 1]
                               + J[a, 2] * J[a, 2])  # fmt: skip
        sigma_px = half_band_mm * math.sqrt(px_per_mm_sq) * direction_sigma_rad
        extra = sigma_px * sigma_px + 0.5 * misfit
        tip_u = J[0, 3] + (J[0, 0] * offset[0] + J[0, 1] * offset[1] + J[0, 2] * offset[2])
        tip_v = J[1, 3] + (J[1, 0] * offset[0] + J[1, 1] * offset[1] + J[1, 2] * offset[2])
        for r in range(R):
            if not found[V, r] or rejected[r]:
                continue
            uv[v, r, 0] = tip_u
            uv[v, r, 1] = tip_v
            for a in range(2):
                for c in range(2):
                    cov[v, r, a, c] = band[v, BAND_COV + a, c] + (extra if a == c else 0.0)


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) the kernels once per process, with the types
    :func:`tracker.vision.pair.combine_views` passes (the camera arrays are read-only)."""

    def frozen(a):
        a.flags.writeable = False
        return a

    # Two cameras 90 degrees apart, 400 mm from the origin, the first one distorted.
    R = frozen(np.array([np.eye(3), [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]]))
    t = frozen(np.array([[0.0, 0.0, 400.0], [0.0, 0.0, 400.0]]))
    intrinsics = frozen(np.array([[1000.0, 1000.0, 320.0, 240.0]] * 2))
    dist = frozen(np.array([[0.1, 0.0, 0.0, 0.0, 0.0], [0.0] * 5]))
    uv = np.full((2, 2, 2), 320.0)
    cov = np.ones((2, 2, 2, 2))
    found = np.ones((3, 2), dtype=np.bool_)
    band = np.full((2, BAND_ROWS, 2), 320.0)
    _, rejected, _, centre_w, geometry, *_ = check_rows(
        uv, cov, found, band, R, t, R, intrinsics, dist, 3.0, 0.5, 1e-3
    )
    place_tip(uv, cov, found, band, rejected, centre_w, geometry, np.array([0.0, 0.0, 1.0]),
              1.0, 0.5, 0.03)  # fmt: skip


__all__ = ["check_rows", "place_tip", "warm_up"]
