"""Exact global fit of a rotation about z_b (the structure of docs/design.md section 3).

Every estimator of the bending plane reduces to: find the angle phi minimising

    f(phi) = (y - m(phi))^T W (y - m(phi)),   m(phi) = blockdiag(Rz(phi), ...) c

for stacked measured vectors ``y`` and delta_L-independent model vectors ``c`` (n vectors of
3), with information matrix ``W`` (the inverse noise covariance). Because
``Rz(phi) c = c_z e_z + cos(phi) [c_x, c_y, 0] + sin(phi) [-c_y, c_x, 0]``, ``f`` is a
trigonometric polynomial of degree two in ``phi``; its stationary points are the unit-circle
roots of a quartic, so the global minimum is found exactly. With weights that are isotropic in
the horizontal plane (the common case) the quadratic terms vanish and the minimiser is the 2-D
Procrustes (Wahba) solution ``atan2(sum w cross_z, sum w dot_xy)``.

``W`` is the joint (3n, 3n) information matrix, or, for independent vectors, their own 3 x 3
informations stacked as (n, 3, 3) (see :func:`is_per_vector`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models._fit_kernels import fit_joint, fit_per_vector

Array = np.ndarray


# Newton steps on the best candidate after the candidates' own: a candidate that started in
# another basin (a near-double root) can be a few 1e-8 rad short of the minimum after three
# steps and still win the comparison of costs, which rounding decides between it and a fully
# converged one. Two more steps on the winner converge it to rounding in every case.
POLISH_STEPS = 2


@dataclass(frozen=True)
class RotationFit:
    """Result of :func:`fit_rotation_z` for a batch (...)."""

    phi_rad: Array  # (...) minimiser, wrapped to [-pi, pi)
    fisher_information: Array  # (...) d^2 f / 2 at the minimiser's model: m'^T W m', 1/rad^2
    cost: Array  # (...) f(phi), the weighted squared residual (chi-square at the minimum)
    informative_radius_mm: Array  # (...) sqrt(sum_k |c_k,xy|^2)


def _basis_vectors(c: Array) -> tuple[Array, Array, Array]:
    """m0, m_c, m_s of m(phi) = m0 + cos(phi) m_c + sin(phi) m_s, each flattened to (..., 3n)."""
    zero = np.zeros_like(c[..., 0])
    m0 = np.stack([zero, zero, c[..., 2]], -1)
    m_c = np.stack([c[..., 0], c[..., 1], zero], -1)
    m_s = np.stack([-c[..., 1], c[..., 0], zero], -1)
    flat = c.shape[:-2] + (3 * c.shape[-2],)
    return m0.reshape(flat), m_c.reshape(flat), m_s.reshape(flat)


def is_per_vector(W: Array, n: int) -> bool:
    """True if ``W`` holds one 3 x 3 information per vector, shape (..., n, 3, 3), rather than
    the joint (..., 3n, 3n) matrix (the two coincide for one vector, read as joint)."""
    return n > 1 and W.shape[-1] == 3


def _times(W: Array, v: Array) -> Array:
    """W v for stacked vectors v (..., 3n), W joint (..., 3n, 3n) or per vector (..., n, 3, 3)."""
    if not is_per_vector(W, v.shape[-1] // 3):
        return np.einsum("...ij,...j->...i", W, v)
    per_vector = v.reshape(v.shape[:-1] + (-1, 3))
    return np.einsum("...kij,...kj->...ki", W, per_vector).reshape(v.shape)


def trig_coefficients(y: Array, c: Array, W: Array) -> tuple[Array, ...]:
    """Coefficients of f(phi) = k + a1 cos + b1 sin + a2 cos 2phi + b2 sin 2phi.

    Parameters
    ----------
    y, c : array, shape (..., n, 3)
        Measured vectors and model vectors.
    W : array, shape (..., 3n, 3n) or (..., n, 3, 3)
        Information matrix (inverse covariance) of the stacked measurement, or of each vector.
    """
    m0, m_c, m_s = _basis_vectors(c)
    r0 = y.reshape(m0.shape) - m0
    Wm_c = _times(W, m_c)
    Wm_s = _times(W, m_s)
    cc = np.sum(m_c * Wm_c, -1)
    ss = np.sum(m_s * Wm_s, -1)
    cs = np.sum(m_s * Wm_c, -1)
    a1 = -2.0 * np.sum(r0 * Wm_c, -1)
    b1 = -2.0 * np.sum(r0 * Wm_s, -1)
    a2 = 0.5 * (cc - ss)
    b2 = cs
    k = np.sum(r0 * _times(W, r0), -1) + 0.5 * (cc + ss)
    return k, a1, b1, a2, b2, cc, ss, cs


def _evaluate(phi: Array, k, a1, b1, a2, b2) -> Array:
    return k + a1 * np.cos(phi) + b1 * np.sin(phi) + a2 * np.cos(2 * phi) + b2 * np.sin(2 * phi)


def _stationary_candidates(a1, b1, a2, b2) -> Array:
    """Angles of the roots of z^2 f'(z) (a quartic in z = exp(i phi)), shape (..., 5).

    The Procrustes angle is appended as a fifth candidate so that the degenerate case of a
    vanishing quartic term is covered as well; every candidate is polished by Newton steps.
    """
    lead = b2 + 1j * a2
    coeffs = np.stack(
        [lead, 0.5 * (b1 + 1j * a1), np.zeros_like(lead), 0.5 * (b1 - 1j * a1), b2 - 1j * a2], -1
    )
    scale = np.max(np.abs(coeffs), axis=-1)
    batch = coeffs.shape[:-1]
    roots = np.full(batch + (4,), np.nan + 0j)
    quartic = np.abs(lead) > 1e-12 * np.where(scale > 0, scale, 1.0)
    if np.any(quartic):
        monic = coeffs[quartic] / coeffs[quartic][:, :1]
        companion = np.zeros(monic.shape[:1] + (4, 4), dtype=complex)
        companion[:, 0, :] = -monic[:, 1:]
        companion[:, 1, 0] = companion[:, 2, 1] = companion[:, 3, 2] = 1.0
        roots[quartic] = np.linalg.eigvals(companion)
    candidates = np.angle(roots)
    procrustes = np.arctan2(-b1, -a1)
    candidates = np.concatenate([candidates, procrustes[..., None]], -1)
    return np.where(np.isfinite(candidates), candidates, procrustes[..., None])


def _newton(phi: Array, a1, b1, a2, b2, steps: int = POLISH_STEPS) -> Array:
    """Newton steps on f'(phi) = 0 from every angle in ``phi``, towards minima only."""
    for _ in range(steps):
        d1 = -a1 * np.sin(phi) + b1 * np.cos(phi)
        d1 += -2 * a2 * np.sin(2 * phi) + 2 * b2 * np.cos(2 * phi)
        d2 = -a1 * np.cos(phi) - b1 * np.sin(phi)
        d2 += -4 * a2 * np.cos(2 * phi) - 4 * b2 * np.sin(2 * phi)
        # Only step towards minima (d2 > 0); maxima stay where they are and lose below.
        phi = np.where(d2 > 0, phi - d1 / np.where(d2 > 0, d2, 1.0), phi)
    return phi


