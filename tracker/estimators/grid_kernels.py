"""The grid filter's per-cell arithmetic, compiled (numba): the numbers behind
:class:`~tracker.estimators.grid.GridFilter`, which stays in Python and decides what is done.

The grid holds 2,048 cells and a frame a few groups, so every stage of a step is a pass over
a few (groups, cells) arrays; in numpy each is a dozen calls and as many temporaries. Here
each stage is one compiled loop:

- :func:`group_terms`: per present group, the affine map ``C`` (3, k) from the cell's basis
  ``[cos, sin, 1, expansion_basis(mu)]`` (k = 8; the first 3 without a deviation) to its
  prediction error in the model frame, the group's covariance (noise, the deviation's
  quadratic spread and its linear term at the most probable cell's deviation) and
  ``A = L^-1 C`` with L its Cholesky factor;
- :func:`squared_residuals`: d^2 of every group at every cell, ``|A b|^2``;
- :func:`exponents` and :func:`posterior`: the heavy-tailed likelihood of the frame on every
  cell times the prior, normalised. The exponentials in between are left to numpy, whose
  vectorised ``exp`` is several times faster than the scalar one a loop calls;
- :func:`circular_moments`: the circular mean and the wrapped spread of the posterior;
- :func:`attenuate` and :func:`mix_in_jump`: the predict around the convolution (which stays
  a real FFT in scipy): the wrapped normal's Fourier coefficients; then clip, normalise, mix
  in a jump's uniform density, the deviation means by moment matching;
- :func:`update_deviation`: the Kalman update of every cell's deviation mean and of the
  shared covariance.

Each kernel takes a few microseconds; the FFTs and the measurement groups
(:func:`~tracker.estimators.ukf.observation_groups`) are now most of a step.

The arithmetic is the numpy code's it replaces (the same formulas; the Cholesky factor in
LAPACK's order, the deviation's solve by partial-pivoting elimination as LAPACK's dgesv);
sums over cells run in eight interleaved partial sums where numpy summed pairwise or BLAS in
blocks, and the likelihood is carried as a product rather than a sum of logs
(:func:`exponents`), so results agree with it to rounding. Divisions follow numpy's error
model (inf or NaN, never an exception, as the numpy code had them), which also lets the
loops vectorise.

Every kernel is ``njit(cache=True, nogil=True)``: compiled once to the ``__pycache__`` next
to this file (about 10 s), loaded from there afterwards; :func:`warm_up` compiles or loads
them when a grid filter is made, so that no frame waits. Arrays are float64 (bool for
masks) and C-contiguous, but for the spectrum :func:`attenuate` takes, a view: another dtype
or layout would compile a second version on first use.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

from tracker.estimators.linalg_kernels import _lu_solve

_TWO_PI = 2.0 * math.pi


@numba.njit(cache=True, nogil=True, error_model="numpy")
def group_terms(y, c, JK, R_bar, M, present, q_r, Sigma, p, mu, deviation):
    """Per present group, the affine map of the cells' prediction errors and its whitening.

    The prediction error ``c + JK expansion_basis(mu) - Rz(q_r + delta)^T y`` of a group at
    a cell (minus its residual) is ``C b`` with ``b = [cos delta, sin delta, 1, mu_p, mu_d,
    mu_p^2, mu_p mu_d, mu_d^2]`` the cell's basis: with ``(u_x, u_y)`` the horizontal part
    of ``Rz(q_r)^T y``, ``Rz(delta)^T u = u cos(delta) + (u_y, -u_x) sin(delta)``. With a
    deviation its quadratic term enters with its mean (``c`` biased) and spread (Isserlis'
    theorem, :func:`~tracker.estimators.deviation.quadratic_moments`), its linear term with
    the Jacobian at the most probable cell's deviation
    (:func:`~tracker.estimators.deviation.deviation_jacobian`).

    Parameters
    ----------
    y, c : arrays (G, 3)
        Measured and model vectors of every group (mm, or mm/s for a velocity).
    JK : array (G, 3, 5)
        ``[J K]``, the shape's expansion in the deviation (mm/mm, 1/mm).
    R_bar, M : arrays (G, 3, 3)
        Rotation-invariant segmentation noise and white model error, mm^2.
    present : bool array (G,)
    q_r : float
        The base rotation, rad.
    Sigma : array (2, 2)
        The deviation's covariance, mm^2.
    p : array (N,)
        The posterior (its most probable cell gives the Jacobian's deviation).
    mu : array (2, N)
        The deviation means of the cells, mm.
    deviation : bool
        Whether the deviation is estimated (k = 8; else k = 3, and Sigma, p, mu are unused).

    Returns
    -------
    C : array (G', 3, k)
        The affine maps of the G' present groups.
    A : array (G', 3, k)
        ``L^-1 C``; not filled unless ``ok``.
    J : array (G', 3, 2)
        The deviation's Jacobian at the most probable cell's deviation (zero without).
    noise : array (G', 3, 3)
        Each group's covariance but for that linear deviation term, mm^2.
    S : array (G', 3, 3)
        Each group's covariance, mm^2.
    ok : bool
        False if some S is not positive definite (the caller factorises with a jitter).
    """
    n_groups = 0
    for g in range(present.size):
        n_groups += present[g]
    k = 8 if deviation else 3
    C = np.zeros((n_groups, 3, k))
    A = np.zeros((n_groups, 3, k))
    J = np.zeros((n_groups, 3, 2))
    noise = np.empty((n_groups, 3, 3))
    S = np.empty((n_groups, 3, 3))
    cq, sq = math.cos(q_r), math.sin(q_r)
    quad = np.zeros((3, 3))
    dq_p = dq_d = 0.0
    a = b = d = 0.0
    if deviation:
        best = 0
        for n in range(p.size):
            if p[n] > p[best]:
                best = n
        dq_p, dq_d = mu[0, best], mu[1, best]
        a, b, d = Sigma[0, 0], Sigma[0, 1], Sigma[1, 1]
        # Covariance of the quadratic terms [dq_p^2, dq_p dq_d, dq_d^2] (Isserlis).
        quad[0, 0], quad[0, 1], quad[0, 2] = 2 * a * a, 2 * a * b, 2 * b * b
        quad[1, 0], quad[1, 1], quad[1, 2] = 2 * a * b, a * d + b * b, 2 * b * d
        quad[2, 0], quad[2, 1], quad[2, 2] = 2 * b * b, 2 * b * d, 2 * d * d
    KQ = np.empty((3, 3))
    JS = np.empty((3, 2))
    L = np.empty((3, 3))
    ok = True
    i = 0
    for g in range(present.size):
        if not present[g]:
            continue
        for r in range(3):
            for s in range(3):
                noise[i, r, s] = R_bar[g, r, s] + M[g, r, s]
        bias = np.zeros(3)
        if deviation:
            for r in range(3):
                K0, K1, K2 = JK[g, r, 2], JK[g, r, 3], JK[g, r, 4]
                J[i, r, 0] = JK[g, r, 0] + (2 * dq_p * K0 + dq_d * K1)
                J[i, r, 1] = JK[g, r, 1] + (dq_p * K1 + 2 * dq_d * K2)
                bias[r] = K0 * a + K1 * b + K2 * d
                for s in range(3):
                    KQ[r, s] = K0 * quad[0, s] + K1 * quad[1, s] + K2 * quad[2, s]
                JS[r, 0] = J[i, r, 0] * Sigma[0, 0] + J[i, r, 1] * Sigma[1, 0]
                JS[r, 1] = J[i, r, 0] * Sigma[0, 1] + J[i, r, 1] * Sigma[1, 1]
            for r in range(3):
                for s in range(3):
                    spread = (
                        KQ[r, 0] * JK[g, s, 2] + KQ[r, 1] * JK[g, s, 3] + KQ[r, 2] * JK[g, s, 4]
                    )
                    noise[i, r, s] += spread
                    S[i, r, s] = noise[i, r, s] + (JS[r, 0] * J[i, s, 0] + JS[r, 1] * J[i, s, 1])
        else:
            S[i] = noise[i]
        y_x, y_y = y[g, 0], y[g, 1]
        u_x, u_y = cq * y_x + sq * y_y, cq * y_y - sq * y_x
        C[i, 0, 0], C[i, 0, 1], C[i, 0, 2] = -u_x, -u_y, c[g, 0] + bias[0]
        C[i, 1, 0], C[i, 1, 1], C[i, 1, 2] = -u_y, u_x, c[g, 1] + bias[1]
        C[i, 2, 2] = (c[g, 2] + bias[2]) - y[g, 2]
        if deviation:
            for r in range(3):
                for j in range(5):
                    C[i, r, 3 + j] = JK[g, r, j]
        if ok and _inverse_cholesky_3(S[i], L):
            for r in range(3):
                for j in range(k):
                    total = 0.0
                    for s in range(r + 1):
                        total += L[r, s] * C[i, s, j]
                    A[i, r, j] = total
        else:
            ok = False
        i += 1
    return C, A, J, noise, S, ok


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _inverse_cholesky_3(S, out):
    """``L^-1`` (3, 3) of the lower Cholesky factor L of S (3, 3), in LAPACK's order of
    operations, into ``out``; False if S is not positive definite (or not finite)."""
    d1 = S[0, 0]
    if not d1 > 0.0:
        return False
    l11 = math.sqrt(d1)
    l21, l31 = S[1, 0] / l11, S[2, 0] / l11
    d2 = S[1, 1] - l21 * l21
    if not d2 > 0.0:
        return False
    l22 = math.sqrt(d2)
    l32 = (S[2, 1] - l31 * l21) / l22
    d3 = S[2, 2] - l31 * l31 - l32 * l32
    if not (d3 > 0.0 and math.isfinite(d3)):
        return False
    l33 = math.sqrt(d3)
    m11, m22, m33 = 1.0 / l11, 1.0 / l22, 1.0 / l33
    m21 = -(l21 * m11) * m22
    m32 = -(l32 * m22) * m33
    m31 = -(l31 * m11 + l32 * m21) * m33
    out[0, 0], out[0, 1], out[0, 2] = m11, 0.0, 0.0
    out[1, 0], out[1, 1], out[1, 2] = m21, m22, 0.0
    out[2, 0], out[2, 1], out[2, 2] = m31, m32, m33
    return True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _sum(x):
    """Sum of x (N,) in eight interleaved partial sums: one running sum waits for each
    addition (a latency-bound loop); eight are vectorised. (Equal to a sum in cell order
    to rounding, as numpy's pairwise sum is.)"""
    N = x.size
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    stop = N - N % 8
    for n in range(0, stop, 8):
        s0 += x[n]
        s1 += x[n + 1]
        s2 += x[n + 2]
        s3 += x[n + 3]
        s4 += x[n + 4]
        s5 += x[n + 5]
        s6 += x[n + 6]
        s7 += x[n + 7]
    for n in range(stop, N):
        s0 += x[n]
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _dot(x, y):
    """``sum(x * y)`` of x, y (N,), as :func:`_sum`."""
    N = x.size
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    stop = N - N % 8
    for n in range(0, stop, 8):
        s0 += x[n] * y[n]
        s1 += x[n + 1] * y[n + 1]
        s2 += x[n + 2] * y[n + 2]
        s3 += x[n + 3] * y[n + 3]
        s4 += x[n + 4] * y[n + 4]
        s5 += x[n + 5] * y[n + 5]
        s6 += x[n + 6] * y[n + 6]
        s7 += x[n + 7] * y[n + 7]
    for n in range(stop, N):
        s0 += x[n] * y[n]
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _least(x, sign):
    """Least element of ``sign * x`` (x (N,), sign +-1: exact), in eight interleaved running
    minima (as :func:`_sum`)."""
    N = x.size
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = np.inf
    stop = N - N % 8
    for n in range(0, stop, 8):
        m0 = min(m0, sign * x[n])
        m1 = min(m1, sign * x[n + 1])
        m2 = min(m2, sign * x[n + 2])
        m3 = min(m3, sign * x[n + 3])
        m4 = min(m4, sign * x[n + 4])
        m5 = min(m5, sign * x[n + 5])
        m6 = min(m6, sign * x[n + 6])
        m7 = min(m7, sign * x[n + 7])
    for n in range(stop, N):
        m0 = min(m0, sign * x[n])
    return min(min(min(m0, m1), min(m2, m3)), min(min(m4, m5), min(m6, m7)))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _min(x):
    """Least element of x (N,)."""
    return _least(x, 1.0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _max(x):
    """Largest element of x (N,)."""
    return -_least(x, -1.0)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def squared_residuals(A, cos, sin, mu):
    """d^2 of every group at every cell: ``|A[g] b_n|^2`` with ``b_n`` the cell's basis
    ``[cos, sin, 1, mu_p, mu_d, mu_p^2, mu_p mu_d, mu_d^2]`` (its first k entries).

    Parameters
    ----------
    A : array (G, 3, k)
        Whitened affine maps (:func:`group_terms`), k = 3 or 8.
    cos, sin : arrays (N,)
        Of the cells' angles.
    mu : array (2, N)
        The cells' deviation means, mm (unused for k = 3).

    Returns
    -------
    d2 : array (G, N)
    """
    G, _, k = A.shape
    N = cos.size
    d2 = np.empty((G, N))
    m0, m1 = mu[0], mu[1]
    # One pass over the cells per group, its three rows at once (vectorised over cells).
    for g in range(G):
        row = d2[g]
        a0, a1, a2 = A[g, 0, 0], A[g, 0, 1], A[g, 0, 2]
        b0, b1, b2 = A[g, 1, 0], A[g, 1, 1], A[g, 1, 2]
        c0, c1, c2 = A[g, 2, 0], A[g, 2, 1], A[g, 2, 2]
        if k == 3:
            for n in range(N):
                x, y = cos[n], sin[n]
                u = a0 * x + a1 * y + a2
                v = b0 * x + b1 * y + b2
                w = c0 * x + c1 * y + c2
                row[n] = u * u + v * v + w * w
            continue
        a3, a4, a5, a6, a7 = A[g, 0, 3], A[g, 0, 4], A[g, 0, 5], A[g, 0, 6], A[g, 0, 7]
        b3, b4, b5, b6, b7 = A[g, 1, 3], A[g, 1, 4], A[g, 1, 5], A[g, 1, 6], A[g, 1, 7]
        c3, c4, c5, c6, c7 = A[g, 2, 3], A[g, 2, 4], A[g, 2, 5], A[g, 2, 6], A[g, 2, 7]
        for n in range(N):
            x, y, p, d = cos[n], sin[n], m0[n], m1[n]
            pp, pd, dd = p * p, p * d, d * d
            u = a0 * x + a1 * y + a2 + a3 * p + a4 * d + a5 * pp + a6 * pd + a7 * dd
            v = b0 * x + b1 * y + b2 + b3 * p + b4 * d + b5 * pp + b6 * pd + b7 * dd
            w = c0 * x + c1 * y + c2 + c3 * p + c4 * d + c5 * pp + c6 * pd + c7 * dd
            row[n] = u * u + v * v + w * w
    return d2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def exponents(d2, shrink, scale2, mixture):
    """The exponents of the frame's likelihood on every cell, for ``np.exp``.

    Each group's likelihood is ``(1 - p) exp(-d2/2) + p s^-dim exp(-d2 / (2 s^2))``
    (:func:`~tracker.estimators.measurement.mixture_log_likelihood`), that is
    ``p s^-dim exp(-d2 / (2 s^2)) (1 + ratio exp(-shrink d2 / 2))``. The product over the
    groups is carried as the exponent of its first factors' product, shifted by its largest
    value (so that the best cell's is exp(0)), and one exponent per group for the second.

    Parameters
    ----------
    d2 : array (G, N)
    shrink : float
        ``1 - s^-2``.
    scale2 : float
        ``s^2``; 1 without outliers (the Gaussian).
    mixture : bool
        False without outliers: the last row only.

    Returns
    -------
    array (G + 1, N), or (1, N) without ``mixture``
        ``-shrink d2 / 2`` of every group, then ``-(sum d2 - min sum d2) / (2 s^2)``.
    """
    G, N = d2.shape
    rows = G if mixture else 0
    out = np.empty((rows + 1, N))
    total = out[rows]
    total[:] = d2[0]
    for g in range(1, G):
        row = d2[g]
        for n in range(N):
            total[n] += row[n]
    least = _min(total)
    for n in range(N):
        total[n] = -0.5 * (total[n] - least) / scale2
    half = -0.5 * shrink
    for g in range(rows):
        row, exponent = d2[g], out[g]
        for n in range(N):
            exponent[n] = half * row[n]
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def posterior(prior, factors, ratio, mixture):
    """Prior times the frame's likelihood on every cell, normalised.

    Parameters
    ----------
    prior : array (N,)
    factors : array (G + 1, N), or (1, N) without ``mixture``
        ``np.exp`` of :func:`exponents`.
    ratio : float
        ``(1 - p) / (p s^-dim)``, the inlier component's weight over the outlier's.
    mixture : bool

    Returns
    -------
    p : array (N,)
        The posterior; only unnormalised unless ``ok``.
    ok : bool
        False where the likelihood's peak lies where the prior has (numerically) no mass:
        the mass is below 1e-250 of what the best cell alone would give, or not finite (the
        caller computes in logs).
    """
    rows, N = factors.shape
    G = rows - 1 if mixture else 0
    likelihood = factors[rows - 1].copy()
    # Each group's factor divided by its largest, 1 + ratio, so that the product cannot
    # overflow: the best cell's likelihood is at most 1.
    unit = 1.0 / (1.0 + ratio)
    for g in range(G):
        row = factors[g]
        for n in range(N):
            likelihood[n] *= (1.0 + ratio * row[n]) * unit
    largest = _max(likelihood)
    p = np.empty(N)
    for n in range(N):
        p[n] = prior[n] * likelihood[n]
    total = _sum(p)
    # In units of the best cell's likelihood, as the likelihood's log shifted by its maximum.
    mass = total / largest
    if not (mass > 1e-250 and math.isfinite(mass)):
        return p, False
    for n in range(N):
        p[n] /= total
    return p, True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def circular_moments(p, cos, sin, angles, cell_rad):
    """Circular mean (rad, in [-pi, pi]) and the variance of the posterior about it (rad^2,
    the cells' offsets wrapped to [-pi, pi]; without a cell's own ``h^2 / 12``).

    Parameters
    ----------
    p, cos, sin, angles : arrays (N,)
        The posterior, the cos and sin of the cells' angles and the angles (rad), from -pi
        in steps of ``cell_rad``.
    cell_rad : float
    """
    N = p.size
    mean = math.atan2(_dot(p, sin), _dot(p, cos))
    # The offsets from the mean, wrapped: only the cells more than half a turn away wrap, a
    # run at one end of the grid.
    offset = np.empty(N)
    for n in range(N):
        offset[n] = angles[n] - mean
    if mean >= 0.0:
        for n in range(min(int(math.ceil(mean / cell_rad)), N)):
            offset[n] += _TWO_PI
    else:
        for n in range(min(int(math.floor((_TWO_PI + mean) / cell_rad)) + 1, N), N):
            offset[n] -= _TWO_PI
    for n in range(N):
        offset[n] *= offset[n]
    return mean, _dot(p, offset)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def attenuate(spectrum, variance, k2):
    """Multiply the Fourier coefficients (rows, K) in place by the wrapped normal's,
    ``exp(-k^2 variance / 2)`` (``k2``: k^2 of the K frequencies; variance in rad^2)."""
    rows, K = spectrum.shape
    for k in range(K):
        factor = math.exp(-0.5 * variance * k2[k])
        for r in range(rows):
            spectrum[r, k] *= factor


@numba.njit(cache=True, nogil=True, error_model="numpy")
def mix_in_jump(p, means, have_means, mu, jump, clip):
    """The predict's end: ``p' = scale p + jump / N`` with ``scale = (1 - jump) / sum(p)``,
    and the deviation means of p' (in place in ``mu``).

    A jump lands anywhere with the deviation's prior mean (zero), so the means become
    ``means`` (``p mu`` convolved where p is) over ``p' / scale`` (a floor of 1e-300 keeps
    that finite where p is 0 and nothing jumps); a certain jump gives the uniform density
    and zero means.

    Parameters
    ----------
    p : array (N,)
        The blurred (``clip``: its negative ringing is set to 0, in place) or unchanged
        posterior.
    means : array (2, N)
        ``p mu`` convolved like p, if ``have_means``; else ignored (p mu is used).
    mu : array (2, N)
        The deviation means, mm: updated in place.
    jump : float
        Probability of a jump.
    clip : bool

    Returns
    -------
    array (N,)
        The predicted posterior (a new array).
    """
    N = p.size
    if clip:
        for n in range(N):
            # (NaN stays NaN, as np.maximum keeps it.)
            if p[n] < 0.0:
                p[n] = 0.0
    scale = (1.0 - jump) / _sum(p)
    out = np.empty(N)
    if scale == 0.0:  # a certain jump
        out[:] = 1.0 / N
        mu[:] = 0.0
        return out
    if not have_means and jump == 0.0:
        for n in range(N):
            out[n] = p[n] * scale
        return out
    floor = max(jump / N / scale, 1e-300)
    m0, m1 = mu[0], mu[1]
    if have_means:
        s0, s1 = means[0], means[1]
        for n in range(N):
            weight = p[n] + floor
            m0[n] = s0[n] / weight
            m1[n] = s1[n] / weight
            out[n] = weight * scale
    else:
        for n in range(N):
            weight = p[n] + floor
            m0[n] = (p[n] * m0[n]) / weight
            m1[n] = (p[n] * m1[n]) / weight
            out[n] = weight * scale
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def update_deviation(J, noise, inlier, C, Sigma, cos, sin, mu):
    """Kalman update of every cell's deviation mean and of the shared covariance with the
    inlying groups: one gain, with the Jacobian at the most probable cell's deviation.

    Parameters
    ----------
    J : array (G, 3, 2)
    noise : array (G, 3, 3)
        Each group's covariance but for the linear deviation term, mm^2.
    inlier : bool array (G,)
        At least one True.
    C : array (G, 3, 8)
        The affine maps of the prediction errors (:func:`group_terms`).
    Sigma : array (2, 2)
        The deviation's covariance, mm^2.
    cos, sin : arrays (N,)
    mu : array (2, N)
        The deviation means, mm: updated in place.

    Returns
    -------
    array (2, 2)
        The deviation's covariance after the update (symmetrised), mm^2.

    Raises
    ------
    numpy.linalg.LinAlgError
        For a singular innovation covariance.
    """
    G = inlier.size
    m = 0
    for g in range(G):
        m += 3 * inlier[g]
    H = np.empty((m, 2))
    Cm = np.empty((m, 8))
    block = np.empty(m, dtype=np.intp)
    i = 0
    for g in range(G):
        if inlier[g]:
            for r in range(3):
                H[i + r, 0], H[i + r, 1] = J[g, r, 0], J[g, r, 1]
                block[i + r] = g
                for j in range(8):
                    Cm[i + r, j] = C[g, r, j]
            i += 3
    HSigma = np.empty((m, 2))
    for r in range(m):
        HSigma[r, 0] = H[r, 0] * Sigma[0, 0] + H[r, 1] * Sigma[1, 0]
        HSigma[r, 1] = H[r, 0] * Sigma[0, 1] + H[r, 1] * Sigma[1, 1]
    S = np.empty((m, m))
    for r in range(m):
        for s in range(m):
            S[r, s] = HSigma[r, 0] * H[s, 0] + HSigma[r, 1] * H[s, 1]
    for r in range(m):
        for s in range(m):
            if block[r] == block[s]:
                S[r, s] += noise[block[r], r % 3, s % 3]
    solution = HSigma.copy()  # solved in place: (m, 2), the gain's transpose
    if _lu_solve(S, solution, np.empty((m, m))) == -math.inf:
        raise np.linalg.LinAlgError("singular innovation covariance of the deviation")
    gain_C = np.zeros((2, 8))
    for r in range(m):
        for j in range(8):
            gain_C[0, j] += solution[r, 0] * Cm[r, j]
            gain_C[1, j] += solution[r, 1] * Cm[r, j]
    g0 = gain_C[0]
    g1 = gain_C[1]
    mu_p, mu_d = mu[0], mu[1]
    for n in range(mu.shape[1]):
        m0, m1 = mu_p[n], mu_d[n]
        q0, q1, q2 = m0 * m0, m0 * m1, m1 * m1
        x, y = cos[n], sin[n]
        mu_p[n] = m0 - (g0[0] * x + g0[1] * y + g0[2] + g0[3] * m0 + g0[4] * m1
                         + g0[5] * q0 + g0[6] * q1 + g0[7] * q2)  # fmt: skip
        mu_d[n] = m1 - (g1[0] * x + g1[1] * y + g1[2] + g1[3] * m0 + g1[4] * m1
                         + g1[5] * q0 + g1[6] * q1 + g1[7] * q2)  # fmt: skip
    after = np.empty((2, 2))
    for r in range(2):
        for s in range(2):
            total = 0.0
            for j in range(m):
                total += solution[j, r] * HSigma[j, s]
            after[r, s] = Sigma[r, s] - total
    off = 0.5 * (after[0, 1] + after[1, 0])
    after[0, 1] = after[1, 0] = off
    return after


@functools.cache
def warm_up() -> None:
    """Compile every kernel, or load it from the cache, on a tiny input with the argument
    types the grid filter passes, so that the first frame does not wait for it."""
    N = 16
    angles = np.linspace(-math.pi, math.pi, N, endpoint=False)
    cos, sin = np.cos(angles), np.sin(angles)
    p = np.full(N, 1.0 / N)
    mu = np.zeros((2, N))
    eye = np.broadcast_to(np.eye(3), (2, 3, 3)).copy()
    JK = np.zeros((2, 3, 5))
    JK[:, :, 0] = 1.0
    present = np.ones(2, dtype=bool)
    for deviation in (True, False):
        C, A, J, noise, _, _ = group_terms(
            np.ones((2, 3)), np.ones((2, 3)), JK, eye, eye, present, 0.1, np.eye(2), p, mu,
            deviation,
        )  # fmt: skip
        d2 = squared_residuals(A, cos, sin, mu)
    for mixture in (True, False):
        factors = np.exp(exponents(d2, 0.5, 4.0, mixture))
        posterior(p, factors, 10.0, mixture)
    circular_moments(p, cos, sin, angles, 2 * math.pi / N)
    # As the filter passes them: the first K coefficients of a real FFT's rows (a view).
    spectrum = np.ones((3, N // 2 + 1), dtype=complex)
    attenuate(spectrum[:, : N // 4], 0.1, angles**2)
    attenuate(spectrum, 0.1, angles**2)  # all of them: C-contiguous
    mix_in_jump(p.copy(), mu, True, mu, 0.1, True)
    C, A, J, noise, _, _ = group_terms(
        np.ones((2, 3)), np.ones((2, 3)), JK, eye, eye, present, 0.1, np.eye(2), p, mu, True
    )
    update_deviation(J, noise, present, C, np.eye(2), cos, sin, mu)


__all__ = [
    "attenuate",
    "circular_moments",
    "exponents",
    "group_terms",
    "mix_in_jump",
    "posterior",
    "squared_residuals",
    "update_deviation",
    "warm_up",
]
