"""The odometry factor (loss.odometry_sigma): the loss term, when "auto" turns it on, and that it
holds the recorded poses of a 3DTK sequence (the excerpt in tests/data)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from deepmapping.api import (
    AUTO_ODOMETRY_FACTOR,
    AUTO_ODOMETRY_GATE_DEG,
    AUTO_ODOMETRY_SIGMA,
    auto_warm_start,
    resolve_odometry_sigma,
)
from deepmapping.config import load_config
from deepmapping.data import ScanSet
from deepmapping.errors import ConfigError
from deepmapping.geometry import se3
from deepmapping.solver.loss import odometry_factor

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"


def _poses(k: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return se3.from_rt(Rotation.from_rotvec(rng.normal(size=(k, 3))).as_matrix(), rng.normal(size=(k, 3)))


def _factor(poses, prior, idx, sigma_t=0.1, sigma_r_deg=2.0, first_below=None) -> float:
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    return float(odometry_factor(t(poses), t(prior), t(idx).long(), sigma_t, math.radians(sigma_r_deg), first_below))


def test_odometry_factor_values():
    prior = _poses(3)
    idx = [4, 5, 6]
    assert _factor(prior, prior, idx) < 1e-20
    moved = _poses(1, seed=1)[0] @ prior  # one rigid motion of the whole sequence: the same relative motions
    assert _factor(moved, prior, idx) < 1e-20
    shift = prior.copy()
    shift[2] = shift[2] @ se3.from_rt(np.eye(3), np.array([0.03, 0.0, -0.04]))  # 5 cm in scan 6's frame
    assert _factor(shift, prior, idx) == pytest.approx((0.05 / 0.1) ** 2 / 2, rel=1e-9)  # one of two pairs
    turn = prior.copy()
    turn[2] = turn[2] @ se3.from_rt(Rotation.from_rotvec([0.0, math.radians(1.0), 0.0]).as_matrix(), np.zeros(3))
    assert _factor(turn, prior, idx) == pytest.approx((1.0 / 2.0) ** 2 / 2, rel=1e-3)  # theta^2, small angles
    assert _factor(shift, prior, [4, 6, 8]) == 0.0  # no temporal neighbours in the batch
    assert _factor(shift, prior, idx, first_below=1) < 1e-20  # a worker's own pairs: (4, 5) only
    assert _factor(shift, prior, idx, first_below=2) > 0.1


def _scans(dim: int = 3, ordered: bool = True, init: bool = True, recorded: bool = True) -> ScanSet:
    k, n = 3, 12
    s = ScanSet(points=np.ones((k, n, dim), np.float32), valid=np.ones((k, n), bool), ordered=ordered, pose_dof=6,
                recorded_poses=recorded)
    if init:
        s.init_poses = np.stack([np.eye(4)] * k) if dim == 3 else np.zeros((k, 3))
    return s


def test_auto_turns_the_factor_on_for_the_scans_own_recorded_poses_only(monkeypatch):
    import deepmapping.methods.icp3d as icp3d

    agreement = {"value": (0.2, 1.5)}  # ICP from the recorded poses moved them 20 cm, 1.5 deg
    monkeypatch.setattr(icp3d, "odometry_agreement", lambda *a, **k: agreement["value"])
    cfg = load_config("default-3d")
    assert cfg.loss.odometry_sigma == "auto" and load_config("paper-3d").loss.odometry_sigma == "off"
    assert auto_warm_start(_scans()) == "file"  # 3D sequence with recorded poses (3DTK's .pose files)
    assert auto_warm_start(_scans(init=False)) == "icp-plane"
    assert auto_warm_start(_scans(ordered=False)) == "icp-plane"  # a set of views (the bunny): no sequence
    assert auto_warm_start(_scans(recorded=False)) == "icp-plane"  # poses someone computed or gave
    on = (AUTO_ODOMETRY_FACTOR * 0.2, AUTO_ODOMETRY_FACTOR * 1.5)  # held loosely: the scans disagree
    assert on[0] > AUTO_ODOMETRY_SIGMA[0] and on[1] > AUTO_ODOMETRY_SIGMA[1]
    assert resolve_odometry_sigma(_scans(), cfg) == pytest.approx(on)
    agreement["value"] = (0.01, 0.1)  # ICP agrees: no tighter than AUTO_ODOMETRY_SIGMA
    assert resolve_odometry_sigma(_scans(), cfg) == pytest.approx(AUTO_ODOMETRY_SIGMA)
    agreement["value"] = (0.2, AUTO_ODOMETRY_GATE_DEG + 0.5)  # the scans contradict them: not held at all
    assert resolve_odometry_sigma(_scans(), cfg) is None
    agreement["value"] = (0.2, 1.5)
    over = lambda **o: load_config("default-3d", overrides=o)  # noqa: E731
    assert resolve_odometry_sigma(_scans(), over(**{"warm_start.method": "file"})) == pytest.approx(on)
    assert resolve_odometry_sigma(_scans(recorded=False), over(**{"warm_start.method": "file"})) is None
    assert resolve_odometry_sigma(_scans(), over(**{"warm_start.method": "icp-plane"})) is None
    assert resolve_odometry_sigma(_scans(), over(**{"warm_start.path": "given.txt", "warm_start.method": "file"})) is None
    assert resolve_odometry_sigma(_scans(init=False), cfg) is None
    assert resolve_odometry_sigma(_scans(ordered=False), cfg) is None
    assert resolve_odometry_sigma(_scans(dim=2), load_config("default")) is None  # 3D only
    assert resolve_odometry_sigma(_scans(), over(**{"loss.odometry_sigma": False})) is None  # YAML's off
    explicit = over(**{"loss.odometry_sigma": [0.01, 5], "warm_start.method": "icp-plane"})
    assert resolve_odometry_sigma(_scans(), explicit) == (0.01, 5.0)
    for bad in ([0.01], [0.0, 1.0], [float("nan"), 1.0], "on", [True, 1.0]):
        with pytest.raises(ConfigError, match="odometry_sigma"):
            over(**{"loss.odometry_sigma": bad})


def test_the_agreement_of_recorded_poses_with_the_scans():
    from deepmapping.io.threedtk import load_3dtk
    from deepmapping.methods.icp3d import odometry_agreement

    scans = load_3dtk(DATA / "3dtk")  # every point of the excerpt
    clouds = [p[v] for p, v in zip(scans.points, scans.valid)]
    trans, rot = odometry_agreement(clouds, scans.init_poses)
    assert 0.01 < trans < 0.2 and 0.2 < rot < 3.0  # excerpt: 6.2 cm, 1.16 deg (ICP's own bias)
    bad = scans.init_poses.copy()
    bad[2] = bad[2] @ se3.from_rt(Rotation.from_rotvec([0.0, 0.1, 0.0]).as_matrix(), np.array([0.3, 0.0, 0.3]))
    trans_bad, rot_bad = odometry_agreement(clouds, bad)
    assert trans_bad > 2 * trans and rot_bad > 1.5 * rot  # a recorded pose off by 42 cm, 5.7 deg


def test_the_3dtk_reader_marks_its_pose_files_as_recorded_poses(tmp_path):
    from deepmapping.io.threedtk import load_3dtk

    scans = load_3dtk(DATA / "3dtk", max_points=50)
    assert scans.recorded_poses and scans.init_poses is not None
    assert not load_3dtk(DATA / "3dtk", max_points=50, use_frames=True).recorded_poses
    np.save(tmp_path / "given.npy", scans.init_poses)
    assert not load_3dtk(DATA / "3dtk", max_points=50, init_path=tmp_path / "given.npy").recorded_poses


def test_each_training_step_adds_the_factor_to_eq4_and_eq7():
    from deepmapping.io.threedtk import load_3dtk
    from deepmapping.solver.frame import Frame
    from deepmapping.solver.model import DeepMappingModel
    from deepmapping.solver.trainer import Trainer

    scans = load_3dtk(DATA / "3dtk", max_points=200)
    torch.manual_seed(0)
    cfg = load_config("default-3d", overrides={"method": "direct", "optim.mnet_warmup_epochs": 0,
                                               "optim.mnet_warmup_steps": 0})
    sigma = AUTO_ODOMETRY_SIGMA  # [m, deg]
    frame = Frame.from_scans(scans.points, scans.valid, scans.init_poses)
    model = DeepMappingModel(cfg, torch.as_tensor(scans.points / frame.scale, dtype=torch.float32),
                             torch.as_tensor(frame.to_norm(scans.init_poses), dtype=torch.float32),
                             valid=torch.as_tensor(scans.valid), pose_dof=6)
    model.make_direct()
    sigma = (sigma[0] / frame.scale, sigma[1])  # metres -> the trainer's normalized frame (as api does)
    trainer = Trainer(cfg, model, torch.as_tensor(scans.valid), ordered=True, odometry_sigma=sigma)
    idx = torch.arange(3)
    assert float(trainer.loss(idx)[2]) < 1e-10  # at the warm start
    with torch.no_grad():
        model.direct_poses[2, 0] += 0.01  # scan 2 moved by 0.01 map units (19 cm): one pair of two
    odo = float(trainer.loss(idx)[2])
    assert odo == pytest.approx((0.01 / sigma[0]) ** 2 / 2, rel=1e-3)
    loss, bce, ch = trainer.step(np.arange(3))
    assert loss - bce - cfg.loss.chamfer_weight * ch == pytest.approx(odo, rel=1e-3)
    off = Trainer(cfg, model, torch.as_tensor(scans.valid), ordered=True, odometry_sigma=None)
    assert float(off.loss(idx)[2]) == 0.0


def _relative_to_slam6d(poses: np.ndarray, ref: np.ndarray) -> list[tuple[float, float]]:
    out = []
    for i in (1, 2):
        d = se3.relative(se3.relative(ref[0], ref[i]), se3.relative(poses[0], poses[i]))
        out.append((float(np.linalg.norm(d[:3, 3])), float(se3.rotation_angle_deg(d[:3, :3]))))
    return out


def test_3dtk_default_starts_from_the_pose_files_and_the_factor_holds_them(tmp_path):
    from deepmapping.io.threedtk import load_3dtk, read_frames
    from test_cli import dm, ok

    ref = load_3dtk(DATA / "3dtk", max_points=100)
    out = tmp_path / "run"
    ok(dm("register", DATA / "3dtk", "--out", out, "--no-plots", "--set", "threads=1"))
    run = json.loads((out / "run.json").read_text())
    assert run["odometry_sigma"] == pytest.approx(list(resolve_odometry_sigma(load_3dtk(DATA / "3dtk"),
                                                                             load_config("default-3d"))), rel=1e-6)
    est = np.stack([read_frames(out / "frames" / f"scan{i:03d}.frames")[-1] for i in range(3)])
    # excerpt, seeds 0-4 with 1 and 2 threads: 0.4-2.2 cm, 0.35-0.84 deg (the odometry 0.4-1.7 cm,
    # 0.71-0.78 deg; with no factor, seeds 0-2: 1.0-6.0 cm)
    for t, r in _relative_to_slam6d(est, ref.gt_poses):
        assert t < 0.05 and r < 1.5
