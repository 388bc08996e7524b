"""3D simulator (AVD-style RGB-D and LiDAR), ray casting, and the RGB-D / LiDAR folder loaders."""

import json
import shutil

import numpy as np
import pytest
from scipy.spatial import cKDTree

from deepmapping.errors import InputError
from deepmapping.geometry import se3
from deepmapping.io.lidar import is_lidar_folder, load_lidar
from deepmapping.io.ply import write_ply
from deepmapping.io.rgbd import is_rgbd_folder, load_rgbd
from deepmapping.sim.lidar import LidarConfig, lidar_pose, scan, simulate_lidar_trajectory, write_lidar_dataset
from deepmapping.sim.raycast import caster_for
from deepmapping.sim.rgbd import Intrinsics, grid_trajectory, render_depth, simulate_rgbd_trajectory, write_rgbd_dataset
from deepmapping.sim.scene3d import make_scene


@pytest.fixture(scope="module")
def box_room():
    """Empty 3.0 m (x) x 4.2 m (z) room, floor 1.0 m below the camera, ceiling 1.6 m above."""
    return make_scene(0, two_rooms=False, furniture=False, room_size=(3.0, 4.2))


@pytest.fixture(scope="module")
def rgbd_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("rgbd")
    write_rgbd_dataset(out, num_trajectories=2, frames=16, seed=5)
    return out


@pytest.fixture(scope="module")
def lidar_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("lidar")
    write_lidar_dataset(out, num_trajectories=1, frames=6, seed=5)
    return out


def test_depth_of_known_walls(box_room):
    intr = Intrinsics()
    depth = render_depth(box_room, se3.from_planar_xz([1.5, 1.2, 0.0]), intr)  # facing +z: wall z = 4.2
    assert depth.dtype == np.uint16 and depth.shape == (60, 80)
    assert np.all(depth[25:35, 30:50] == 3000)
    v = 59  # bottom row sees the floor (y = +1.0 m, y is down): z = 1.0 * fy / (v - cy)
    assert abs(int(depth[v, 40]) - 1000.0 * intr.fy / (v - intr.cy)) <= 1
    assert depth[0, 40] == 3000  # top row still sees the wall (ceiling is 1.6 m up)
    side = render_depth(box_room, se3.from_planar_xz([1.2, 2.1, np.pi / 2]), intr)  # facing +x: wall x = 3.0
    assert np.all(side[25:35, 30:50] == 1800)
    far = render_depth(box_room, se3.from_planar_xz([1.5, 0.3, 0.0]), intr, max_depth_m=3.0)
    assert np.all(far[25:35, 30:50] == 0)  # 3.9 m > max depth: no return


def test_scene_free_grid():
    scene = make_scene(3, two_rooms=True)
    kinds = {k for k, _, _ in scene.boxes}
    assert {"wall", "lintel", "stairs", "table", "shelf", "cabinet", "floor", "ceiling"} <= kinds
    free = scene.free_positions
    assert len(free) > 50
    np.testing.assert_allclose(free / 0.3, np.round(free / 0.3), atol=1e-9)
    cams = np.c_[free[:, 0], np.zeros(len(free)), free[:, 1]]
    ray_down = np.concatenate([cams, np.tile([0, 1, 0], (len(free), 1))], 1)
    np.testing.assert_allclose(caster_for(scene).cast(ray_down), scene.camera_height, atol=1e-5)  # floor below
    assert caster_for(scene).distance(cams).min() > 0.35
    door_x = [lo[0] for k, lo, _ in scene.boxes if k == "lintel"][0] + 0.05
    assert (free[:, 0] < door_x).any() and (free[:, 0] > door_x).any()  # both rooms reachable


