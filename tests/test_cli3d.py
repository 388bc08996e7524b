"""The `deepmapping` command on 3D data: simulate --kind rgbd|lidar, register, evaluate, outputs, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from test_cli import DM, assert_one_line_error, dm, dm_many, ok

pytestmark = pytest.mark.skipif(DM is None, reason="the `deepmapping` console script is not installed")
TINY = ["--epochs", "3", "--set", "optim.eval_every=1", "--set", "loss.beams_per_scan=128"]


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("sim3d")
    res = dm_many({
        "rgbd": ["simulate", root / "rgbd", "--kind", "rgbd", "--trajectories", "1", "--frames", "6"],
        "lidar": ["simulate", root / "lidar", "--kind", "lidar", "--trajectories", "1", "--frames", "4"],
    })
    for r in res.values():
        ok(r)
    return root


@pytest.fixture(scope="module")
def runs(datasets, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs3d")
    jobs = {
        "dm": ["register", datasets / "rgbd" / "traj_000", "--out", out / "dm", *TINY],
        "multiway": ["register", datasets / "rgbd" / "traj_000", "--out", out / "mw", "--method", "multiway"],
        "lidar": ["register", datasets / "lidar" / "traj_000", "--out", out / "lidar", "--method", "direct",
                  "--warm-start", "icp-plane", *TINY],
    }
    return {name: (out / args[3].name, dm_many({name: args})[name]) for name, args in jobs.items()}


def test_simulate_writes_avd_like_and_lidar_folders(datasets):
    traj = datasets / "rgbd" / "traj_000"
    assert len(list((traj / "depth").glob("*.png"))) == 6
    assert json.loads((traj / "meta.json").read_text())["pose_dof"] == 3
    assert len(list((datasets / "lidar" / "traj_000" / "scans").glob("*.ply"))) == 4


def test_register_3d_writes_poses_cloud_occupancy_and_pictures(runs):
    from deepmapping.io.poses3d import read_poses_3d

    folder, res = runs["dm"]
    ok(res)
    for name in ("poses.npy", "poses_kitti.txt", "poses_tum.txt", "map.ply", "map.pcd", "map.png", "occupancy.npz",
                 "occupancy_mesh.ply", "metrics.json", "config.yaml", "curves.png"):
        assert (folder / name).is_file() and (folder / name).stat().st_size > 0, name
    poses = read_poses_3d(folder / "poses.npy")
    assert poses.shape == (6, 4, 4)
    np.testing.assert_allclose(read_poses_3d(folder / "poses_kitti.txt"), poses, atol=1e-9)
    np.testing.assert_allclose(read_poses_3d(folder / "poses_tum.txt"), poses, atol=1e-9)
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["unit"] == "mm" and metrics["success_threshold"] == 450.0
    assert "default-3d" in (folder / "config.yaml").read_text()  # 3D data gets the 3D profile
    grid = np.load(folder / "occupancy.npz")
    assert grid["grid"].ndim == 3 and 0.0 <= grid["grid"].min() <= grid["grid"].max() <= 1.0
    run = json.loads((folder / "run.json").read_text())
    res = run["map_resolution"]  # the M-Net's encoding as built, from the data's point spacing
    assert res["point_spacing"] > 0 and res["fourier_max_freq"] >= 32 and res["finest_period"] > 0
    assert run["occupancy_grid"]["cells"] == list(grid["grid"].shape)
    assert 64 <= max(grid["grid"].shape) <= 130  # the export follows the map (64-128 cells a side)


def test_multiway_and_lidar_runs_evaluate(runs):
    for name in ("multiway", "lidar"):
        folder, res = runs[name]
        ok(res)
        metrics = json.loads((folder / "metrics.json").read_text())
        again = ok(dm("evaluate", folder))
        assert "success" in again.stdout + again.stderr  # the table goes to the console (stderr)
        assert json.loads((folder / "metrics.json").read_text())["ate"] == pytest.approx(metrics["ate"])
    assert json.loads((runs["lidar"][0] / "metrics.json").read_text())["unit"] == "m"


def test_corrupt_depth_image_is_a_one_line_error_and_no_run_folder(datasets, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(datasets / "rgbd" / "traj_000", bad)
    (bad / "depth" / "000003.png").write_bytes(b"not a png")
    out = tmp_path / "run"
    assert_one_line_error(dm("register", bad, "--out", out, *TINY), "000003.png", out)


def test_multiway_on_2d_scans_is_a_clear_error(sim_folder, tmp_path):
    res = dm("register", sim_folder, "--method", "multiway", "--out", tmp_path / "r")
    assert res.returncode == 2 and "3D scans only" in res.stderr


def test_register_tum_folder_with_frame_options_then_evaluate(tmp_path):
    """Frame and pixel flags reach the loader, the dropped-frames note is printed, run.json keeps the
    options so that `evaluate` reads the same frames; a bad flag is one line and no run folder."""
    from test_depth_layouts import tum

    data = tum(tmp_path / "seq", k=8, gt_span=(1, 8))  # frame 0 has no ground truth within 20 ms
    out = tmp_path / "run"
    res = ok(dm("register", data, "--method", "icp-plane", "--frames", "0:6", "--every", "2", "--pixel-stride", "2",
                "--out", out, "--no-plots"))
    assert "note:" in res.stderr and "1 of 8 depth frames" in res.stderr
    run = json.loads((out / "run.json").read_text())
    assert run["depth"] == {"every": 2, "frames": [0, 6], "pixel_stride": 2, "image_size": None, "max_depth_m": None,
                            "intrinsics": None}
    assert np.load(out / "poses.npy").shape == (3, 4, 4)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["unit"] == "mm" and 0 < metrics["success_threshold"] < 450.0  # 2 % of the typical range
    ok(dm("evaluate", out))
    assert json.loads((out / "metrics.json").read_text())["ate"] == pytest.approx(metrics["ate"])
    bad = tmp_path / "bad"
    assert_one_line_error(dm("register", data, "--image-size", "80", "--out", bad), "--image-size", bad)
    assert_one_line_error(dm("register", data, "--frames", "7:", "--out", bad), "0 frame(s) of 7", bad)
