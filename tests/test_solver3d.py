"""3D solver pieces: pose parameterizations, L-Net variants, padding, and a small 6-DoF registration."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from deepmapping.config import load_config
from deepmapping.geometry import se3
from deepmapping.solver.geometry import correction_matrix, planar_matrix, rotation_from_6d, six_dof_matrix, transform
from deepmapping.solver.model import DeepMappingModel, fill_invalid
from deepmapping.solver.networks import LNet


def test_planar_matrix_matches_the_avd_convention():
    p = np.array([[0.3, -1.2, 0.7], [2.0, 0.5, -2.5]])
    np.testing.assert_allclose(planar_matrix(torch.tensor(p)).numpy(), se3.from_planar_xz(p), atol=1e-12)


def test_six_dof_correction_is_identity_at_zero_and_a_rotation_elsewhere():
    np.testing.assert_allclose(six_dof_matrix(torch.zeros(2, 9, dtype=torch.float64)).numpy(), se3.identity((2,)))
    rot = rotation_from_6d(torch.randn(50, 6, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    # the 6D form is the first two columns: it reproduces any rotation exactly
    r = Rotation.random(5, random_state=1).as_matrix()
    six = torch.tensor(np.concatenate([r[:, :, 0], r[:, :, 1]], axis=1))
    np.testing.assert_allclose(rotation_from_6d(six).numpy(), r, atol=1e-12)
    assert correction_matrix(torch.zeros(3, 3)).shape == (3, 4, 4)


def test_transform_3d_matches_numpy():
    poses = se3.from_rt(Rotation.random(3, random_state=0).as_matrix(), np.random.default_rng(0).normal(size=(3, 3)))
    pts = np.random.default_rng(1).normal(size=(3, 7, 3))
    out = transform(torch.tensor(poses), torch.tensor(pts)).numpy()
    np.testing.assert_allclose(out, se3.transform_points(poses, pts), atol=1e-12)
    # free-space samples have an extra axis: (B, N, S, 3)
    assert transform(torch.tensor(poses), torch.tensor(pts)[:, :, None].expand(-1, -1, 4, -1)).shape == (3, 7, 4, 3)


def test_lnet_variants_output_planar_or_six_dof_corrections():
    cfg = load_config("default-3d").lnet
    depth = LNet(cfg, in_dim=3, out_dim=3, grid_shape=(12, 16))
    assert isinstance(depth.features[0], torch.nn.Conv2d)
    init = torch.eye(4).expand(2, 4, 4)
    assert depth(torch.randn(2, 192, 3), init).shape == (2, 3)
    cloud = LNet(cfg, in_dim=3, out_dim=9)
    assert isinstance(cloud.features[0], torch.nn.Conv1d) and cloud.features[0].kernel_size == (1,)
    assert cloud(torch.randn(2, 50, 3), init).shape == (2, 9)
    with pytest.raises(ValueError, match="organized"):
        LNet(cfg.model_copy(update={"extractor": "cnn"}), in_dim=3)


def test_pointnet_sees_only_the_scan_not_its_padding():
    torch.manual_seed(0)
    cfg = load_config("default-3d").model_copy(deep=True)
    cfg.lnet.zero_init_output, cfg.lnet.feature_norm = False, False
    pts = torch.randn(1, 40, 3)
    padded = torch.cat([pts, torch.full((1, 25, 3), 5.0)], dim=1)  # whatever the padding holds
    valid = torch.cat([torch.ones(1, 40, dtype=torch.bool), torch.zeros(1, 25, dtype=torch.bool)], dim=1)
    model = DeepMappingModel(cfg, padded, torch.eye(4)[None], valid=valid, pose_dof=6)
    direct = model.lnet(pts, torch.eye(4)[None])
    torch.testing.assert_close(model.lnet(model.lnet_scans, torch.eye(4)[None]), direct)
    assert not torch.allclose(model.lnet(padded, torch.eye(4)[None]), direct)  # the padding would change it
    assert torch.equal(fill_invalid(padded, valid)[0, :40], pts[0])


@pytest.fixture(scope="module")
def lidar_problem(tmp_path_factory):
    """4 simulated LiDAR scans (6-DoF) with initial poses 5 cm / 2 deg off the ground truth."""
    from deepmapping.io.lidar import load_lidar
    from deepmapping.sim.lidar import write_lidar_dataset

    root = tmp_path_factory.mktemp("lidar")
    write_lidar_dataset(root, num_trajectories=1, frames=4, seed=3)
    scans = load_lidar(root / "traj_000", max_points=600)
    rng = np.random.default_rng(0)
    rot = Rotation.from_rotvec(rng.normal(size=(4, 3)) * np.radians(2)).as_matrix()
    scans.init_poses = scans.gt_poses @ se3.from_rt(rot, rng.normal(size=(4, 3)) * 0.05)
    return scans


@pytest.mark.parametrize("method", ["deepmapping", "direct"])
def test_six_dof_registration_reduces_position_and_rotation_errors(lidar_problem, method):
    from deepmapping.api import register
    from deepmapping.evaluation.metrics3d import ate_3d, rotation_errors_deg

    s = lidar_problem
    # 50 steps in all: no M-Net warm-up (default-3d holds the poses for 20 epochs and 100 steps)
    cfg = load_config("default-3d", overrides={"method": method, "warm_start.method": "file", "threads": 1,
                                               "optim.epochs": 50, "optim.mnet_warmup_epochs": 0,
                                               "optim.mnet_warmup_steps": 0})
    result = register(s, cfg)
    ate0, rot0 = ate_3d(s.init_poses, s.gt_poses), rotation_errors_deg(s.init_poses, s.gt_poses).mean()
    assert result.poses.shape == (4, 4, 4)
    assert ate_3d(result.poses, s.gt_poses) < 0.4 * ate0  # from 63 mm
    assert rotation_errors_deg(result.poses, s.gt_poses).mean() < 0.8 * rot0  # from 2.2 deg
    assert result.metrics["unit"] == "m" and result.metrics["ate"] == pytest.approx(ate_3d(result.poses, s.gt_poses))


def test_centroid_pivot_turns_a_scan_about_its_centroid():
    cfg = load_config("default-3d").model_copy(deep=True)
    cfg.lnet.pivot = "centroid"
    pts = torch.tensor([[[0.0, 0.0, 2.0], [0.2, 0.0, 2.0], [0.0, 0.2, 2.2]]]).repeat(2, 1, 1)
    model = DeepMappingModel(cfg, pts, torch.eye(4).repeat(2, 1, 1), valid=torch.ones(2, 3, dtype=torch.bool),
                             pose_dof=6)
    model.make_direct()
    with torch.no_grad():
        model.direct_poses[0, 3:] = torch.tensor([0.0, 0.0, 1.0, 0.0, 1.0, 0.0]) - torch.tensor(
            [1.0, 0.0, 0.0, 0.0, 1.0, 0.0])  # a 90 deg turn about y
    pose = model.poses(torch.tensor([0]))[0]
    centroid = pts[0].mean(0)
    torch.testing.assert_close(pose[:3, :3] @ centroid + pose[:3, 3], centroid)  # the centroid stays put
    assert not torch.allclose(pose[:3, :3], torch.eye(3))


def test_paper_3d_profile_is_section_4_2_and_runs(tmp_path):
    """§4.2: C(64)-C(128)-C(256)-C(1024)-AM(1)-FC(512)-FC(256)-FC(3), 35 samples per ray, lambda 0.1, batch 8."""
    from deepmapping.api import register
    from deepmapping.io.rgbd import load_rgbd
    from deepmapping.sim.rgbd import write_rgbd_dataset

    cfg = load_config("paper-3d", overrides={"optim.epochs": 1, "threads": 1})
    assert (cfg.lnet.conv_channels, cfg.lnet.fc_channels) == ([64, 128, 256, 1024], [512, 256])
    assert (cfg.lnet.kernel_size, cfg.lnet.dilation, cfg.lnet.stride) == (3, 2, 1)
    assert (cfg.loss.free_samples, cfg.loss.chamfer_weight, cfg.optim.batch_size) == (35, 0.1, 8)
    assert cfg.mnet.kind == "mlp" and cfg.mnet.hidden == [64, 512, 512, 256, 128]
    write_rgbd_dataset(tmp_path, num_trajectories=1, frames=3, seed=1)
    scans = load_rgbd(tmp_path / "traj_000", stride=8)  # 10 x 8 pixels: the full-size networks stay cheap
    result = register(scans, cfg)
    assert result.poses.shape == (3, 4, 4) and np.isfinite(result.poses).all()
    # planar poses: the rotation stays about the vertical axis
    np.testing.assert_allclose(result.poses[:, 1, :], [[0.0, 1.0, 0.0, 0.0]] * 3, atol=1e-6)


def test_coarse_to_fine_opens_fourier_bands_in_order():
    from deepmapping.solver.networks import FourierEncoding

    enc = FourierEncoding(3, 4, 8.0)
    enc.set_progress(0.0)
    assert torch.equal(enc.band_weights, torch.zeros(4))
    x = torch.rand(5, 3)
    torch.testing.assert_close(enc(x)[:, 3:], torch.zeros(5, 24))  # only the raw coordinate passes
    enc.set_progress(0.5)  # the two coarsest bands open, the two finest stay shut
    torch.testing.assert_close(enc.band_weights, torch.tensor([1.0, 1.0, 0.0, 0.0]))
    enc.set_progress(1.0)
    assert torch.equal(enc.band_weights, torch.ones(4))


def test_standardize_std_floor_bounds_the_gain_of_a_constant_feature():
    from deepmapping.solver.networks import Standardize

    x = torch.cat([torch.randn(64, 3), torch.full((64, 1), 2.0)], dim=1)  # last feature: no spread
    for floor, bounded in ((0.0, False), (0.1, True)):
        norm = Standardize(4, floor)
        norm.calibrating = True
        norm(x)
        norm.calibrating = False
        gain = 1.0 / norm.std[3].item()
        assert (gain < 20.0) == bounded  # without the floor: 1e5


def test_auto_warm_start_is_planar_icp_for_depth_images_and_icp_for_clouds(lidar_problem, tmp_path):
    from deepmapping.api import baseline_poses, warm_start_poses
    from deepmapping.io.rgbd import load_rgbd
    from deepmapping.sim.rgbd import write_rgbd_dataset

    cfg = load_config("default-3d")
    assert cfg.warm_start.method == "auto"
    write_rgbd_dataset(tmp_path, num_trajectories=1, frames=3, seed=2)
    depth = load_rgbd(tmp_path / "traj_000", stride=4)
    np.testing.assert_array_equal(warm_start_poses(depth, cfg), baseline_poses(depth, cfg, "icp-planar"))
    depth.pose_dof = 6  # 6-DoF depth images (handheld): point-to-plane ICP
    # Open3D's ICP may differ in the last bits between two runs
    np.testing.assert_allclose(warm_start_poses(depth, cfg), baseline_poses(depth, cfg, "icp-plane"), atol=1e-9)
    clouds = warm_start_poses(lidar_problem, cfg)  # incremental ICP: close to the truth
    from deepmapping.evaluation.metrics3d import ate_3d

    assert ate_3d(clouds, lidar_problem.gt_poses) < 0.05


def test_kiss_icp_warm_start_on_a_slow_lidar_sequence(tmp_path):
    """--warm-start kiss-icp: DeepMapping starts from KISS-ICP's odometry (a robot at 1 m/s, 10 Hz)."""
    from deepmapping.api import register
    from deepmapping.evaluation.metrics3d import ate_3d
    from deepmapping.io.lidar import load_lidar
    from deepmapping.methods.kiss_odometry import kiss_icp_poses
    from deepmapping.sim.lidar import write_lidar_dataset

    write_lidar_dataset(tmp_path, num_trajectories=1, frames=12, seed=3, step_m=0.1)
    scans = load_lidar(tmp_path / "traj_000", max_points=2000)
    kiss = kiss_icp_poses([p[v] for p, v in zip(scans.points, scans.valid)])
    assert ate_3d(kiss, scans.gt_poses) < 0.05  # 1.1 m of travel; no registration: see below
    assert ate_3d(np.tile(np.eye(4), (12, 1, 1)), scans.gt_poses) > 0.2
    res = register(scans, load_config("default-3d", overrides={"warm_start.method": "kiss-icp", "optim.epochs": 1,
                                                               "threads": 1}))
    np.testing.assert_allclose(res.init_poses, kiss, atol=1e-9)
    baseline = register(scans, load_config("default-3d", overrides={"method": "kiss-icp"}))
    np.testing.assert_allclose(baseline.poses, kiss, atol=1e-9)
