"""Modal model of one bending segment: theta(s, q) = psi(s)^T A eta(q).

``theta`` is the in-plane tangent angle measured from the segment's local x-axis toward its
z-axis (straight segment: theta = pi/2). ``psi`` is a basis in the normalised arclength
``s / L`` and ``eta`` a basis in the joint value ``q`` (mm). Bases are pluggable: anything
with ``values(x)`` and ``derivatives(x)`` returning arrays of shape (..., size) will do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

Array = np.ndarray


class Basis(Protocol):
    """A finite function basis b_k(x), k = 0..size-1."""

    size: int

    def values(self, x: Array) -> Array:
        """Basis values, shape x.shape + (size,)."""

    def derivatives(self, x: Array) -> Array:
        """Basis derivatives d b_k / dx, shape x.shape + (size,)."""


@dataclass(frozen=True)
class PowerBasis:
    """Monomials x^k for k = 0..size-1 (the default model's psi and eta)."""

    size: int

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError(f"a power basis needs at least one term, got size={self.size}")

    def values(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        return x[..., None] ** np.arange(self.size)

    def derivatives(self, x: Array) -> Array:
        x = np.asarray(x, dtype=float)
        k = np.arange(self.size)
        # x**(k-1) at k = 0 would be 0**-1; the k factor zeroes that term anyway.
        return k * x[..., None] ** np.maximum(k - 1, 0)


@dataclass(frozen=True)
class ModalSegment:
    """One bending segment of the catheter.

    Parameters
    ----------
    length_mm : float
        Segment length L, mm.
    A : array, shape (psi.size, eta.size)
        Modal shape matrix.
    psi, eta : Basis
        Arclength basis (in s / L) and joint basis (in q, mm).
    """

    length_mm: float
    A: Array
    psi: Basis = field(default_factory=lambda: PowerBasis(3))
    eta: Basis = field(default_factory=lambda: PowerBasis(3))

    def __post_init__(self) -> None:
        if not np.isfinite(self.length_mm) or self.length_mm <= 0:
            raise ValueError(f"segment length must be positive and finite, got {self.length_mm}")
        A = np.array(self.A, dtype=float)
        if A.shape != (self.psi.size, self.eta.size):
            raise ValueError(
                f"modal matrix A has shape {A.shape}, expected ({self.psi.size}, {self.eta.size})"
                " from the sizes of the psi and eta bases"
            )
        if not np.all(np.isfinite(A)):
            raise ValueError("modal matrix A contains non-finite values")
        A.setflags(write=False)
        object.__setattr__(self, "A", A)

    def coefficients(self, q_mm: Array) -> Array:
        """a(q) = A eta(q), shape q.shape + (psi.size,), so that theta(s) = psi(s/L) . a."""
        return self.eta.values(q_mm) @ self.A.T

    def coefficient_rates(self, q_mm: Array) -> Array:
        """d a / d q = A eta'(q), shape q.shape + (psi.size,)."""
        return self.eta.derivatives(q_mm) @ self.A.T

    def theta(self, arclength_mm: Array, q_mm: Array) -> Array:
        """Tangent angle theta(s, q), rad, broadcasting s against q."""
        psi = self.psi.values(np.asarray(arclength_mm, dtype=float) / self.length_mm)
        return np.sum(psi * self.coefficients(q_mm), axis=-1)


def gauss_legendre_unit(order: int) -> tuple[Array, Array]:
    """Gauss-Legendre nodes and weights on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(order)
    return 0.5 * (x + 1.0), 0.5 * w


@dataclass(frozen=True)
class SegmentQuadrature:
    """Precomputed quadrature of int_0^{s_j} [cos theta, sin theta] ds for fixed upper limits.

    For upper limits ``s_j`` (mm) the nodes of every interval are stacked, so one matrix product
    per configuration gives theta at all nodes and one more the integrals for every limit.
    """

    psi_nodes: Array  # (n_nodes_total, psi.size), psi at the normalised nodes
    weights: Array  # (n_nodes_total, n_limits), node weights in mm, zero outside the interval
    psi_end: Array  # (psi.size,), psi at s = L

    @classmethod
    def build(cls, segment: ModalSegment, limits_mm: Array, order: int) -> SegmentQuadrature:
        limits = np.atleast_1d(np.asarray(limits_mm, dtype=float))
        unit_x, unit_w = gauss_legendre_unit(order)
        nodes = (limits[:, None] * unit_x[None, :]).ravel()
        weights = np.zeros((limits.size * order, limits.size))
        for j, s in enumerate(limits):
            weights[j * order : (j + 1) * order, j] = s * unit_w
        psi_nodes = segment.psi.values(nodes / segment.length_mm)
        psi_end = segment.psi.values(np.array(1.0))
        return cls(psi_nodes=psi_nodes, weights=weights, psi_end=psi_end)
