"""Radio-opaque bands located by a least-squares fit of a local tube-and-band model
(docs/vision.md section 4, "The bands' centres fitted").

A band's contrast-weighted centroid (:func:`tracker.vision.kernels.bands`) weighs every
pixel of the band alike, though only its edges say where it is: the flat inside adds noise
and no information, and the threshold that picks the pixels moves with the noise. At 8 gray
levels of sensor noise it scatters about three times the Cramer-Rao bound of the image. The
fit here uses what the bound does: the contrast of every pixel near the band (the fraction
of the light it blocks, not clipped at zero), weighted by its noise, against a model of the
catheter there:

- a band: a box of half-length ``h`` and half-width ``r_b`` of contrast ``A_b``;
- the tube on either side of it: boxes of half-widths ``r_1`` (toward the base) and ``r_2``
  (toward the tip; none past a band at the tip) of contrast ``A_t``;
- all along a parabola through the centre ``(c_x, c_y)`` with direction ``theta`` and
  curvature ``kappa`` (the across offset ``v`` of a pixel is measured from the parabola, the
  along offset ``a`` along its tangent), and blurred by a Gaussian of ``sigma``.

A blurred box is a product of differences of the normal CDF across and along, so the model
and its derivatives are closed forms. Nothing in it is the simulator's: widths, contrasts,
blur and curvature are all fitted; the band's centre comes from the symmetry of its outline,
whatever the exact profile across the tube. A few Gauss-Newton steps (Levenberg damped) from
the centroid and the centreline's direction converge; a fit that moves the centre by more
than ``max_move_px`` or ends in nonsense (a width or blur out of range) is dropped and the
centroid kept.

:func:`fit_band` is compiled (numba, as the segmentation's other per-pixel kernels,
:mod:`tracker.vision.kernels`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from tracker.estimators.linalg_kernels import _cholesky_into, _solve_lower

N_PARAMS = 11
"""Parameters of the model: c_x, c_y, theta, kappa, sigma, h, r_b, r_1, r_2, A_b, A_t."""

FIT_FIELDS = 8
"""A row of :func:`fit_band`: ok (1 or 0), c_x, c_y, direction (x, y) of the chord from the
centre to the band's end toward the tip, cov_xx, cov_xy, cov_yy of the centre."""

_ALONG_MARGIN_PX = 2.5
_ACROSS_MARGIN_PX = 2.0
"""The window of the fit: the band's and the tube's outline, past them by these (the blur
is about a pixel), px."""

_SQRT1_2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


# The normal CDF and density tabulated every 1/32 over [-8, 8] with the density's slope:
# a cubic Hermite interpolation of either is exact to 1e-8, a third of the cost of the
# erf and exp it replaces (16 per pixel and step).
_Z_MAX = 8.0
_PER_UNIT = 32.0
_Z = np.linspace(-_Z_MAX, _Z_MAX, int(2 * _Z_MAX * _PER_UNIT) + 1)
_PDF_TABLE = _INV_SQRT_2PI * np.exp(-0.5 * _Z**2)
_CDF_TABLE = np.array([0.5 * (1.0 + math.erf(z * _SQRT1_2)) for z in _Z])
_SLOPE_TABLE = -_Z * _PDF_TABLE
for _table in (_PDF_TABLE, _CDF_TABLE, _SLOPE_TABLE):
    _table.flags.writeable = False
_LAST = _Z.size - 1


