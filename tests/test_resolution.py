"""A map that follows the data: the 3D M-Net's Fourier encoding and the occupancy export voxel
from the point spacing and the map's extent (solver.resolution)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from deepmapping.config import load_config
from deepmapping.solver.resolution import export_voxel, fourier_encoding, point_spacing, resolve


def mnet(**kw):
    return load_config("default-3d", overrides={f"mnet.{k}": v for k, v in kw.items()}).mnet


def test_small_maps_keep_the_fixed_encoding():
    # bunny / AVD-like / 7-Scenes: finest period 3.4-7.8 spacings already (docs/3d.md)
    assert fourier_encoding(mnet(), spacing=0.0015, scale=0.086) == (32.0, 16)
    assert fourier_encoding(mnet(), spacing=0.0212, scale=2.641) == (32.0, 16)


def test_a_large_map_for_its_sampling_gets_finer_bands_at_the_same_log_spacing():
    # 3DTK: 1.6 cm spacing, 19 m half-extent
    f, n = fourier_encoding(mnet(), spacing=0.0165, scale=19.0)
    assert 2.0 * 19.0 / f == pytest.approx(8 * 0.0165)  # finest period = 8 spacings
    assert n > 16
    base_step = math.log(32.0) / 15
    assert math.log(f) / (n - 1) == pytest.approx(base_step, rel=0.05)  # same density of bands


def test_the_rule_is_off_when_not_asked_for_and_for_other_m_nets():
    assert fourier_encoding(mnet(fourier_period_spacings=0.0), 0.0165, 19.0) == (32.0, 16)
    assert fourier_encoding(mnet(kind="mlp"), 0.0165, 19.0) == (32.0, 16)
    assert fourier_encoding(mnet(), 0.0, 19.0) == (32.0, 16)  # no spacing measured
    assert load_config("default").mnet.fourier_period_spacings == 0  # 2D keeps its measured encoding


def test_resolve_builds_and_reports_the_encoding():
    cfg, report = resolve(mnet(), 0.0165, 19.0)
    assert cfg.fourier_max_freq == report["fourier_max_freq"] > 32 and cfg.fourier_features == report["fourier_features"]
    assert report["finest_period"] == pytest.approx(8 * 0.0165)


def test_point_spacing_of_a_regular_grid():
    g = np.stack(np.meshgrid(np.arange(20), np.arange(20), [0.0]), -1).reshape(-1, 3) * 0.05
    pts = np.stack([g, g + 1.0])
    valid = np.ones(pts.shape[:2], bool)
    valid[1, :10] = False
    assert point_spacing(pts, valid) == pytest.approx(0.05)


def test_export_voxel_is_half_the_finest_period_within_64_to_128_cells():
    assert 10.0 / export_voxel(10.0, 0.1) == pytest.approx(128)
    assert export_voxel(10.0, 0.25) == pytest.approx(0.125)  # 80 cells
    assert 10.0 / export_voxel(10.0, 1.0) == pytest.approx(64)  # coarse map: still 64 cells
    assert 10.0 / export_voxel(10.0, None) == pytest.approx(64)


def test_the_pointnet_l_net_has_its_own_learning_rate_in_the_3d_profile():
    import torch

    from deepmapping.solver.model import DeepMappingModel

    cfg = load_config("default-3d")
    clouds = torch.rand(3, 64, 3)
    init = torch.eye(4).repeat(3, 1, 1)
    valid = torch.ones(3, 64, dtype=torch.bool)
    point = DeepMappingModel(cfg, clouds, init, valid=valid, pose_dof=6)
    depth = DeepMappingModel(cfg, torch.rand(3, 48, 3), init, valid=torch.ones(3, 48, dtype=torch.bool),
                             grid_shape=(6, 8), pose_dof=3)
    assert point.lnet.kind == "pointnet" and depth.lnet.kind == "cnn"
    assert point.param_groups()[0]["lr_factor"] == cfg.lnet.pointnet_lr_factor != cfg.lnet.lr_factor
    assert depth.param_groups()[0]["lr_factor"] == cfg.lnet.lr_factor
