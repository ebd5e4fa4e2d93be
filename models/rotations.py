"""Rotations about the coordinate axes and the one shared angle-wrapping helper.

All functions are vectorised over leading batch axes and use radians.
"""

from __future__ import annotations

import math

import numpy as np

Array = np.ndarray


def wrap_angle(angle_rad: Array | float) -> Array | float:
    """Wrap angles to [-pi, pi).

    Every estimated or compared angle in the project goes through this function, and errors
    between angles are ``wrap_angle(a - b)``.
    """
    if isinstance(angle_rad, float):
        # One angle (a frame's estimate): Python's float % is np.mod's arithmetic, without
        # its per-call overhead.
        return (float(angle_rad) + math.pi) % (2.0 * math.pi) - math.pi
    wrapped = np.mod(np.asarray(angle_rad, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    if np.ndim(wrapped) == 0:
        return float(wrapped)
    return wrapped


def deg_from_rad(angle_rad: Array | float) -> Array | float:
    """Degrees from radians (for reports and command-line output only)."""
    return np.degrees(angle_rad)


def rot_z(angle_rad: Array | float) -> Array:
    """Rotation matrices about z, shape (..., 3, 3)."""
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    zero, one = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)],
        -2,
    )


def rot_y(angle_rad: Array | float) -> Array:
    """Rotation matrices about y, shape (..., 3, 3)."""
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    zero, one = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1), np.stack([-s, zero, c], -1)],
        -2,
    )


def rotate_z(vectors: Array, angle_rad: Array | float) -> Array:
    """Rotate vectors (..., 3) about z by angles broadcastable to their batch shape."""
    v = np.asarray(vectors, dtype=float)
    a = np.asarray(angle_rad, dtype=float)[..., None]
    c, s = np.cos(a)[..., 0], np.sin(a)[..., 0]
    out = np.empty(np.broadcast_shapes(v.shape, a.shape[:-1] + (3,)))
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    out[..., 2] = v[..., 2]
    return out


def skew(v: Array) -> Array:
    """Skew-symmetric cross-product matrices, (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    zero = np.zeros_like(v[..., 0])
    return np.stack(
        [
            np.stack([zero, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], zero, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], zero], -1),
        ],
        -2,
    )
