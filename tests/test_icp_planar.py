"""Planar (3-DoF) ICP with yaw hypotheses: the AVD-like warm start and baseline ``icp-planar``."""

import numpy as np
import pytest

from deepmapping.api import auto_warm_start, baseline_poses
from deepmapping.config import load_config
from deepmapping.data import FullSequence, ScanSet
from deepmapping.errors import ConfigError
from deepmapping.geometry import se3
from deepmapping.methods.icp3d import default_scales, prepare_clouds
from deepmapping.methods.icp_planar import incremental_icp_planar, planar_params, register_pair_planar
from deepmapping.sim.rgbd import Intrinsics, render_depth
from deepmapping.sim.scene3d import make_scene

INTR = Intrinsics()


def _cloud(depth):
    d = depth.astype(np.float64).ravel() / 1000.0
    return (INTR.ray_directions() * d[:, None])[d > 0]


@pytest.fixture(scope="module")
def turns():
    """Six camera pairs in a furnished scene: the second view turned 30 deg in place (AVD's turn)."""
    scene = make_scene(2)
    pairs = []
    for k, (x, z) in enumerate(scene.free_positions[::7][:6]):
        a = se3.from_planar_xz([x, z, 0.4 * k])
        b = se3.from_planar_xz([x, z, 0.4 * k + np.radians(30)])
        pairs.append((_cloud(render_depth(scene, a, INTR)), _cloud(render_depth(scene, b, INTR)), se3.relative(a, b)))
    return pairs


def _pair_errors(pairs, hypotheses):
    errors = []
    for ca, cb, truth in pairs:
        scales = default_scales([ca, cb])
        pa, pb = prepare_clouds([ca, cb], scales)
        est, fit = register_pair_planar(np.asarray(pb.points), np.asarray(pa.points), np.asarray(pa.normals),
                                        scales.fine, scales.coarse, hypotheses)
        assert 0.0 <= fit <= 1.0
        err = se3.relative(truth, est)
        errors.append((np.linalg.norm(err[:3, 3]), float(se3.rotation_angle_deg(err[:3, :3]))))
    return np.array(errors)


def test_yaw_hypotheses_recover_30_degree_turns(turns):
    err = _pair_errors(turns, [0.0, 30.0, -30.0])
    assert err[:, 1].max() < 0.5 and err[:, 0].max() < 0.12, err
    assert np.median(err[:, 0]) < 0.02
    # one hypothesis (plain ICP from the identity) falls short of the turn on most pairs
    single = _pair_errors(turns, [0.0])
    assert (single[:, 1] > 10.0).sum() >= 4, single


def test_planar_params_round_trip():
    x = np.array([0.3, -1.2, 2.5])
    np.testing.assert_allclose(planar_params(se3.from_planar_xz(x)), x, atol=1e-12)


def test_chain_and_init(turns):
    ca, cb, truth = turns[0]
    poses = incremental_icp_planar([ca, cb])
    assert poses.shape == (2, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4))
    assert se3.rotation_angle_deg(se3.relative(truth, poses[1])[:3, :3]) < 0.5
    # from an initial guess: the hypotheses are offsets from the guessed relative motion
    start = se3.from_planar_xz([1.0, 2.0, 0.7])
    init = np.stack([start, start @ se3.from_planar_xz(planar_params(truth) + [0.05, -0.05, 0.1])])
    poses = incremental_icp_planar([ca, cb], init=init, yaw_hypotheses_deg=[0.0])
    np.testing.assert_allclose(poses[0], start)
    assert np.linalg.norm(se3.relative(start @ truth, poses[1])[:3, 3]) < 0.03


def _scans(dim, grid, dof):
    k, n = 2, 12
    return ScanSet(points=np.ones((k, n, dim), np.float32), valid=np.ones((k, n), bool),
                   grid_shape=(3, 4) if grid else None, pose_dof=dof)