def fit_rotation_z(y: Array, c: Array, W: Array, newton_steps: int = 3) -> RotationFit:
    """Global weighted least-squares angle of a rotation about z.

    Parameters
    ----------
    y : array, shape (..., n, 3)
        Measured vectors (positions relative to the base or velocities) in {B}.
    c : array, shape (..., n, 3)
        delta_L-independent model vectors: the model predicts ``Rz(phi) c``.
    W : array, shape (..., 3n, 3n) or (..., n, 3, 3)
        Information matrix of the stacked measurement (inverse of its noise covariance), or of
        each vector when they are independent.

    Returns
    -------
    RotationFit
        ``phi_rad`` is the bending-plane angle delta_1; subtract q_r for delta_L. Python
        floats for one problem (no batch axes).
    """
    y = np.asarray(y, dtype=float)
    c = np.asarray(c, dtype=float)
    W = np.asarray(W, dtype=float)
    if c.ndim == 2 and y.shape == c.shape and W.shape in ((c.size, c.size), c.shape + (3,)):
        return _fit_one(y, c, W, newton_steps)
    k, a1, b1, a2, b2, cc, ss, cs = trig_coefficients(y, c, W)
    args = [x[..., None] for x in (a1, b1, a2, b2)]
    phi = _newton(_stationary_candidates(a1, b1, a2, b2), *args, newton_steps)
    best = np.argmin(_evaluate(phi, k[..., None], *args), axis=-1)
    phi_best = _newton(np.take_along_axis(phi, best[..., None], -1)[..., 0], a1, b1, a2, b2)
    cost = _evaluate(phi_best, k, a1, b1, a2, b2)
    # Fisher information m'(phi)^T W m'(phi), m' = -sin m_c + cos m_s.
    s, co = np.sin(phi_best), np.cos(phi_best)
    info = s * s * cc + co * co * ss - 2 * s * co * cs
    radius = np.sqrt(np.sum(c[..., :, 0] ** 2 + c[..., :, 1] ** 2, axis=-1))
    phi_wrapped = np.mod(phi_best + np.pi, 2 * np.pi) - np.pi
    return RotationFit(
        phi_rad=phi_wrapped,
        fisher_information=info,
        cost=np.maximum(cost, 0.0),
        informative_radius_mm=radius,
    )


def _fit_one(y: Array, c: Array, W: Array, newton_steps: int) -> RotationFit:
    """:func:`fit_rotation_z` for one problem, compiled (:mod:`models._fit_kernels`):
    the same coefficients, candidates and Newton iterations as the batched path, which on one
    frame spends ten times the arithmetic in numpy's per-call overhead (the per-frame
    estimators call it every frame)."""
    n = c.shape[0]
    # Writable C-ordered copies: the kernels' one type (a read-only array would compile anew).
    y, c, W = np.array(y, dtype=float), np.array(c, dtype=float), np.array(W, dtype=float)
    if n == 1 or is_per_vector(W, n):
        fit = fit_per_vector(y, c, W.reshape(n, 3, 3), newton_steps, POLISH_STEPS)
    else:
        fit = fit_joint(y, c, W, newton_steps, POLISH_STEPS)
    phi, information, cost, radius = fit
    return RotationFit(
        phi_rad=phi, fisher_information=information, cost=cost, informative_radius_mm=radius
    )


def rotation_fisher_information(c: Array, W: Array, phi_rad: Array) -> Array:
    """Fisher information of phi for measurements Rz(phi) c + noise with information W.

    Parameters
    ----------
    c : array, shape (..., n, 3)
    W : array, shape (..., 3n, 3n) or (..., n, 3, 3)
    phi_rad : array, shape (...)
    """
    _, m_c, m_s = _basis_vectors(np.asarray(c, dtype=float))
    phi = np.asarray(phi_rad, dtype=float)[..., None]
    dm = -np.sin(phi) * m_c + np.cos(phi) * m_s
    return np.sum(dm * _times(np.asarray(W, dtype=float), dm), -1)
