"""Small versions of the real-data checks of `deepmapping experiment real-3d`: the Stanford bunny and 3DTK."""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"  # excerpts of ../shared/data (tests/data/make_excerpts.py)


def test_bunny_check_small():
    from deepmapping.api import register
    from deepmapping.config import load_config
    from deepmapping.experiments.real_3d import coarse_start
    from deepmapping.io.bunny import bunny_pose_errors, load_bunny, scan_centroids

    scans = load_bunny(DATA / "bunny", max_points=300)
    centroids = scan_centroids(scans.points, scans.valid)
    scans.init_poses = coarse_start(scans, deg=5.0)
    start = bunny_pose_errors(scans.init_poses, scans.gt_poses, scans.names, centroids)
    assert start[0]["rot_deg"] < 1e-6 and start[0]["trans_mm"] < 1e-6  # bun000 is the fixed reference
    errors = {}
    for method in ("direct", "deepmapping"):
        # 90 steps in all: no M-Net warm-up (default-3d holds the poses for 20 epochs and 100 steps)
        cfg = load_config("bunny", overrides={"method": method, "warm_start.method": "file", "threads": 1,
                                              "optim.epochs": 30, "optim.mnet_warmup_epochs": 0,
                                              "optim.mnet_warmup_steps": 0})
        poses = register(scans, cfg).poses
        errors[method] = bunny_pose_errors(poses, scans.gt_poses, scans.names, centroids)
        assert len(errors[method]) == 10 and all(np.isfinite([e["rot_deg"], e["trans_mm"]]).all()
                                                 for e in errors[method])
    mean_t = {m: np.mean([e["trans_mm"] for e in errs[1:]]) for m, errs in errors.items()}
    t0 = np.mean([e["trans_mm"] for e in start[1:]])
    assert mean_t["direct"] < 0.95 * t0  # excerpt, seeds 0-2: 9.5 mm -> x 0.81-0.90
    assert mean_t["deepmapping"] < 1.5 * t0  # stays in place at this size (does not run away)


def test_3dtk_check_small(tmp_path):
    from deepmapping.geometry import se3
    from deepmapping.io.threedtk import load_3dtk, read_frames
    from test_cli import dm, ok

    out = tmp_path / "run"
    ok(dm("register", DATA / "3dtk", "--method", "icp-plane", "--warm-start", "file", "--out", out))
    ref = load_3dtk(DATA / "3dtk", max_points=100).gt_poses  # slam6D's final poses
    est = np.stack([read_frames(out / "frames" / f"scan{i:03d}.frames")[-1] for i in range(3)])
    for i in (1, 2):
        d = se3.relative(se3.relative(ref[0], ref[i]), se3.relative(est[0], est[i]))
        assert np.linalg.norm(d[:3, 3]) < 0.10  # metres; excerpt 5.1-6.7 cm (full scans 3-6; odometry 0.4-1.7)
        assert se3.rotation_angle_deg(d[:3, :3]) < 2.0  # excerpt 0.8-1.3 deg (full scans 0.7-1.3)
