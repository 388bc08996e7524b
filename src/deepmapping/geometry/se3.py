"""Vectorised SE(3) helpers on 4x4 homogeneous matrices (first step of the 3D issue, #4).

A pose T maps a sensor-frame point p to the global frame: ``R @ p + t``; ``compose(a, b)``
= apply b first, then a (``T_a @ T_b``), as in ``geometry/se2.py``. Arrays of shape (..., 4, 4)
broadcast over the leading axes. Quaternions are scalar-last ``[qx, qy, qz, qw]`` (SciPy's
and TUM's order). AVD-style 3-DoF poses ``[x, z, theta]`` rotate about the vertical y axis.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def _as_matrices(T) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"poses must have shape (..., 4, 4), got {T.shape}")
    return T


def identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    return np.broadcast_to(np.eye(4), tuple(shape) + (4, 4)).copy()


def from_rt(rot, t) -> np.ndarray:
    """Rotation matrices (..., 3, 3) and translations (..., 3) -> poses (..., 4, 4)."""
    rot, t = np.asarray(rot, dtype=np.float64), np.asarray(t, dtype=np.float64)
    out = identity(np.broadcast_shapes(rot.shape[:-2], t.shape[:-1]))
    out[..., :3, :3], out[..., :3, 3] = rot, t
    return out


def compose(a, b) -> np.ndarray:
    return _as_matrices(a) @ _as_matrices(b)


def inverse(T) -> np.ndarray:
    T = _as_matrices(T)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return from_rt(rt, -(rt @ T[..., :3, 3:])[..., 0])


def relative(a, b) -> np.ndarray:
    """a^-1 b: the pose of b in the frame of a."""
    return compose(inverse(a), b)


def transform_points(T, points) -> np.ndarray:
    """Poses (..., 4, 4) applied to points (..., N, 3)."""
    T, points = _as_matrices(T), np.asarray(points, dtype=np.float64)
    return points @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def from_xyz_quat(xyz_quat) -> np.ndarray:
    """(..., 7) ``[x, y, z, qx, qy, qz, qw]`` (TUM order) -> (..., 4, 4); quaternions are normalized."""
    q = np.asarray(xyz_quat, dtype=np.float64)
    if q.shape[-1] != 7:
        raise ValueError(f"expected (..., 7) [x y z qx qy qz qw], got {q.shape}")
    quat = q[..., 3:].reshape(-1, 4)
    scale = np.abs(quat).max(axis=1, keepdims=True)
    quat = quat / np.where(scale > 0, scale, 1.0)  # to ~1 first: |q|^2 of huge components (1e200) overflows
    rot = Rotation.from_quat(quat).as_matrix().reshape(q.shape[:-1] + (3, 3))
    return from_rt(rot, q[..., :3])


def to_xyz_quat(T) -> np.ndarray:
    """(..., 4, 4) -> (..., 7) ``[x, y, z, qx, qy, qz, qw]`` with qw >= 0."""
    T = _as_matrices(T)
    q = Rotation.from_matrix(T[..., :3, :3].reshape(-1, 3, 3)).as_quat().reshape(T.shape[:-2] + (4,))
    q = np.where(q[..., 3:] < 0, -q, q)
    return np.concatenate([T[..., :3, 3], q], axis=-1)


def from_planar_xz(poses) -> np.ndarray:
    """AVD-style 3-DoF poses (..., 3) ``[x, z, theta]``, theta about the vertical y axis -> (..., 4, 4)."""
    p = np.asarray(poses, dtype=np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    rot = np.zeros(p.shape[:-1] + (3, 3))
    rot[..., 0, 0], rot[..., 0, 2], rot[..., 1, 1], rot[..., 2, 0], rot[..., 2, 2] = c, s, 1.0, -s, c
    t = np.stack([p[..., 0], np.zeros_like(p[..., 0]), p[..., 1]], axis=-1)
    return from_rt(rot, t)


def rotation_from_6d(six) -> np.ndarray:
    """Zhou et al.'s continuous 6D representation (..., 6) = two columns -> rotations (..., 3, 3).

    Gram-Schmidt on the two 3-vectors; the third column is their cross product.
    """
    six = np.asarray(six, dtype=np.float64)
    a, b = six[..., :3], six[..., 3:]
    c1 = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b - (c1 * b).sum(-1, keepdims=True) * c1
    c2 = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.stack([c1, c2, np.cross(c1, c2)], axis=-1)


def rotation_angle_deg(rot) -> np.ndarray:
    """Angle (degrees) of rotation matrices (..., 3, 3), robust near 0 and 180."""
    return np.degrees(np.linalg.norm(Rotation.from_matrix(np.reshape(rot, (-1, 3, 3))).as_rotvec(), axis=-1)
                      ).reshape(np.shape(rot)[:-2])
