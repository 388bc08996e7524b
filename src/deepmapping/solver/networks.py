"""The two networks of DeepMapping (§3.3, §4.1): L-Net f_theta and M-Net m_phi."""

from __future__ import annotations

import math

import torch
from torch import nn

from deepmapping.config import LNetConfig, MNetConfig, unresolved_auto
from deepmapping.solver.geometry import pose_features


class Standardize(nn.Module):
    """x -> (x - mean) / std, with the statistics of one pass over all scans at the start.

    The statistics are then fixed buffers (saved in checkpoints): unlike batch normalization a
    pose never depends on which scans share a batch, and evaluation equals training.
    """

    def __init__(self, dim: int, std_floor: float = 0.0):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))
        self.std_floor = std_floor
        self.calibrating = False

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.calibrating:
            std = x.std(0, unbiased=False)
            # a feature that barely varies over the scans must not be amplified without bound
            # once the weights move: floor its std at a fraction of the layer's mean std
            self.mean.copy_(x.mean(0))
            self.std.copy_(std.clamp(min=self.std_floor * float(std.mean())) + 1e-5)
        return (x - self.mean) / self.std


def extractor_kind(cfg: LNetConfig, in_dim: int, grid_shape: tuple[int, int] | None) -> str:
    """"cnn" or "pointnet": ``lnet.extractor``, where "auto" is a CNN for organized scans."""
    if cfg.extractor != "auto":
        return cfg.extractor
    return "cnn" if (in_dim == 2 or grid_shape is not None) else "pointnet"


def feature_extractor(cfg: LNetConfig, in_dim: int, grid_shape: tuple[int, int] | None) -> tuple[nn.Module, int]:
    """The L-Net's latent feature module (§3.3): a CNN over organized scans, PointNet otherwise.

    2D scans: 1D atrous convolutions over the beam order. Depth images (grid_shape set): 2D
    atrous convolutions. Unorganized clouds (or ``extractor="pointnet"``): a shared per-point
    MLP (PointNet without its input/feature transforms). Each layer is followed by a ReLU;
    the global max-pool comes after (in LNet).
    """
    kind = extractor_kind(cfg, in_dim, grid_shape)
    layers: list[nn.Module] = []
    prev = in_dim
    if kind == "pointnet":
        for ch in cfg.point_channels:
            layers += [nn.Conv1d(prev, ch, 1), nn.ReLU()]
            prev = ch
        return nn.Sequential(*layers), prev
    if in_dim == 3 and grid_shape is None:
        raise ValueError("the CNN L-Net needs organized scans (depth images); use extractor='pointnet'")
    conv = nn.Conv1d if in_dim == 2 else nn.Conv2d
    pad = cfg.dilation * (cfg.kernel_size - 1) // 2
    for ch in cfg.conv_channels:
        layers += [conv(prev, ch, cfg.kernel_size, stride=cfg.stride, dilation=cfg.dilation, padding=pad), nn.ReLU()]
        prev = ch
    return nn.Sequential(*layers), prev


class LNet(nn.Module):
    """L-Net f_theta: latent features of one scan, global max-pool, MLP -> the scan's pose.

    2D (§4.1): C(64)-C(128)-C(1024)-M(1024)-FC(512)-FC(256)-FC(3) -> (tx, ty, theta).
    3D (§4.2): C(64)-C(128)-C(256)-C(1024)-AM(1)-FC(512)-FC(256)-FC(3) -> (tx, tz, theta) for
    depth images, or PointNet FC(64)-FC(128)-FC(256)-FC(1024)-max-FC(512)-FC(256) (supp. A),
    with 9 outputs (translation + 6D rotation) for 6-DoF poses.
    Invalid beams enter as the zero point, as in the authors' data.
    """

    def __init__(self, cfg: LNetConfig, in_dim: int = 2, out_dim: int = 3,
                 grid_shape: tuple[int, int] | None = None):
        super().__init__()
        self.grid_shape = grid_shape
        self.kind = extractor_kind(cfg, in_dim, grid_shape)
        self.features, prev = feature_extractor(cfg, in_dim, grid_shape)
        self.pose_encoding: FourierEncoding | None = None
        if cfg.pose_input_freqs:
            self.pose_encoding = FourierEncoding(4 if in_dim == 2 else 9, cfg.pose_input_freqs,
                                                 2.0 ** (cfg.pose_input_freqs - 1))
            prev += self.pose_encoding.out_dim
        floor = cfg.feature_std_floor
        mlp: list[nn.Module] = [Standardize(prev, floor)] if cfg.feature_norm else []
        for ch in cfg.fc_channels:
            mlp += [nn.Linear(prev, ch)] + ([Standardize(ch, floor)] if cfg.feature_norm else []) + [nn.ReLU()]
            prev = ch
        self.head = nn.Sequential(*mlp)
        self.out = nn.Linear(prev, out_dim)
        if cfg.zero_init_output:  # a warm start begins exactly at the initial poses
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    @torch.no_grad()
    def calibrate(self, scans: torch.Tensor, init_poses: torch.Tensor | None = None) -> None:
        """Set the Standardize statistics from these scans, layer after layer (one forward pass)."""
        norms = [m for m in self.modules() if isinstance(m, Standardize)]
        for m in norms:
            m.calibrating = True
        try:
            self(scans, init_poses)
        finally:
            for m in norms:
                m.calibrating = False

    def forward(self, scans: torch.Tensor, init_poses: torch.Tensor | None = None) -> torch.Tensor:
        """scans (B, N, D) in sensor frames -> pose outputs (B, out_dim).

        init_poses (B, 3) or (B, 4, 4): the warm-start poses, used only when pose_input_freqs > 0."""
        x = scans.transpose(1, 2)  # (B, D, N)
        if self.grid_shape is not None and isinstance(self.features[0], nn.Conv2d):
            x = x.reshape(x.shape[0], x.shape[1], *self.grid_shape)
        pooled = self.features(x).flatten(2).amax(dim=2)  # M / AM(1): global max-pool
        if self.pose_encoding is not None:
            pooled = torch.cat([pooled, self.pose_encoding(pose_features(init_poses))], dim=1)
        return self.out(self.head(pooled))