@numba.njit(cache=True, nogil=True)
def _normal(z):
    """The standard normal CDF and density at z (tabulated, cubic Hermite)."""
    t = (z + _Z_MAX) * _PER_UNIT
    if t <= 0.0:
        return 0.0, 0.0
    if t >= _LAST:
        return 1.0, 0.0
    i = int(t)
    u = t - i
    u2 = u * u
    w = 1.0 - u
    w2 = w * w
    h00 = (1.0 + 2.0 * u) * w2
    h01 = u2 * (3.0 - 2.0 * u)
    h10 = u * w2 / _PER_UNIT
    h11 = -u2 * w / _PER_UNIT
    f0 = _PDF_TABLE[i]
    f1 = _PDF_TABLE[i + 1]
    cdf = h00 * _CDF_TABLE[i] + h01 * _CDF_TABLE[i + 1] + h10 * f0 + h11 * f1
    pdf = h00 * f0 + h01 * f1 + h10 * _SLOPE_TABLE[i] + h11 * _SLOPE_TABLE[i + 1]
    return cdf, pdf


@numba.njit(cache=True, nogil=True)
def _window(image, background, lut, dark_gray, sigma_gray, cx, cy, ux, uy, along, across):
    """The pixels within ``along`` of (cx, cy) along the unit direction (ux, uy) and within
    ``across`` of it across: x, y, contrast (unclipped) and weight (1 / its noise variance),
    as four float64 arrays."""
    height, width = image.shape
    radius = math.hypot(along, across)
    x_lo = max(int(math.floor(cx - radius)), 0)
    x_hi = min(int(math.ceil(cx + radius)), width - 1)
    y_lo = max(int(math.floor(cy - radius)), 0)
    y_hi = min(int(math.ceil(cy + radius)), height - 1)
    n_max = max(x_hi - x_lo + 1, 0) * max(y_hi - y_lo + 1, 0)
    xs = np.empty(n_max)
    ys = np.empty(n_max)
    w = np.empty(n_max)
    weight = np.empty(n_max)
    n = 0
    for y in range(y_lo, y_hi + 1):
        for x in range(x_lo, x_hi + 1):
            dx = x - cx
            dy = y - cy
            if abs(dx * ux + dy * uy) > along or abs(dy * ux - dx * uy) > across:
                continue
            lit = np.float64(lut[background[y, x]])
            bg = lit - dark_gray
            if bg < 1.0:
                bg = 1.0
            xs[n] = x
            ys[n] = y
            w[n] = (lit - np.float64(image[y, x])) / bg
            weight[n] = (bg / sigma_gray) ** 2
            n += 1
    return xs[:n], ys[:n], w[:n], weight[:n]


@numba.njit(cache=True, nogil=True)
def _model(p, x, y, at_tip, jac):
    """The model's contrast at (x, y) and its gradient over the parameters into ``jac``."""
    return _model_at(p, math.cos(p[2]), math.sin(p[2]), x, y, at_tip, jac)


