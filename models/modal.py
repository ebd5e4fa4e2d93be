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
        out = np.empty(x.shape + (self.size,))
        out[..., 0] = 1.0
        # Cumulative products, not x ** k: general pow is about 40x slower on large batches.
        for k in range(1, self.size):
            np.multiply(out[..., k - 1], x, out=out[..., k])
        return out

    def derivatives(self, x: Array) -> Array:
        powers = self.values(x)
        out = np.zeros_like(powers)
        out[..., 1:] = powers[..., :-1] * np.arange(1, self.size)
        return out


# eq=False: equality and hashing by identity; the generated field-wise versions fail on the
# ndarray field A (`==` raises "truth value of an array is ambiguous", hash raises TypeError).
@dataclass(frozen=True, eq=False)
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


@dataclass(frozen=True, eq=False)
class SegmentQuadrature:
    """Precomputed quadrature of int_0^{s_j} [cos theta, sin theta] ds for fixed upper limits.

    The distinct positive limits cut [0, max s_j] into pieces, each integrated with its own
    Gauss-Legendre rule; the integral up to s_j is the sum over the pieces below it. Repeated
    limits therefore share their nodes (the tip and the last marker are often the same
    arclength), and a limit of 0 gives a zero column. With theta at the stacked nodes,
    ``cos(theta) @ weights`` gives the integrals for every limit in one product.

    Attributes
    ----------
    psi_nodes : array, shape (n_nodes, psi.size)
        psi at the normalised nodes s_n / L (``order`` nodes per piece).
    weights : array, shape (n_nodes, n_limits)
        Node weights in mm; column j is zero for the nodes above limit j.
    psi_end : array, shape (psi.size,)
        psi at s = L.
    """

    psi_nodes: Array
    weights: Array
    psi_end: Array

    @classmethod
    def build(cls, segment: ModalSegment, limits_mm: Array, order: int) -> SegmentQuadrature:
        """Quadrature of ``segment`` for upper limits ``limits_mm`` (mm, each >= 0).

        Parameters
        ----------
        segment : ModalSegment
            The segment whose psi basis is evaluated at the nodes.
        limits_mm : float or array, shape (n_limits,)
            Upper integration limits, mm; repeats and zeros are allowed.
        order : int
            Gauss-Legendre nodes per piece.
        """
        limits = np.atleast_1d(np.asarray(limits_mm, dtype=float))
        if limits.ndim != 1 or not np.all(np.isfinite(limits)) or np.any(limits < 0.0):
            raise ValueError(f"quadrature limits must be finite, >= 0 and 1-D, got {limits}")
        boundaries = np.concatenate([[0.0], np.unique(limits[limits > 0.0])])
        starts, ends = boundaries[:-1], boundaries[1:]
        unit_x, unit_w = gauss_legendre_unit(order)
        piece = (ends - starts)[:, None]
        nodes = (starts[:, None] + piece * unit_x).ravel()
        node_weights = (piece * unit_w).ravel()
        # Limit j covers piece k when the piece ends at or below it.
        covers = np.repeat(ends[:, None] <= limits[None, :], order, axis=0)
        weights = node_weights[:, None] * covers
        psi_nodes = segment.psi.values(nodes / segment.length_mm)
        psi_end = segment.psi.values(np.array(1.0))
        for array in (psi_nodes, weights, psi_end):
            array.setflags(write=False)
        return cls(psi_nodes=psi_nodes, weights=weights, psi_end=psi_end)