def test_auto_warm_start_and_errors():
    assert auto_warm_start(_scans(3, True, 3)) == "icp-planar"
    assert auto_warm_start(_scans(3, True, 6)) == "icp-plane"  # 6-DoF depth images: handheld (7-Scenes), was a cold start
    assert auto_warm_start(_scans(3, False, 6)) == "icp-plane"
    assert auto_warm_start(_scans(2, False, 3)) == "icp-plane"
    log = _scans(2, False, 3)
    log.sequence = FullSequence(["0", "1"], np.zeros(2), np.zeros((2, 3)), np.arange(2))
    assert auto_warm_start(log) == "loop-closure"
    from deepmapping.api import LONG_SEQUENCE

    def scans_2d(k, ordered):
        return ScanSet(points=np.ones((k, 4, 2), np.float32), valid=np.ones((k, 4), bool), ordered=ordered)

    assert auto_warm_start(scans_2d(LONG_SEQUENCE, True)) == "loop-closure"  # a long trajectory: its loops
    assert auto_warm_start(scans_2d(LONG_SEQUENCE - 1, True)) == "icp-plane"
    assert auto_warm_start(scans_2d(LONG_SEQUENCE, False)) == "icp-plane"  # no sequence, no loop
    assert LONG_SEQUENCE <= 128  # the paper's 128- and 256-scan trajectories start from their loop closures
    # the settings "auto" that follow the start: the loop-closure ones only from a loop-closure start (2D);
    # a value given stays
    from deepmapping.api import LOOP_WARMUP_EPOCHS, START_SETTINGS, start_settings

    cfg2 = load_config("default")
    near = START_SETTINGS["loop-closure"]
    other = START_SETTINGS["other"]
    assert near == {"optim.mnet_warmup_epochs": LOOP_WARMUP_EPOCHS, "mnet.kind": "grid", "loss.near_hit_samples": 4,
                    "optim.batch_order": "random", "lnet.lr_factor": 0.05}
    assert other == {"optim.mnet_warmup_epochs": 0, "mnet.kind": "fourier", "loss.near_hit_samples": 0,
                     "optim.batch_order": "contiguous", "lnet.lr_factor": 0.1}
    from deepmapping.config import AUTO_FALLBACKS, unresolved_auto  # what a model built directly takes for "auto"

    assert AUTO_FALLBACKS == other and all(near.keys() == s.keys() for s in START_SETTINGS.values())
    assert unresolved_auto("auto", "lnet.lr_factor") == 0.1 and unresolved_auto(0.05, "lnet.lr_factor") == 0.05
    assert (cfg2.optim.mnet_warmup_epochs, cfg2.mnet.kind, cfg2.loss.near_hit_samples, cfg2.optim.batch_order,
            cfg2.lnet.lr_factor) == ("auto",) * 5
    assert start_settings(scans_2d(LONG_SEQUENCE, True), cfg2) == near
    assert start_settings(log, cfg2) == START_SETTINGS["log"] == other | {"optim.mnet_warmup_epochs": LOOP_WARMUP_EPOCHS}
    assert start_settings(scans_2d(LONG_SEQUENCE - 1, True), cfg2) == other  # icp-plane
    assert start_settings(scans_2d(8, True), cfg2.with_overrides({"warm_start.method": "loop-closure"})) == near
    assert start_settings(scans_2d(LONG_SEQUENCE, True), cfg2.with_overrides({"warm_start.method": "icp-plane"})) == other
    given = cfg2.with_overrides({"optim.mnet_warmup_epochs": 3, "mnet.kind": "fourier"})
    assert start_settings(scans_2d(LONG_SEQUENCE, True), given) == {"loss.near_hit_samples": 4, "optim.batch_order": "random",
                                                                     "lnet.lr_factor": 0.05}
    given = given.with_overrides({"optim.batch_order": "contiguous", "lnet.lr_factor": 0.1})
    assert start_settings(scans_2d(LONG_SEQUENCE, True), given) == {"loss.near_hit_samples": 4}
    assert start_settings(_scans(3, False, 6), cfg2) == other  # 3D: no grid M-Net
    resolved = cfg2.with_overrides(start_settings(scans_2d(LONG_SEQUENCE, True), cfg2))
    assert (resolved.optim.mnet_warmup_epochs, resolved.mnet.kind, resolved.loss.near_hit_samples,
            resolved.optim.batch_order, resolved.lnet.lr_factor) == (25, "grid", 4, "random", 0.05)
    from deepmapping.cli.register_cmd import settings_line

    assert settings_line(scans_2d(LONG_SEQUENCE, True), cfg2) == (
        f"settings: profile default, warm start loop-closure (auto), 250 epochs, the first {LOOP_WARMUP_EPOCHS} M-Net only, "
        "grid M-Net, 4 free-space samples near each hit, batches of scans drawn at random")
    assert settings_line(scans_2d(8, True), cfg2) == "settings: profile default, warm start icp-plane (auto), 250 epochs"
    cfg = load_config("default-3d")
    with pytest.raises(ConfigError, match="3-DoF"):
        baseline_poses(_scans(3, True, 6), cfg, "icp-planar")
    with pytest.raises(ConfigError, match="3D scans only"):
        baseline_poses(_scans(2, False, 3), load_config("default"), "icp-planar")