@numba.njit(cache=True, nogil=True)
def _model_at(p, ct, st, x, y, at_tip, jac):
    """:func:`_model` with the direction's cosine and sine given (the same for every pixel
    of a step)."""
    cx, cy, theta, kappa, sigma, h, rb, r1, r2, ab, at = p
    dx = x - cx
    dy = y - cy
    a = dx * ct + dy * st
    v0 = -dx * st + dy * ct
    v = v0 - 0.5 * kappa * a * a
    inv = 1.0 / sigma
    # Across: the band's and the two tubes' profiles, their derivatives in v, r, sigma.
    zp, zm = (v + rb) * inv, (v - rb) * inv
    cp, fp = _normal(zp)
    cm, fm = _normal(zm)
    pb = cp - cm
    pb_v, pb_r, pb_s = (fp - fm) * inv, (fp + fm) * inv, -(fp * zp - fm * zm) * inv
    zp, zm = (v + r1) * inv, (v - r1) * inv
    cp, fp = _normal(zp)
    cm, fm = _normal(zm)
    p1 = cp - cm
    p1_v, p1_r, p1_s = (fp - fm) * inv, (fp + fm) * inv, -(fp * zp - fm * zm) * inv
    # Along: the band's box [-h, h], the tube before it (a < -h) and after it (a > h).
    z1, z2 = (h - a) * inv, (-h - a) * inv
    c1, f1 = _normal(z1)
    c2, f2 = _normal(z2)
    qb = c1 - c2
    qb_a, qb_h, qb_s = (f2 - f1) * inv, (f1 + f2) * inv, -(f1 * z1 - f2 * z2) * inv
    q1 = c2
    q1_a, q1_h, q1_s = -f2 * inv, -f2 * inv, -f2 * z2 * inv
    m = ab * pb * qb + at * p1 * q1
    m_v = ab * pb_v * qb + at * p1_v * q1
    m_a = ab * pb * qb_a + at * p1 * q1_a
    m_s = ab * (pb_s * qb + pb * qb_s) + at * (p1_s * q1 + p1 * q1_s)
    m_h = ab * pb * qb_h + at * p1 * q1_h
    jac[7] = at * p1_r * q1
    jac[8] = 0.0
    jac[10] = p1 * q1
    if not at_tip:
        zp, zm = (v + r2) * inv, (v - r2) * inv
        cp, fp = _normal(zp)
        cm, fm = _normal(zm)
        p2 = cp - cm
        p2_v, p2_r, p2_s = (fp - fm) * inv, (fp + fm) * inv, -(fp * zp - fm * zm) * inv
        q2 = 1.0 - c1
        q2_a, q2_h, q2_s = f1 * inv, -f1 * inv, f1 * z1 * inv
        m += at * p2 * q2
        m_v += at * p2_v * q2
        m_a += at * p2 * q2_a
        m_s += at * (p2_s * q2 + p2 * q2_s)
        m_h += at * p2 * q2_h
        jac[8] = at * p2_r * q2
        jac[10] += p2 * q2
    # Chain rule to the centre, the direction and the curvature.
    jac[0] = m_a * (-ct) + m_v * (st + kappa * a * ct)
    jac[1] = m_a * (-st) + m_v * (-ct + kappa * a * st)
    jac[2] = m_a * v0 + m_v * (-a - kappa * a * v0)
    jac[3] = m_v * (-0.5 * a * a)
    jac[4] = m_s
    jac[5] = m_h
    jac[6] = ab * pb_r * qb
    jac[9] = pb * qb
    return m


