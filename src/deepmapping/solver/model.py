"""Where poses come from: the L-Net (DeepMapping) or free per-scan parameters (direct optimization)."""

from __future__ import annotations

import torch
from torch import nn

from deepmapping.config import Config, unresolved_auto
from deepmapping.solver.geometry import compose, correction_matrix, translation
from deepmapping.solver.networks import LNet, MNet
from deepmapping.solver.resolution import resolve_step


def fill_invalid(scans: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Unorganized clouds for PointNet: each invalid (padding) point becomes a copy of a valid
    point of the same scan, so the max-pool sees exactly the scan's points."""
    first = valid.float().argmax(dim=1)  # index of a valid point per scan
    anchor = scans[torch.arange(scans.shape[0], device=scans.device), first]
    return torch.where(valid[..., None], scans, anchor[:, None, :])


def centroids(scans: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(K, 3) mean of each scan's valid points (in its sensor frame)."""
    w = valid[..., None].to(scans.dtype)
    return (scans * w).sum(1) / w.sum(1).clamp(min=1)


class DeepMappingModel(nn.Module):
    """T_i = T_init_i ∘ f_theta(S_i) (warm start, §3.5); T_init = identity for a cold start.

    2D poses are (K, 3); 3D poses (K, 4, 4) with a planar (3-DoF) or 6-DoF correction.
    """

    constant_buffers = ("scans", "lnet_scans", "pivot")  # never change: snapshots share them

    def __init__(self, cfg: Config, scans: torch.Tensor, init_poses: torch.Tensor,
                 valid: torch.Tensor | None = None, grid_shape: tuple[int, int] | None = None, pose_dof: int = 3):
        super().__init__()
        dim = scans.shape[2]
        self.is_3d = init_poses.dim() == 3
        out_dim = 9 if (self.is_3d and pose_dof == 6) else 3
        lnet_cfg = resolve_step(cfg, scans.shape[1], grid_shape).lnet  # its stride "auto" made a number
        self.lnet = LNet(lnet_cfg, in_dim=dim, out_dim=out_dim, grid_shape=grid_shape)
        self.mnet = MNet(cfg.mnet, in_dim=dim)
        self.register_buffer("scans", scans)
        lnet_in = scans if (grid_shape is not None or dim == 2 or valid is None) else fill_invalid(scans, valid)
        self.register_buffer("lnet_scans", lnet_in)
        self.register_buffer("init_poses", init_poses)
        use_pivot = self.is_3d and cfg.lnet.pivot == "centroid" and valid is not None
        self.register_buffer("pivot", centroids(scans, valid) if use_pivot else None)
        self.direct_poses: nn.Parameter | None = None
        self.mnet_lr_factor = cfg.mnet.lr_factor
        use_point_rate = self.lnet.kind == "pointnet" and cfg.lnet.pointnet_lr_factor is not None
        lnet_rate = unresolved_auto(cfg.lnet.lr_factor, "lnet.lr_factor")  # api.register resolves "auto" first
        self.lnet_lr_factor = cfg.lnet.pointnet_lr_factor if use_point_rate else lnet_rate
        if cfg.lnet.feature_norm:
            self.calibrate_lnet()

    def calibrate_lnet(self) -> None:
        """Standardization statistics from (an even spread of at most 512 of) all scans and their init poses."""
        k = self.scans.shape[0]
        spread = torch.linspace(0, k - 1, min(k, 512), device=self.scans.device).long()
        self.lnet.calibrate(self.lnet_scans[spread], self.init_poses[spread])

    def _with_correction(self, idx: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        return self._compose(self.init_poses[idx], out, None if self.pivot is None else self.pivot[idx])

    def _compose(self, init: torch.Tensor, out: torch.Tensor, pivot: torch.Tensor | None) -> torch.Tensor:
        if not self.is_3d:
            return compose(init, out)
        if pivot is None:
            return init @ correction_matrix(out)
        # the correction turns the scan about its centroid (pivot), not about the sensor
        return init @ translation(pivot) @ correction_matrix(out) @ translation(-pivot)

    @torch.no_grad()
    def localize(self, scans: torch.Tensor, valid: torch.Tensor, init_poses: torch.Tensor) -> torch.Tensor:
        """Poses of scans the model was not built with (normalized frame, as ``poses``): the
        trained L-Net on each scan, composed with its prior pose ``init_poses`` as in training
        (T = T_init ∘ f_theta(S)); the identity prior for a cold-started model."""
        lnet_in = scans if (self.lnet.grid_shape is not None or scans.shape[2] == 2) else fill_invalid(scans, valid)
        pivot = centroids(scans, valid) if self.pivot is not None else None
        return self._compose(init_poses, self.lnet(lnet_in, init_poses), pivot)

    def poses(self, idx: torch.Tensor) -> torch.Tensor:
        if self.direct_poses is not None:
            if self.is_3d:  # 3D direct parameters are the corrections themselves
                return self._with_correction(idx, self.direct_poses[idx])
            return self.direct_poses[idx]
        return self._with_correction(idx, self.lnet(self.lnet_scans[idx], self.init_poses[idx]))

    @torch.no_grad()
    def all_poses(self, chunk: int = 256) -> torch.Tensor:
        k = self.scans.shape[0]
        idx = torch.arange(k, device=self.scans.device)
        return torch.cat([self.poses(idx[i : i + chunk]) for i in range(0, k, chunk)])

    @torch.no_grad()
    def _all_corrections(self, chunk: int = 256) -> torch.Tensor:
        k = self.scans.shape[0]
        return torch.cat([self.lnet(self.lnet_scans[i : i + chunk], self.init_poses[i : i + chunk])
                          for i in range(0, k, chunk)])

    def make_direct(self) -> None:
        """Direct optimization baseline: drop the L-Net from the problem and optimize the poses
        themselves, starting from one forward pass of the L-Net (as the paper does)."""
        start = self._all_corrections() if self.is_3d else self.all_poses()
        self.direct_poses = nn.Parameter(start.clone())

    def param_groups(self) -> list[dict]:
        """Two optimizer groups: what produces the poses (L-Net or direct poses), and the M-Net."""
        if self.direct_poses is not None:
            pose_group = {"params": [self.direct_poses], "name": "poses", "lr_factor": 1.0}
        else:
            pose_group = {"params": list(self.lnet.parameters()), "name": "poses", "lr_factor": self.lnet_lr_factor}
        return [pose_group,
                {"params": list(self.mnet.parameters()), "name": "mnet", "lr_factor": self.mnet_lr_factor}]