def test_grid_protocol():
    scene = make_scene(1)
    p = grid_trajectory(scene, 16, np.random.default_rng(0))
    assert p.shape == (16, 3)
    np.testing.assert_allclose(p[:, :2] / 0.3, np.round(p[:, :2] / 0.3), atol=1e-9)
    deg = np.degrees(p[:, 2])
    np.testing.assert_allclose(deg / 30, np.round(deg / 30), atol=1e-9)
    keys = {(round(x / 0.3), round(z / 0.3), round(d / 30) % 12) for x, z, d in zip(p[:, 0], p[:, 1], deg)}
    assert len(keys) == 16  # no (position, view) visited twice
    moved = np.abs(np.diff(p[:, :2], axis=0)).sum(1)
    turned = np.abs((np.diff(deg) + 180) % 360 - 180)
    assert np.all(((np.abs(moved - 0.3) < 1e-9) & (turned < 1e-9)) | ((moved < 1e-9) & (np.abs(turned - 30) < 1e-9)))
    free = {(round(x / 0.3), round(z / 0.3)) for x, z in scene.free_positions}
    assert all((round(x / 0.3), round(z / 0.3)) in free for x, z in p[:, :2])


def test_seeds_reproducible():
    scene = make_scene(2)
    a = simulate_rgbd_trajectory(scene, 8, np.random.default_rng(4), noise_std_m=0.01)
    b = simulate_rgbd_trajectory(scene, 8, np.random.default_rng(4), noise_std_m=0.01)
    c = simulate_rgbd_trajectory(scene, 8, np.random.default_rng(5), noise_std_m=0.01)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and not np.array_equal(a[1], c[1])
    s1, s2 = make_scene(7), make_scene(7)
    assert np.array_equal(s1.vertices, s2.vertices) and not np.array_equal(s1.vertices, make_scene(8).vertices)


def _world(scans):
    return [se3.transform_points(scans.gt_poses[k], scans.points[k][scans.valid[k]]) for k in range(scans.num_scans)]


def test_rgbd_folder_round_trip_on_surfaces(rgbd_dir):
    folder = rgbd_dir / "traj_001"
    assert is_rgbd_folder(folder) and not is_rgbd_folder(rgbd_dir)
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["kind"] == "rgbd" and meta["pose_dof"] == 3 and meta["frames"] == 16
    s = load_rgbd(folder)
    assert s.points.shape == (16, 4800, 3) and s.grid_shape == (60, 80) and s.pose_dof == 3
    assert (s.unit, s.unit_scale, s.ordered, s.names[0]) == ("mm", 1000.0, True, "000000.png")
    world = _world(s)
    assert caster_for(make_scene(meta["scene"])).distance(np.concatenate(world)).max() < 0.005
    overlap = [np.mean(cKDTree(a).query(b)[0] < 0.05) for a, b in zip(world[:-1], world[1:])]
    assert np.mean(overlap) > 0.2
    half = load_rgbd(folder, stride=2)
    assert half.grid_shape == (30, 40)
    np.testing.assert_array_equal(half.points[3].reshape(30, 40, 3), s.points[3].reshape(60, 80, 3)[::2, ::2])


def _copy(src, tmp_path):
    dst = tmp_path / "t"
    shutil.copytree(src, dst)
    return dst


def _raises(fn, *words):
    with pytest.raises(InputError) as e:
        fn()
    assert "\n" not in str(e.value) and all(w in str(e.value) for w in words), str(e.value)