@numba.njit(cache=True, nogil=True)
def fit_band(image, background, lut, dark_gray, sigma_gray, cx, cy, dir_x, dir_y,
             half_length_px, radius_px, at_tip, iterations, max_move_px):
    """The centre of one band by a least-squares fit of the local model (module docstring).

    Parameters
    ----------
    image, background : uint8 arrays (h, w)
    lut : float32 array (256,)
        The frame's tone curve at every background gray level.
    dark_gray, sigma_gray : float
        The frame's black level and noise, gray levels.
    cx, cy : float
        Where to start: the band's centroid, image px.
    dir_x, dir_y : float
        The catheter's unit direction there, toward the tip.
    half_length_px, radius_px : float
        Starting half-length of the band and radius of the tube, px.
    at_tip : bool
        The band ends the catheter (no tube past it).
    iterations : int
        Gauss-Newton steps (3 converge from the centroid).
    max_move_px : float
        A fit whose centre moves farther from the start is dropped.

    Returns
    -------
    float64 (FIT_FIELDS,)
        :data:`FIT_FIELDS`; ok = 0 (and the rest NaN) when the fit was dropped.
    """
    out = np.full(FIT_FIELDS, np.nan)
    out[0] = 0.0
    if not (sigma_gray > 0 and half_length_px > 0 and radius_px > 0):
        return out
    # The band and its outline, and the tube for as long again as the band's outline.
    xs, ys, w, weight = _window(image, background, lut, dark_gray, sigma_gray, cx, cy, dir_x,
                                dir_y, half_length_px + _ALONG_MARGIN_PX,
                                radius_px + _ACROSS_MARGIN_PX)
    n = xs.size
    if n < 2 * N_PARAMS:
        return out
    # Start: the brightest quarter of the window gives the band's contrast.
    peak = 0.0
    for i in range(n):
        peak = max(peak, w[i])
    p = np.array([cx, cy, math.atan2(dir_y, dir_x), 0.0, 1.0, half_length_px, radius_px,
                  radius_px, radius_px, 0.9 * peak, 0.45 * peak])
    jac = np.zeros(N_PARAMS)
    A = np.empty((N_PARAMS, N_PARAMS))
    g = np.empty(N_PARAMS)
    damping = 1e-3
    cost = np.inf
    C = np.empty((N_PARAMS, N_PARAMS))
    L = np.zeros((N_PARAMS, N_PARAMS))
    step = np.empty(N_PARAMS)
    for _ in range(iterations):
        A[:] = 0.0
        g[:] = 0.0
        total = 0.0
        ct, st = math.cos(p[2]), math.sin(p[2])
        for i in range(n):
            r = w[i] - _model_at(p, ct, st, xs[i], ys[i], at_tip, jac)
            wi = weight[i]
            total += wi * r * r
            for j in range(N_PARAMS):
                wj = wi * jac[j]
                g[j] += wj * r
                for k in range(j + 1):
                    A[j, k] += wj * jac[k]
        for j in range(N_PARAMS):
            for k in range(j):
                A[k, j] = A[j, k]
        if at_tip:  # r_2 plays no part
            A[8, :] = 0.0
            A[:, 8] = 0.0
            A[8, 8] = 1.0
            g[8] = 0.0
        cost = total
        # The undamped normal matrix of the last step gives the covariance.
        C[:] = A
        for j in range(N_PARAMS):
            A[j, j] *= 1.0 + damping
        if not _cholesky_into(A, L):
            return out
        step[:] = g
        _solve_lower(L, step)
        for j in range(N_PARAMS):
            p[j] += step[j]
        if not (p[4] > 0.2 and p[5] > 0.0 and p[6] > 0.3 and p[7] > 0.3 and p[8] > 0.3):
            return out
    if not math.isfinite(cost):
        return out
    move = math.hypot(p[0] - cx, p[1] - cy)
    if not move <= max_move_px:
        return out
    # The centre's covariance from the inverse normal matrix of the last step (the step
    # that converged: it hardly moves from there), scaled by the misfit per degree of
    # freedom (unity for a good model).
    if not _cholesky_into(C, L):
        return out
    # Columns 0 and 1 of the inverse: the centre's block.
    e = np.zeros(N_PARAMS)
    e[0] = 1.0
    step[:] = e
    _solve_lower(L, step)
    cxx, cxy = step[0], step[1]
    e[0] = 0.0
    e[1] = 1.0
    step[:] = e
    _solve_lower(L, step)
    cyy = step[1]
    scale = max(cost / max(n - N_PARAMS, 1), 1.0)
    theta, kappa, h = p[2], p[3], p[5]
    ct, st = math.cos(theta), math.sin(theta)
    # The chord from the centre to the band's far end (a = h, v = kappa h^2 / 2).
    ux = ct * h - st * 0.5 * kappa * h * h
    uy = st * h + ct * 0.5 * kappa * h * h
    norm = math.hypot(ux, uy)
    out[0] = 1.0
    out[1] = p[0]
    out[2] = p[1]
    out[3] = ux / norm
    out[4] = uy / norm
    out[5] = cxx * scale
    out[6] = cxy * scale
    out[7] = cyy * scale
    return out


def warm_up() -> None:
    """Compile :func:`fit_band` (or load it from the cache) with the segmentation's types."""
    image = np.full((24, 24), 160, np.uint8)
    image[10:14, 4:20] = 100
    image[10:14, 10:14] = 40
    background = np.full((24, 24), 160, np.uint8)
    lut = np.arange(256, dtype=np.float32)
    for at_tip in (False, True):
        fit_band(image, background, lut, 0.0, 2.0, 11.5, 11.5, 1.0, 0.0, 2.0, 2.0, at_tip, 3,
                 2.0)