def _open_window(weights: torch.Tensor, alpha: float) -> None:
    """BARF's raised-cosine window in place: entry k gets (1 - cos(pi * clamp(alpha - k, 0, 1))) / 2,
    so the first floor(alpha) entries are open, the next one partly, the rest shut."""
    k = torch.arange(len(weights), dtype=weights.dtype, device=weights.device)
    weights.copy_((1 - torch.cos(math.pi * (alpha - k).clamp(0.0, 1.0))) / 2)


class FourierEncoding(nn.Module):
    """Axis-aligned sin/cos features at log-spaced frequencies (period 2/f on a [-1, 1] map).

    ``progress`` in [0, 1] opens the frequency bands one after the other, coarse to fine
    (BARF, Lin et al. 2021): early on the map is smooth and its gradients reach poses that are
    far off; 1 (the default) uses every band.
    """

    def __init__(self, in_dim: int, num_freqs: int, max_freq: float):
        super().__init__()
        freqs = torch.logspace(0.0, math.log10(max(max_freq, 1.0)), num_freqs) * math.pi
        self.register_buffer("freqs", freqs)
        self.register_buffer("band_weights", torch.ones(num_freqs))
        self.out_dim = in_dim * (1 + 2 * num_freqs)

    def set_progress(self, progress: float) -> None:
        _open_window(self.band_weights, min(max(progress, 0.0), 1.0) * len(self.freqs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        arg = x[..., :, None] * self.freqs  # (..., D, F)
        w = self.band_weights
        enc = torch.cat([torch.sin(arg) * w, torch.cos(arg) * w], dim=-1).flatten(-2)
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
        self.register_buffer("level_weights", torch.ones(levels), persistent=False)  # set each epoch (trainer)
        self.out_dim = levels * features

    def set_progress(self, progress: float) -> None:
        """``mnet.coarse_to_fine`` for the grid: the levels open one after the other, as FourierEncoding's
        bands; progress 0 keeps the coarsest level alone, 1 (the default) uses every level."""
        _open_window(self.level_weights, 1.0 + min(max(progress, 0.0), 1.0) * (len(self.grids) - 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.reshape(1, 1, -1, 2)
        feats = [w * torch.nn.functional.grid_sample(g, flat, mode="bilinear", padding_mode="border", align_corners=True)
                 for g, w in zip(self.grids, self.level_weights)]
        return torch.cat(feats, dim=1)[0, :, 0].T.reshape(*x.shape[:-1], -1)


class ResidualBlock(nn.Module):
    """RB(n) of the supplementary's ResMLP (He et al.'s basic block with FC layers):
    relu(FC(n)(relu(FC(n)(x))) + shortcut(x)); the shortcut is the identity, or a linear
    projection when the input width is not n."""

    def __init__(self, in_dim: int, width: int):
        super().__init__()
        self.fc1 = nn.Linear(in_dim, width)
        self.fc2 = nn.Linear(width, width)
        self.shortcut: nn.Module = nn.Identity() if in_dim == width else nn.Linear(in_dim, width, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.fc2(torch.relu(self.fc1(x))) + self.shortcut(x))


class MNet(nn.Module):
    """M-Net: a global coordinate -> occupancy logit (sigmoid gives the probability).

    Paper: FC(64)-FC(512)-FC(512)-FC(256)-FC(128)-FC(1) on the raw coordinate ("mlp").
    "resmlp" (supplementary A): one residual block RB(n) per entry n of ``hidden``, then FC(1).
    "fourier" feeds a positional encoding of the coordinate to a smaller MLP; "grid" feeds
    bilinearly interpolated multi-resolution features. Either way the map stays a continuous
    function of the coordinate, queryable at any resolution.
    """

    def __init__(self, cfg: MNetConfig, in_dim: int = 2):
        super().__init__()
        self.encoding: nn.Module = nn.Identity()
        prev = in_dim
        kind = unresolved_auto(cfg.kind, "mnet.kind")  # "auto" unresolved (a model built directly)
        if kind == "fourier":
            self.encoding = FourierEncoding(in_dim, cfg.fourier_features, cfg.fourier_max_freq)
            prev = self.encoding.out_dim
        elif kind == "grid":
            if in_dim != 2:
                raise ValueError("the grid M-Net is 2D only")
            self.encoding = GridEncoding(cfg.grid_levels, cfg.grid_features, cfg.grid_base, cfg.grid_finest)
            prev = self.encoding.out_dim
        layers: list[nn.Module] = []
        for ch in cfg.hidden:
            layers += [ResidualBlock(prev, ch)] if kind == "resmlp" else [nn.Linear(prev, ch), nn.ReLU()]
            prev = ch
        layers.append(nn.Linear(prev, 1))
        self.mlp = nn.Sequential(*layers)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """xy (..., D) normalized global coordinates -> logits (...)."""
        return self.mlp(self.encoding(xy)).squeeze(-1)
