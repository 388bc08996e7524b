"""Poses in torch (differentiable), the same conventions as deepmapping.geometry.se2 / geometry.se3.

2D poses are (..., 3) [x, y, theta]. 3D poses are (..., 4, 4) sensor-to-global matrices; the
L-Net's 3D output is a correction, either planar [dx, dz, dtheta] about the vertical y axis
(AVD, 3-DoF) or [dt (3), d6 (6)] with the rotation in Zhou et al.'s continuous 6D form
(6-DoF; see docs/method.md for why 6D rather than quaternions).
"""

from __future__ import annotations

import torch

IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a ∘ b for (..., 3) poses [x, y, theta]: apply b first, then a."""
    c, s = torch.cos(a[..., 2]), torch.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return torch.stack([x, y, a[..., 2] + b[..., 2]], dim=-1)


def transform(poses: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Move sensor-frame points (B, ..., D) to the global frame with poses (B, 3) or (B, 4, 4)."""
    if poses.dim() == 3:
        rot, t = poses[:, :3, :3], poses[:, :3, 3]
        flat = points.reshape(points.shape[0], -1, 3)
        return (flat @ rot.transpose(1, 2) + t[:, None, :]).reshape(points.shape)
    shape = (poses.shape[0],) + (1,) * (points.dim() - 2)
    c = torch.cos(poses[:, 2]).view(shape)
    s = torch.sin(poses[:, 2]).view(shape)
    x, y = points[..., 0], points[..., 1]
    gx = c * x - s * y + poses[:, 0].view(shape)
    gy = s * x + c * y + poses[:, 1].view(shape)
    return torch.stack([gx, gy], dim=-1)


def rotate(poses: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """Turn sensor-frame directions (B, N, D) (normals) with poses (B, 3) or (B, 4, 4): no translation."""
    if poses.dim() == 3:
        return vectors @ poses[:, :3, :3].transpose(1, 2)
    return transform(torch.cat([torch.zeros_like(poses[:, :2]), poses[:, 2:]], 1), vectors)


def _matrix(rot: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    bottom = torch.zeros(rot.shape[:-2] + (1, 4), dtype=rot.dtype, device=rot.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([torch.cat([rot, t[..., :, None]], dim=-1), bottom], dim=-2)


def inverse(m: torch.Tensor) -> torch.Tensor:
    """(B, 4, 4) rigid transforms -> their inverses (as geometry.se3.inverse)."""
    rot_t = m[:, :3, :3].transpose(1, 2)
    return _matrix(rot_t, -(rot_t @ m[:, :3, 3:])[..., 0])


def relative(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a^-1 b for (B, 4, 4) poses: b in a's frame (as geometry.se3.relative)."""
    return inverse(a) @ b


def translation(t: torch.Tensor) -> torch.Tensor:
    """(B, 3) -> (B, 4, 4) pure translations."""
    return _matrix(torch.eye(3, dtype=t.dtype, device=t.device).expand(t.shape[0], 3, 3), t)


def planar_matrix(p: torch.Tensor) -> torch.Tensor:
    """(B, 3) [x, z, theta] (theta about the vertical y axis) -> (B, 4, 4)."""
    c, s = torch.cos(p[:, 2]), torch.sin(p[:, 2])
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    rot = torch.stack([c, zero, s, zero, one, zero, -s, zero, c], dim=-1).view(-1, 3, 3)
    return _matrix(rot, torch.stack([p[:, 0], zero, p[:, 1]], dim=-1))


def rotation_from_6d(six: torch.Tensor) -> torch.Tensor:
    """(B, 6) two columns -> rotation (B, 3, 3) by Gram-Schmidt; the third column is their cross product."""
    a, b = six[:, :3], six[:, 3:]
    c1 = a / a.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    b = b - (c1 * b).sum(-1, keepdim=True) * c1
    c2 = b / b.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    return torch.stack([c1, c2, torch.cross(c1, c2, dim=-1)], dim=-1)


def six_dof_matrix(v: torch.Tensor) -> torch.Tensor:
    """(B, 9) [t (3), delta 6D (6)] -> (B, 4, 4); v = 0 is the identity (the 6D part is a residual)."""
    six = v[:, 3:] + torch.tensor(IDENTITY_6D, dtype=v.dtype, device=v.device)
    return _matrix(rotation_from_6d(six), v[:, :3])


def correction_matrix(v: torch.Tensor) -> torch.Tensor:
    """An L-Net 3D output (B, 3) planar or (B, 9) 6-DoF -> (B, 4, 4)."""
    return planar_matrix(v) if v.shape[1] == 3 else six_dof_matrix(v)


def pose_features(init_poses: torch.Tensor) -> torch.Tensor:
    """What the L-Net sees of a warm-start pose: 2D (x, y, cos, sin); 3D (t, first two columns of R)."""
    if init_poses.dim() == 3:
        return torch.cat([init_poses[:, :3, 3], init_poses[:, :3, :2].transpose(1, 2).reshape(-1, 6)], dim=1)
    th = init_poses[:, 2:]
    return torch.cat([init_poses[:, :2], torch.cos(th), torch.sin(th)], dim=1)
