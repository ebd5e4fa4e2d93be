"""Rigid poses: the registered base frame {B} in the world frame {W} (docs/design.md section 2).

A :class:`Pose` is ``T_w_b = [R_w_b, o_b_w]``: a point ``p_b`` in {B} is ``R_w_b p_b + o_b_w``
in {W}. Every conversion between {B} and {W} (points, difference vectors, covariances) goes
through it, so the convention is written once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Array = np.ndarray


def check_rotation(R, name: str = "R") -> Array:
    """A 3x3 proper rotation matrix as float, or one ValueError naming ``name``."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"{name} must be a finite 3x3 matrix, got shape {R.shape}")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0.0:
        raise ValueError(f"{name} must be a rotation matrix (orthonormal, det +1)")
    return R


@dataclass(frozen=True, eq=False)
class Pose:
    """``T_w_b``: the rotation ``R_w_b`` and origin ``o_b_w_mm`` of {B} in {W}.

    Parameters
    ----------
    R_w_b : array, shape (3, 3)
        Rotation of {B} in {W}.
    o_b_w_mm : array, shape (3,)
        Origin of {B} in {W}, mm.
    """

    R_w_b: Array
    o_b_w_mm: Array

    def __post_init__(self) -> None:
        R = check_rotation(self.R_w_b, "R_w_b")
        o = np.asarray(self.o_b_w_mm, dtype=float)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise ValueError(f"o_b_w_mm must be a finite 3-vector, got {o!r}")
        R.setflags(write=False)
        o.setflags(write=False)
        object.__setattr__(self, "R_w_b", R)
        object.__setattr__(self, "o_b_w_mm", o)

    @classmethod
    def identity(cls) -> Pose:
        return cls(np.eye(3), np.zeros(3))

    def world_from_base(self, points_b) -> Array:
        """Points (..., 3) in {B} -> {W}, mm."""
        return np.asarray(points_b, dtype=float) @ self.R_w_b.T + self.o_b_w_mm

    def base_from_world(self, points_w) -> Array:
        """Points (..., 3) in {W} -> {B}, mm.

        Element by element (``d_x R[0] + d_y R[1] + d_z R[2]``), not a matrix product: the
        same numbers for a point whatever else is in the batch (a product of many rows may
        take another BLAS kernel, with another order of its sums, than one of a few), so
        that a batch and the same frames one by one agree bit for bit on any processor."""
        d = np.asarray(points_w, dtype=float) - self.o_b_w_mm
        R = self.R_w_b
        return d[..., 0:1] * R[0] + d[..., 1:2] * R[1] + d[..., 2:3] * R[2]

    def covariance_to_base(self, cov_w) -> Array:
        """Covariances (..., 3, 3) of points in {W} expressed in {B}: ``R_w_b^T C R_w_b``."""
        return self.R_w_b.T @ np.asarray(cov_w, dtype=float) @ self.R_w_b

    def matrix(self) -> Array:
        """The 4x4 homogeneous matrix ``T_w_b``."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R_w_b, self.o_b_w_mm
        return T
