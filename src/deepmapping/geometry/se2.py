"""Vectorised SE(2) helpers on ``[x, y, theta]`` poses (see docs/conventions.md).

A pose maps a sensor-frame point p to the global frame: ``R(theta) @ p + [x, y]``.
Composition ``compose(a, b)`` = apply b first, then a (matrix product ``T_a @ T_b``).
All functions accept arrays of shape (..., 3) and broadcast over the leading axes.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "identity",
    "wrap_angle",
    "rotation",
    "to_matrix",
    "to_se3",
    "from_matrix",
    "compose",
    "inverse",
    "relative",
    "transform_points",
    "chain",
]


def _as_poses(p) -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"poses must have shape (..., 3), got {p.shape}")
    return p


def identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    """Identity pose(s) of shape ``shape + (3,)``."""
    return np.zeros(tuple(shape) + (3,), dtype=np.float64)


def wrap_angle(theta) -> np.ndarray:
    """Wrap angles (radians) to (-pi, pi]."""
    theta = np.asarray(theta, dtype=np.float64)
    wrapped = np.mod(theta + np.pi, 2.0 * np.pi) - np.pi  # in [-pi, pi)
    return np.where(wrapped <= -np.pi, wrapped + 2.0 * np.pi, wrapped)


def rotation(theta) -> np.ndarray:
    """Rotation matrices R(theta), shape (..., 2, 2)."""
    theta = np.asarray(theta, dtype=np.float64)
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def to_matrix(poses) -> np.ndarray:
    """(..., 3) poses -> (..., 3, 3) homogeneous matrices."""
    p = _as_poses(poses)
    m = np.zeros(p.shape[:-1] + (3, 3), dtype=np.float64)
    m[..., :2, :2] = rotation(p[..., 2])
    m[..., 0, 2] = p[..., 0]
    m[..., 1, 2] = p[..., 1]
    m[..., 2, 2] = 1.0
    return m


def to_se3(poses) -> np.ndarray:
    """(..., 3) planar poses [x, y, theta] -> (..., 4, 4) (z = 0, rotation about z)."""
    m2 = to_matrix(poses)
    m = np.zeros(m2.shape[:-2] + (4, 4), dtype=np.float64)
    m[..., :2, :2] = m2[..., :2, :2]
    m[..., :2, 3] = m2[..., :2, 2]
    m[..., 2, 2] = m[..., 3, 3] = 1.0
    return m


def from_matrix(matrices) -> np.ndarray:
    """(..., 3, 3) homogeneous matrices -> (..., 3) poses (angle wrapped)."""
    m = np.asarray(matrices, dtype=np.float64)
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"matrices must have shape (..., 3, 3), got {m.shape}")
    theta = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.stack([m[..., 0, 2], m[..., 1, 2], wrap_angle(theta)], -1)


def compose(a, b) -> np.ndarray:
    """a ∘ b (apply b first, then a); broadcasts over leading axes."""
    a, b = _as_poses(a), _as_poses(b)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], -1)


def inverse(a) -> np.ndarray:
    """Inverse pose: compose(inverse(a), a) = identity."""
    a = _as_poses(a)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], -1)


def relative(a, b) -> np.ndarray:
    """inverse(a) ∘ b: pose of frame b expressed in frame a."""
    return compose(inverse(a), b)


def transform_points(poses, points) -> np.ndarray:
    """Map sensor-frame points to the global frame.

    poses (K, 3) with points (K, N, 2) -> (K, N, 2); a single pose (3,) with points (N, 2)
    -> (N, 2). More generally poses (..., 3) broadcast against points (..., N, 2).
    """
    p = _as_poses(poses)
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1] != 2:
        raise ValueError(f"points must have shape (..., N, 2), got {pts.shape}")
    c = np.cos(p[..., 2])[..., None]
    s = np.sin(p[..., 2])[..., None]
    x = c * pts[..., 0] - s * pts[..., 1] + p[..., 0][..., None]
    y = s * pts[..., 0] + c * pts[..., 1] + p[..., 1][..., None]
    return np.stack([x, y], -1)


def chain(relatives, first=None) -> np.ndarray:
    """Accumulate relative motions into absolute poses.

    relatives (K-1, 3) with rel_i = relative(T_i, T_{i+1}); returns (K, 3) with
    T_0 = first (identity by default) and T_{i+1} = T_i ∘ rel_i. The translation of rel_i
    is rotated by the rotation of T_i (not the already-updated one).
    """
    rel = _as_poses(relatives)
    if rel.ndim != 2:
        raise ValueError(f"relatives must have shape (K-1, 3), got {rel.shape}")
    out = np.empty((rel.shape[0] + 1, 3), dtype=np.float64)
    out[0] = identity() if first is None else _as_poses(first)
    for i in range(rel.shape[0]):
        out[i + 1] = compose(out[i], rel[i])
    return out