def test_rgbd_loader_errors(rgbd_dir, tmp_path):
    from PIL import Image

    d = _copy(rgbd_dir / "traj_000", tmp_path)
    (d / "depth" / "000003.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    _raises(lambda: load_rgbd(d), "000003.png", "cannot read")
    Image.fromarray(np.zeros((60, 80), np.uint8)).save(d / "depth" / "000003.png")
    _raises(lambda: load_rgbd(d), "000003.png", "16-bit")
    Image.fromarray(np.ones((50, 80), np.uint16)).save(d / "depth" / "000003.png")
    _raises(lambda: load_rgbd(d), "000003.png", "size")
    shutil.copy(rgbd_dir / "traj_000" / "depth" / "000003.png", d / "depth" / "000003.png")
    lines = (d / "gt_poses.txt").read_text().splitlines()
    (d / "gt_poses.txt").write_text("\n".join(lines[:-1]) + "\n")
    _raises(lambda: load_rgbd(d), "gt_poses.txt", "15 poses for 16 scans")
    _raises(lambda: load_rgbd(d, gt_path=rgbd_dir / "traj_000" / "gt_poses.txt", init_path=d / "gt_poses.txt"),
            "gt_poses.txt", "counts differ")
    (d / "intrinsics.json").unlink()
    assert is_rgbd_folder(d)
    _raises(lambda: load_rgbd(d), "intrinsics.json", "not found")


def test_lidar_pose_and_sensor_frame(box_room):
    cfg = LidarConfig(beams=1, vfov_deg=(0.0, 0.0), azimuth_res_deg=90.0)
    pts = scan(box_room, lidar_pose(1.2, 1.5, 0.0), cfg)  # x forward = world +z, y left = world -x
    np.testing.assert_allclose(pts, [[2.7, 0, 0], [0, 1.2, 0], [-1.5, 0, 0], [0, -1.8, 0]], atol=1e-5)
    zenith = LidarConfig(beams=1, vfov_deg=(90.0, 90.0), azimuth_res_deg=360)
    up = scan(box_room, lidar_pose(1.2, 1.5, 0.0, dh=0.2), zenith)
    np.testing.assert_allclose(up, [[0, 0, 1.4]], atol=1e-5)  # z up: ceiling 1.6 m above y = 0


def test_lidar_trajectory_6dof():
    scene = make_scene(4)
    clouds, poses = simulate_lidar_trajectory(scene, 12, np.random.default_rng(1), LidarConfig(beams=16))
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.2) & (steps < 0.45))
    up_world = poses[:, :3, :3] @ [0, 0, 1]
    tilt = np.degrees(np.arccos(np.clip(-up_world[:, 1], -1, 1)))
    assert tilt.max() > 0.5 and np.ptp(poses[:, 1, 3]) > 0.02  # not planar: roll/pitch and height vary
    world = [se3.transform_points(T, c) for T, c in zip(poses, clouds)]
    assert caster_for(scene).distance(np.concatenate(world)).max() < 1e-3
    overlap = [np.mean(cKDTree(a).query(b)[0] < 0.1) for a, b in zip(world[:-1], world[1:])]
    assert min(overlap) > 0.3


def test_lidar_folder_and_errors(lidar_dir, tmp_path):
    folder = lidar_dir / "traj_000"
    assert is_lidar_folder(folder) and not is_lidar_folder(lidar_dir)
    s = load_lidar(folder)
    assert s.grid_shape is None and s.pose_dof == 6 and s.unit == "m" and s.num_scans == 6
    assert s.valid.sum(1).max() == s.points.shape[1] and np.all(s.points[~s.valid] == 0)
    sub = load_lidar(folder, max_points=500, seed=1)
    assert sub.points.shape == (6, 500, 3) and sub.valid.all()
    assert np.array_equal(sub.points, load_lidar(folder, max_points=500, seed=1).points)
    d = _copy(folder, tmp_path)
    write_ply(d / "scans" / "000002.ply", np.zeros((0, 3), np.float32))
    _raises(lambda: load_lidar(d), "000002.ply", "no point")
    (d / "scans" / "000002.ply").write_bytes(b"not a ply")
    _raises(lambda: load_lidar(d), "000002.ply")
    shutil.copy(folder / "scans" / "000002.ply", d / "scans" / "000002.ply")
    (d / "gt_poses.txt").write_text((folder / "gt_poses.txt").read_text() * 2)
    _raises(lambda: load_lidar(d), "gt_poses.txt", "12 poses for 6 scans")
