"""Exact global fit of a rotation about z_b (the structure of DESIGN.md section 3).

Every estimator of the bending plane reduces to: find the angle phi minimising

    f(phi) = (y - m(phi))^T W (y - m(phi)),   m(phi) = blockdiag(Rz(phi), ...) c

for stacked measured vectors ``y`` and delta_L-independent model vectors ``c`` (n vectors of
3), with information matrix ``W`` (the inverse noise covariance). Because
``Rz(phi) c = c_z e_z + cos(phi) [c_x, c_y, 0] + sin(phi) [-c_y, c_x, 0]``, ``f`` is a
trigonometric polynomial of degree two in ``phi``; its stationary points are the unit-circle
roots of a quartic, so the global minimum is found exactly. With weights that are isotropic in
the horizontal plane (the common case) the quadratic terms vanish and the minimiser is the 2-D
Procrustes (Wahba) solution ``atan2(sum w cross_z, sum w dot_xy)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Array = np.ndarray


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


def trig_coefficients(y: Array, c: Array, W: Array) -> tuple[Array, ...]:
    """Coefficients of f(phi) = k + a1 cos + b1 sin + a2 cos 2phi + b2 sin 2phi.

    Parameters
    ----------
    y, c : array, shape (..., n, 3)
        Measured vectors and model vectors.
    W : array, shape (..., 3n, 3n)
        Information matrix (inverse covariance) of the stacked measurement.
    """
    m0, m_c, m_s = _basis_vectors(c)
    r0 = y.reshape(m0.shape) - m0
    Wm_c = np.einsum("...ij,...j->...i", W, m_c)
    Wm_s = np.einsum("...ij,...j->...i", W, m_s)
    cc = np.sum(m_c * Wm_c, -1)
    ss = np.sum(m_s * Wm_s, -1)
    cs = np.sum(m_s * Wm_c, -1)
    a1 = -2.0 * np.sum(r0 * Wm_c, -1)
    b1 = -2.0 * np.sum(r0 * Wm_s, -1)
    a2 = 0.5 * (cc - ss)
    b2 = cs
    k = np.sum(r0 * np.einsum("...ij,...j->...i", W, r0), -1) + 0.5 * (cc + ss)
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


def fit_rotation_z(y: Array, c: Array, W: Array, newton_steps: int = 3) -> RotationFit:
    """Global weighted least-squares angle of a rotation about z.

    Parameters
    ----------
    y : array, shape (..., n, 3)
        Measured vectors (positions relative to the base or velocities) in {B}.
    c : array, shape (..., n, 3)
        delta_L-independent model vectors: the model predicts ``Rz(phi) c``.
    W : array, shape (..., 3n, 3n)
        Information matrix of the stacked measurement (inverse of its noise covariance).

    Returns
    -------
    RotationFit
        ``phi_rad`` is the bending-plane angle delta_1; subtract q_r for delta_L.
    """
    y = np.asarray(y, dtype=float)
    c = np.asarray(c, dtype=float)
    W = np.asarray(W, dtype=float)
    k, a1, b1, a2, b2, cc, ss, cs = trig_coefficients(y, c, W)
    phi = _stationary_candidates(a1, b1, a2, b2)
    args = [x[..., None] for x in (a1, b1, a2, b2)]
    for _ in range(newton_steps):
        d1 = -args[0] * np.sin(phi) + args[1] * np.cos(phi)
        d1 += -2 * args[2] * np.sin(2 * phi) + 2 * args[3] * np.cos(2 * phi)
        d2 = -args[0] * np.cos(phi) - args[1] * np.sin(phi)
        d2 += -4 * args[2] * np.cos(2 * phi) - 4 * args[3] * np.sin(2 * phi)
        # Only step towards minima (d2 > 0); maxima stay where they are and lose below.
        phi = np.where(d2 > 0, phi - d1 / np.where(d2 > 0, d2, 1.0), phi)
    costs = _evaluate(phi, k[..., None], *args)
    best = np.argmin(costs, axis=-1)
    phi_best = np.take_along_axis(phi, best[..., None], -1)[..., 0]
    cost = np.take_along_axis(costs, best[..., None], -1)[..., 0]
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


def rotation_fisher_information(c: Array, W: Array, phi_rad: Array) -> Array:
    """Fisher information of phi for measurements Rz(phi) c + noise with information W.

    Parameters
    ----------
    c : array, shape (..., n, 3)
    W : array, shape (..., 3n, 3n)
    phi_rad : array, shape (...)
    """
    _, m_c, m_s = _basis_vectors(np.asarray(c, dtype=float))
    phi = np.asarray(phi_rad, dtype=float)[..., None]
    dm = -np.sin(phi) * m_c + np.cos(phi) * m_s
    return np.sum(dm * np.einsum("...ij,...j->...i", np.asarray(W, dtype=float), dm), -1)
