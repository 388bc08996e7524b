"""The two networks of DeepMapping (§3.3, §4.1): L-Net f_theta and M-Net m_phi."""

from __future__ import annotations

import math

import torch
from torch import nn

from deepmapping.config import LNetConfig, MNetConfig


class LNet(nn.Module):
    """L-Net for organized 2D scans: C(64)-C(128)-C(1024)-M(1024)-FC(512)-FC(256)-FC(3) in the paper.

    C(n): 1D atrous convolution over the beam order (kernel 3, dilation 2), ReLU.
    M: global max-pool over beams. FC: fully connected, ReLU except the output (tx, ty, theta).
    Invalid beams enter as the zero point, as in the authors' data.
    """

    def __init__(self, cfg: LNetConfig, in_dim: int = 2, out_dim: int = 3):
        super().__init__()
        layers: list[nn.Module] = []
        prev = in_dim
        pad = cfg.dilation * (cfg.kernel_size - 1) // 2
        for ch in cfg.conv_channels:
            layers += [nn.Conv1d(prev, ch, cfg.kernel_size, dilation=cfg.dilation, padding=pad), nn.ReLU()]
            prev = ch
        self.features = nn.Sequential(*layers)
        mlp: list[nn.Module] = []
        for ch in cfg.fc_channels:
            mlp += [nn.Linear(prev, ch), nn.ReLU()]
            prev = ch
        self.head = nn.Sequential(*mlp)
        self.out = nn.Linear(prev, out_dim)
        if cfg.zero_init_output:  # a warm start begins exactly at the initial poses
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    def forward(self, scans: torch.Tensor) -> torch.Tensor:
        """scans (B, N, D) in sensor frames -> poses (B, 3) = (tx, ty, theta)."""
        feat = self.features(scans.transpose(1, 2))  # (B, C, N)
        pooled = feat.amax(dim=2)  # M(n): global max-pool over beams
        return self.out(self.head(pooled))


class FourierEncoding(nn.Module):
    """Axis-aligned sin/cos features at log-spaced frequencies (period 2/f on a [-1, 1] map)."""

    def __init__(self, in_dim: int, num_freqs: int, max_freq: float):
        super().__init__()
        freqs = torch.logspace(0.0, math.log10(max(max_freq, 1.0)), num_freqs) * math.pi
        self.register_buffer("freqs", freqs)
        self.out_dim = in_dim * (1 + 2 * num_freqs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        arg = x[..., :, None] * self.freqs  # (..., D, F)
        enc = torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1).flatten(-2)
        return torch.cat([x, enc], dim=-1)


class GridEncoding(nn.Module):
    """Multi-resolution dense feature grids (2D), bilinearly interpolated and concatenated.

    Level l has a resolution growing geometrically from `base` to `finest` cells across the
    normalized map [-1, 1]^2; coarse levels give wide, smooth basins, fine ones sharp walls.
    """

    def __init__(self, levels: int, features: int, base: int, finest: int):
        super().__init__()
        growth = (finest / base) ** (1.0 / max(levels - 1, 1))
        res = [int(round(base * growth**i)) for i in range(levels)]
        self.grids = nn.ParameterList(nn.Parameter(torch.empty(1, features, r, r).uniform_(-1e-2, 1e-2)) for r in res)
        self.out_dim = levels * features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.reshape(1, 1, -1, 2)
        feats = [torch.nn.functional.grid_sample(g, flat, mode="bilinear", padding_mode="border", align_corners=True)
                 for g in self.grids]
        return torch.cat(feats, dim=1)[0, :, 0].T.reshape(*x.shape[:-1], -1)


class MNet(nn.Module):
    """M-Net: a global coordinate -> occupancy logit (sigmoid gives the probability).

    Paper: FC(64)-FC(512)-FC(512)-FC(256)-FC(128)-FC(1) on the raw coordinate ("mlp").
    "fourier" feeds a positional encoding of the coordinate to a smaller MLP; "grid" feeds
    bilinearly interpolated multi-resolution features. Either way the map stays a continuous
    function of the coordinate, queryable at any resolution.
    """

    def __init__(self, cfg: MNetConfig, in_dim: int = 2):
        super().__init__()
        self.encoding: nn.Module = nn.Identity()
        prev = in_dim
        if cfg.kind == "fourier":
            self.encoding = FourierEncoding(in_dim, cfg.fourier_features, cfg.fourier_max_freq)
            prev = self.encoding.out_dim
        elif cfg.kind == "grid":
            if in_dim != 2:
                raise ValueError("the grid M-Net is 2D only")
            self.encoding = GridEncoding(cfg.grid_levels, cfg.grid_features, cfg.grid_base, cfg.grid_finest)
            prev = self.encoding.out_dim
        layers: list[nn.Module] = []
        for ch in cfg.hidden:
            layers += [nn.Linear(prev, ch), nn.ReLU()]
            prev = ch
        layers.append(nn.Linear(prev, 1))
        self.mlp = nn.Sequential(*layers)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """xy (..., D) normalized global coordinates -> logits (...)."""
        return self.mlp(self.encoding(xy)).squeeze(-1)
