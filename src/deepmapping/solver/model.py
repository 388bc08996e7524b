"""Where poses come from: the L-Net (DeepMapping) or free per-scan parameters (direct optimization)."""

from __future__ import annotations

import torch
from torch import nn

from deepmapping.config import Config
from deepmapping.solver.geometry import compose
from deepmapping.solver.networks import LNet, MNet


class DeepMappingModel(nn.Module):
    """T_i = T_init_i ∘ f_theta(S_i) (warm start, §3.5); T_init = identity for a cold start."""

    def __init__(self, cfg: Config, scans: torch.Tensor, init_poses: torch.Tensor):
        super().__init__()
        self.lnet = LNet(cfg.lnet, in_dim=scans.shape[2])
        self.mnet = MNet(cfg.mnet, in_dim=scans.shape[2])
        self.register_buffer("scans", scans)
        self.register_buffer("init_poses", init_poses)
        self.direct_poses: nn.Parameter | None = None
        self.mnet_lr_factor = cfg.mnet.lr_factor
        self.lnet_lr_factor = cfg.lnet.lr_factor
        if cfg.lnet.feature_norm:  # statistics from (an even spread of at most 512 of) all scans
            k = scans.shape[0]
            spread = torch.linspace(0, k - 1, min(k, 512), device=scans.device).long()
            self.lnet.calibrate(scans[spread], init_poses[spread])

    def poses(self, idx: torch.Tensor) -> torch.Tensor:
        if self.direct_poses is not None:
            return self.direct_poses[idx]
        return compose(self.init_poses[idx], self.lnet(self.scans[idx], self.init_poses[idx]))

    @torch.no_grad()
    def all_poses(self, chunk: int = 256) -> torch.Tensor:
        k = self.scans.shape[0]
        idx = torch.arange(k, device=self.scans.device)
        return torch.cat([self.poses(idx[i : i + chunk]) for i in range(0, k, chunk)])

    def make_direct(self) -> None:
        """Direct optimization baseline: drop the L-Net from the problem and optimize the poses
        themselves, starting from one forward pass of the L-Net (as the paper does)."""
        self.direct_poses = nn.Parameter(self.all_poses().clone())

    def param_groups(self) -> list[dict]:
        """Two optimizer groups: what produces the poses (L-Net or direct poses), and the M-Net."""
        if self.direct_poses is not None:
            pose_group = {"params": [self.direct_poses], "name": "poses", "lr_factor": 1.0}
        else:
            pose_group = {"params": list(self.lnet.parameters()), "name": "poses", "lr_factor": self.lnet_lr_factor}
        return [pose_group,
                {"params": list(self.mnet.parameters()), "name": "mnet", "lr_factor": self.mnet_lr_factor}]
