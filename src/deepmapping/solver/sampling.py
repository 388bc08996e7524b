"""Occupied and free-space samples (§3.2, Fig. 3).

Occupied: the scan points themselves (label 1). Free: points drawn on each beam between the
sensor centre (the origin of the sensor frame, i.e. the estimated sensor position once moved
to the global frame) and the hit (label 0), drawn afresh every forward pass, independently
per beam.
"""

from __future__ import annotations

import torch


def select_beams(points: torch.Tensor, valid: torch.Tensor, count: int | None, gen: torch.Generator):
    """A random subset of `count` beams per scan (all beams when count is None or >= N)."""
    n = points.shape[1]
    if count is None or count >= n:
        return points, valid
    # rank valid beams first (random order among them) so every scan gets valid samples
    keys = torch.rand(valid.shape, generator=gen, device=points.device) + (~valid).float()
    idx = keys.argsort(dim=1)[:, :count]
    return points.gather(1, idx[..., None].expand(-1, -1, points.shape[2])), valid.gather(1, idx)


def free_space_fractions(shape: tuple[int, ...], samples: int, mode: str, gen: torch.Generator, device) -> torch.Tensor:
    """Fractions t in [0, 1) along each beam, (…, samples). 'stratified': one per 1/samples bin."""
    u = torch.rand(shape + (samples,), generator=gen, device=device)
    if mode == "stratified":
        return (torch.arange(samples, device=device) + u) / samples
    return u


def near_hit_fractions(points: torch.Tensor, samples: int, distance: float, gen: torch.Generator) -> torch.Tensor:
    """Fractions of free-space samples within `distance` before each hit: (B, N, samples).

    Still on the beam between sensor and hit (label 0); they concentrate where a misaligned
    scan's wall contradicts another scan's line of sight.
    """
    rng = points.norm(dim=-1, keepdim=True).clamp(min=1e-9)
    u = torch.rand(points.shape[:2] + (samples,), generator=gen, device=points.device)
    return (1.0 - u * distance / rng).clamp(min=0.0)


def free_space_points(points: torch.Tensor, fractions: torch.Tensor) -> torch.Tensor:
    """Sensor-frame free-space samples t·p on the segment from the sensor (origin) to p: (B, N, S, D)."""
    return points[:, :, None, :] * fractions[..., None]
