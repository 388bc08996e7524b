"""SE(2) in torch (differentiable): the same convention as deepmapping.core.se2."""

from __future__ import annotations

import torch


def compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a ∘ b for (..., 3) poses [x, y, theta]: apply b first, then a."""
    c, s = torch.cos(a[..., 2]), torch.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return torch.stack([x, y, a[..., 2] + b[..., 2]], dim=-1)


def transform(poses: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Move sensor-frame points (B, ..., 2) to the global frame with poses (B, 3)."""
    shape = (poses.shape[0],) + (1,) * (points.dim() - 2)
    c = torch.cos(poses[:, 2]).view(shape)
    s = torch.sin(poses[:, 2]).view(shape)
    x, y = points[..., 0], points[..., 1]
    gx = c * x - s * y + poses[:, 0].view(shape)
    gy = s * x + c * y + poses[:, 1].view(shape)
    return torch.stack([gx, gy], dim=-1)
