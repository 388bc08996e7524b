"""DeepMapping loss: L_cls (eq. 4) + lambda * L_ch (eq. 5-7)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp(min=1)


def occupancy_bce(occ_logits: torch.Tensor, occ_mask: torch.Tensor,
                  free_logits: torch.Tensor, free_mask: torch.Tensor) -> torch.Tensor:
    """Eq. 4 with logits: mean BCE of occupied samples against 1 plus free samples against 0.

    Masks drop samples of invalid beams (no return) from both means.
    """
    occ = F.binary_cross_entropy_with_logits(occ_logits, torch.ones_like(occ_logits), reduction="none")
    free = F.binary_cross_entropy_with_logits(free_logits, torch.zeros_like(free_logits), reduction="none")
    return masked_mean(occ, occ_mask) + masked_mean(free, free_mask)


def _matched_distance(x, xv, y, idx) -> torch.Tensor:
    """Mean over valid x of the distance to y[idx] (with gradient), per pair."""
    matched = y.gather(1, idx[..., None].expand(-1, -1, y.shape[2]))
    dist = ((x - matched).pow(2).sum(-1) + 1e-12).sqrt()
    return (dist * xv).sum(1) / xv.sum(1).clamp(min=1)


def chamfer(x: torch.Tensor, xv: torch.Tensor, y: torch.Tensor, yv: torch.Tensor) -> torch.Tensor:
    """Eq. 5 for P pairs at once: x (P, N, D), y (P, M, D) with validity masks -> (P,).

    Two-way mean Euclidean distance to the nearest point of the other cloud; invalid points
    neither count nor serve as neighbours. Nearest neighbours are searched without gradient
    and the distances to them re-evaluated with gradient (same value and gradient).
    """
    with torch.no_grad():
        d = torch.cdist(x, y)
        d = d.masked_fill(~yv[:, None, :], float("inf")).masked_fill(~xv[:, :, None], float("inf"))
        x_to_y, y_to_x = d.argmin(dim=2), d.argmin(dim=1)
    has = (xv.any(1) & yv.any(1)).to(x.dtype)
    return (_matched_distance(x, xv, y, x_to_y) + _matched_distance(y, yv, x, y_to_x)) * has


def temporal_pairs(indices: torch.Tensor, window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (a, b) in a batch whose scans are temporal neighbours: 0 < i_b - i_a <= window."""
    diff = indices[None, :] - indices[:, None]
    a, b = torch.nonzero((diff > 0) & (diff <= window), as_tuple=True)
    return a, b


def chamfer_loss(glob: torch.Tensor, valid: torch.Tensor, indices: torch.Tensor, window: int) -> torch.Tensor:
    """Eq. 7 averaged over the neighbour pairs present in the batch (0 when there are none)."""
    a, b = temporal_pairs(indices, window)
    if a.numel() == 0:
        return glob.new_zeros(())
    return chamfer(glob[a], valid[a], glob[b], valid[b]).mean()
