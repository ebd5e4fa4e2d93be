"""The photometric fit of a frame to its background, compiled (numba; docs/vision.md section 4).

:func:`fit` is the whole numeric body of :func:`tracker.vision.photometry.fit_photometry` in
one call, run for every view of every frame: the frame on the fit's grid of a few thousand
pixels and its histogram over the background's gray levels, the choice of the tone curve's
degree, the least-squares tone curve (its normal equations summed over the 256 gray levels,
solved by Cramer's rule), the residual and its robust gate, the second fit without the
pixels beyond the gate, the noise, the first-order shift, the slope and the black level
(before: four compiled calls with some forty numpy and Python steps between them, 2.5 times
the time).

The arithmetic is written as the numpy and Python steps it replaces did it (same operations
in the same order, the same singularity thresholds), so the decisions taken (the pixels
usable, the degree, the gate, the pixels beyond it, the branches) are the same, and the
sums of integers (the histograms, the mean and spread of the gray levels, a degree-0 fit)
are exact. Only the sums over the 256 gray levels of non-integers (the moments of a fit of
degree 1 or 2, and the tone curve from its coefficients), which numpy left to BLAS, may
differ in their last bits (the order of their terms).

As in :mod:`tracker.vision.kernels`: ``njit(cache=True, nogil=True)``, plain arrays of the
fixed dtypes given in the docstring, and :func:`warm_up` compiles (or loads) the kernel with
the argument types :func:`tracker.vision.photometry.fit_photometry` passes.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from tracker.vision.kernels import _select

# The background's gray level, centred, as the fit's variable, and its powers x^0 ... x^4 at
# every gray level (5, 256): numpy's powers (its own for 0 to 2, pow for 3 and 4), frozen
# into the compiled code as a constant.
_X = np.arange(256, dtype=np.float64) / 255.0 - 0.5
_POWERS = np.stack([_X**k for k in range(5)])


@numba.njit(cache=True, nogil=True)
def _solve_2(a, b, d, p, q):
    """``[[a, b], [b, d]] x = (p, q)`` by Cramer's rule; zeros when singular (a pivot of the
    Gaussian elimination, a ratio of leading minors, at most 1e-12)."""
    det = a * d - b * b
    if not (a > 1e-12 and det > 1e-12 * a):
        return 0.0, 0.0
    return (d * p - b * q) / det, (a * q - b * p) / det


@numba.njit(cache=True, nogil=True)
def _tone_curve(counts, sums, degree, lut):
    """The least-squares tone curve of ``degree`` (0, 1 or 2) at every gray level into
    ``lut`` (float64 (256,)), from the per-level pixel counts and sums of the frame's gray
    levels (float64 (256,) each): the normal equations are sums over the levels,
    ``sum_b counts(b) x(b)^(i + j)``. A singular system gives zeros."""
    if degree == 0:
        # Through the origin: a gain alone (sums of integers, exact in any order).
        num = 0.0
        den = 0.0
        for b in range(256):
            num += sums[b] * np.float64(b)
            den += counts[b] * np.float64(b * b)
        scale = num / max(den, 1e-12)
        for b in range(256):
            lut[b] = scale * np.float64(b)
        return
    m0 = m1 = m2 = m3 = m4 = 0.0
    v0 = v1 = v2 = 0.0
    for b in range(256):
        c = counts[b]
        s = sums[b]
        m0 += _POWERS[0, b] * c
        m1 += _POWERS[1, b] * c
        m2 += _POWERS[2, b] * c
        v0 += _POWERS[0, b] * s
        v1 += _POWERS[1, b] * s
        if degree == 2:
            m3 += _POWERS[3, b] * c
            m4 += _POWERS[4, b] * c
            v2 += _POWERS[2, b] * s
    if degree == 1:
        c0, c1 = _solve_2(m0, m1, m2, v0, v1)
        for b in range(256):
            lut[b] = c0 * _POWERS[0, b] + c1 * _POWERS[1, b]
        return
    # The adjugate (cofactors) of [[m0, m1, m2], [m1, m2, m3], [m2, m3, m4]].
    a, b_, c, d, e, f = m0, m1, m2, m2, m3, m4
    A, B, C = d * f - e * e, c * e - b_ * f, b_ * e - c * d
    D, E, F = a * f - c * c, b_ * c - a * e, a * d - b_ * b_
    det = a * A + b_ * B + c * C
    c0 = c1 = c2 = 0.0
    if a > 1e-12 and F > 1e-12 * a and det > 1e-12 * F:
        c0 = (A * v0 + B * v1 + C * v2) / det
        c1 = (B * v0 + D * v1 + E * v2) / det
        c2 = (C * v0 + E * v1 + F * v2) / det
    for b in range(256):
        lut[b] = c0 * _POWERS[0, b] + c1 * _POWERS[1, b] + c2 * _POWERS[2, b]


@numba.njit(cache=True, nogil=True)
def _residuals(frame, level, lut, gate, residual, out):
    """``residual = frame - lut[level]`` and ``out = |residual| > gate`` (into the arrays
    given), with ``gate`` NaN for ``max(4 x 1.4826 x median |residual|, 2)`` (the upper
    median). Returns the gate and the number of pixels beyond it."""
    n = frame.size
    for i in range(n):
        residual[i] = frame[i] - lut[level[i]]
    if math.isnan(gate):
        k = n // 2
        gate = max(4.0 * 1.4826 * _select(np.abs(residual), k), 2.0)
    n_out = 0
    for i in range(n):
        out[i] = abs(residual[i]) > gate
        n_out += out[i]
    return gate, n_out


@numba.njit(cache=True, nogil=True)
def fit(image, rows, cols, levels, usable_levels, gradient, normalise, fit_shift, min_samples):
    """The frame's tone curve, noise and first-order shift against its background.

    Parameters
    ----------
    image : uint8 array (h, w)
    rows, cols : (start, stop, step) tuples of ints
        The grid (rows, then columns within a row: the order of ``levels``).
    levels : uint8 array (m,)
        The background's gray levels on the grid.
    usable_levels : bool array (m,)
        The background is neither black nor saturated there.
    gradient : float64 array (2, m)
        The background's central differences on the grid (twice its gradient), x and y.
    normalise, fit_shift : bool
        Fit the tone curve (otherwise it is the identity); fit the shift (otherwise zero).
    min_samples : int
        Fewer pixels usable in both images than this: nothing is fitted.

    Returns
    -------
    n : int
        The grid's pixels neither black nor saturated in either image; when fewer than
        ``min_samples`` the rest is the identity, zeros and NaN.
    lut : float64 (256,)
        The tone curve at every background gray level, made non-decreasing.
    shift_x, shift_y, sigma, gain, dark : float
        As :class:`tracker.vision.photometry.Photometry` has them.
    degree : int
        The tone curve's degree (0, 1 or 2; -1 for the identity).
    """
    m = levels.size
    frame = np.empty(m)
    level = np.empty(m, np.uint8)
    grid = np.empty(m, np.intp)  # each usable pixel's place on the grid
    counts = np.zeros(256)
    sums = np.zeros(256)
    lut = np.arange(256).astype(np.float64)
    i = 0
    n = 0
    for r in range(rows[0], rows[1], rows[2]):
        for c in range(cols[0], cols[1], cols[2]):
            f = image[r, c]
            if 0 < f < 255 and usable_levels[i]:
                b = levels[i]
                frame[n] = f
                level[n] = b
                grid[n] = i
                counts[b] += 1.0
                sums[b] += np.float64(f)
                n += 1
            i += 1
    if n < min_samples:
        return n, lut, 0.0, 0.0, math.nan, 0.0, 0.0, -1
    frame = frame[:n]
    level = level[:n]
    # Sums of integers: exact, in any order.
    total = 0.0
    total_sq = 0.0
    for b in range(256):
        total += counts[b] * np.float64(b)
        total_sq += counts[b] * np.float64(b * b)
    mean_level = total / n
    degree = -1
    if normalise:
        # A curvature needs a spread of gray levels, an offset at least two of them.
        spread = math.sqrt(max(total_sq / n - mean_level**2, 0.0))
        degree = 2 if spread >= 12.0 else (1 if spread >= 3.0 else 0)
        _tone_curve(counts, sums, degree, lut)
    residual = np.empty(n)
    out = np.empty(n, np.bool_)
    gate, n_out = _residuals(frame, level, lut, math.nan, residual, out)
    if normalise and n_out > 0:
        # Again without the pixels beyond the gate (the catheter, occluders).
        for k in range(n):
            if out[k]:
                counts[level[k]] -= 1.0
                sums[level[k]] -= frame[k]
        _tone_curve(counts, sums, degree, lut)
        _, n_out = _residuals(frame, level, lut, gate, residual, out)
    # The noise, and the normal equations of the shift on the pixels within the gate.
    squares = 0.0
    g00 = g01 = g11 = 0.0
    o00 = o01 = o11 = 0.0
    r0 = r1 = 0.0
    for k in range(n):
        j = grid[k]
        gx = gradient[0, j]
        gy = gradient[1, j]
        g00 += gx * gx
        g01 += gx * gy
        g11 += gy * gy
        if out[k]:
            o00 += gx * gx
            o01 += gx * gy
            o11 += gy * gy
        else:
            rk = residual[k]
            squares += rk * rk
            r0 += gx * rk
            r1 += gy * rk
    g00 -= o00
    g01 -= o01
    g11 -= o11
    n_in = n - n_out
    sigma = math.sqrt(squares / n_in) if n_in > 10 else gate / 4.0
    # The slope of the tone curve at the background's mean gray level.
    at_level = min(max(round(mean_level), 1), 254)
    at = lut[at_level]
    gain = 0.5 * (lut[at_level + 1] - lut[at_level - 1])
    shift_x = shift_y = 0.0
    if fit_shift and abs(gain) > 1e-6:
        # frame(p) = f(bg(p - d)) ~ f(bg(p)) - f' grad(bg) . d on the inliers; central
        # differences are twice the gradient.
        d0, d1 = _solve_2(g00, g01, g11, r0, r1)
        shift_x = -2.0 * d0 / gain
        shift_y = -2.0 * d1 / gain
    # The black level, within a quarter of f at the mean level. An offset of the frame does
    # not scale with the light: contrasts are fractions of f(b) - f(0). (A gamma has no
    # black level; f(0) of its fitted curve is the intercept of the curve's chord over the
    # background's levels, which keeps contrasts to first order.)
    bound = 0.25 * abs(at)
    dark = min(max(lut[0], -bound), bound) if normalise else 0.0
    for b in range(1, 256):
        lut[b] = max(lut[b], lut[b - 1])
    return n, lut, shift_x, shift_y, sigma, gain, dark, degree


def warm_up() -> None:
    """Compile (or load) :func:`fit` on a tiny input, with the argument types
    :func:`tracker.vision.photometry.fit_photometry` passes."""
    background = np.full((8, 8), 100, np.uint8)
    background[:, ::2] = 120
    grid = (1, 7, 2)
    levels = background[1:7:2, 1:7:2].ravel()
    gradient = np.zeros((2, levels.size))
    fit(background + 5, grid, grid, levels, levels > 0, gradient, True, True, 2)
