"""Cramer-Rao lower bound on delta_L (docs/design.md section 5).

The measurements are ``Rz(q_r + delta_L) c + noise`` with Gaussian noise of known covariance,
so the Fisher information of delta_L is ``m'^T Sigma^-1 m'`` with ``m' = e_z x Rz(delta_1) c``.
For the tip alone with isotropic noise sigma this is ``r_xy^2 / sigma^2``: the bound is about
``sigma / r_xy`` radians and grows without limit as the catheter straightens (r_xy -> 0),
where it is reported as ``inf`` (never NaN).
"""

from __future__ import annotations

import math

import numpy as np

from models._fit_kernels import NOT_FINITE, NOT_POSITIVE_DEFINITE, information_blocks
from models.catheter import Catheter
from models.rotation_fit import rotation_fisher_information

Array = np.ndarray


def block_diagonal(covariances: Array) -> Array:
    """(..., n, 3, 3) per-point covariances -> (..., 3n, 3n) block-diagonal joint covariance."""
    cov = np.asarray(covariances, dtype=float)
    n = cov.shape[-3]
    out = np.zeros(cov.shape[:-3] + (3 * n, 3 * n))
    for k in range(n):
        out[..., 3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = cov[..., k, :, :]
    return out


def information_from_covariance(covariance: Array) -> Array:
    """Inverse of a symmetric positive-definite covariance by Cholesky solves.

    Parameters
    ----------
    covariance : array, shape (..., m, m)

    Raises ValueError naming the problem if the covariance is not finite or not positive
    definite, rather than returning NaN.
    """
    cov = np.asarray(covariance, dtype=float)
    if cov.ndim < 2 or cov.shape[-1] != cov.shape[-2]:
        raise ValueError(f"covariance must be square, got shape {cov.shape}")
    if cov.shape == (3, 3) or (cov.ndim == 3 and cov.shape[1:] == (3, 3) and cov.shape[0]):
        # One frame's points: compiled, by the steps of the numpy path below.
        # A writable C-ordered copy: the kernel's one type.
        status, information = information_blocks(np.array(cov, dtype=float).reshape(-1, 3, 3))
        if status == NOT_FINITE:
            raise ValueError("covariance contains non-finite values")
        if status == NOT_POSITIVE_DEFINITE:
            raise ValueError("covariance is not positive definite")
        return information.reshape(cov.shape)
    if not np.all(np.isfinite(cov)):
        raise ValueError("covariance contains non-finite values")
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    try:
        chol = np.linalg.cholesky(sym)
    except np.linalg.LinAlgError as exc:
        raise ValueError("covariance is not positive definite") from exc
    if cov.ndim == 2:
        # One matrix: inv is the same LAPACK solve against the identity, without the
        # broadcasting machinery that costs more than the arithmetic at this size.
        inv_chol = np.linalg.inv(chol)
    else:
        inv_chol = np.linalg.solve(chol, np.broadcast_to(np.eye(cov.shape[-1]), cov.shape))
    return np.swapaxes(inv_chol, -1, -2) @ inv_chol


def std_from_information(information: Array | float) -> Array | float:
    """Standard deviation 1 / sqrt(I) from a Fisher information I, inf where I <= 0 (never NaN).

    A float for a float (one frame), else an array of the same shape.
    """
    if isinstance(information, float):
        return 1.0 / math.sqrt(information) if information > 0 else math.inf
    info = np.asarray(information, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(info > 0, 1.0 / np.sqrt(np.maximum(info, 1e-300)), np.inf)


def _joint_covariance(cov: Array, n: int) -> Array:
    cov = np.asarray(cov, dtype=float)
    if cov.shape[-2:] == (3, 3) and (cov.ndim == 2 or cov.shape[-3] != n) and n == 1:
        return cov
    if cov.ndim >= 3 and cov.shape[-3:] == (n, 3, 3):
        return block_diagonal(cov)
    if cov.shape[-2:] == (3 * n, 3 * n):
        return cov
    if cov.shape[-2:] == (3, 3):
        return block_diagonal(np.broadcast_to(cov[..., None, :, :], cov.shape[:-2] + (n, 3, 3)))
    raise ValueError(
        f"covariance of {n} points must have shape (3,3), (n,3,3) or (3n,3n), got {cov.shape}"
    )


def crb_tip(catheter: Catheter, q: Array, delta_L: Array | float, cov_b: Array) -> Array:
    """Bound on the standard deviation of delta_L from one tip position, rad.

    Parameters
    ----------
    q : array, shape (..., 3)
    delta_L : float or array (...), rad
    cov_b : array, shape (..., 3, 3)
        Covariance of the reconstructed tip relative to the base, in {B}, mm^2.
    """
    shape = catheter.shape_vectors(q)
    info = rotation_fisher_information(
        shape.c_tip_mm[..., None, :],
        information_from_covariance(cov_b),
        shape.q_r_rad + delta_L,
    )
    return std_from_information(info)


def crb_markers(catheter: Catheter, q: Array, delta_L: Array | float, cov_b: Array) -> Array:
    """Bound from the tip and every backbone marker of the catheter (Body Positions), rad.

    ``cov_b`` covers the n = 1 + n_markers points in the order (tip, marker_0, ...): (3, 3)
    for identical independent points, (..., n, 3, 3) per point, or the joint (..., 3n, 3n)
    covariance (points measured relative to a noisy base are correlated).
    """
    shape = catheter.shape_vectors(q)
    c = np.concatenate([shape.c_tip_mm[..., None, :], shape.c_markers_mm], axis=-2)
    W = information_from_covariance(_joint_covariance(cov_b, c.shape[-2]))
    info = rotation_fisher_information(c, W, shape.q_r_rad + delta_L)
    return std_from_information(info)


def crb_velocity(
    catheter: Catheter, q: Array, q_dot: Array, delta_L: Array | float, cov_b: Array
) -> Array:
    """Bound from one tip-velocity measurement with covariance ``cov_b`` (mm^2/s^2), rad."""
    shape = catheter.shape_vectors(q, q_dot)
    info = rotation_fisher_information(
        shape.u_tip_mm_s[..., None, :],
        information_from_covariance(cov_b),
        shape.q_r_rad + delta_L,
    )
    return std_from_information(info)
