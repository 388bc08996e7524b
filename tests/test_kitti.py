"""KITTI odometry layout: velodyne .bin scans, calib.txt Tr, camera-0 poses -> LiDAR poses."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from deepmapping.errors import InputError
from deepmapping.geometry import se3
from deepmapping.io.kitti import read_velodyne_bin, write_velodyne_bin
from deepmapping.io.loaders import detect_format, load_scans
from deepmapping.io.poses3d import write_kitti_poses

TR = se3.from_rt(Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix(), [0.0, -0.08, -0.27])


@pytest.fixture()
def sequence(tmp_path):
    rng = np.random.default_rng(0)
    seq = tmp_path / "sequences" / "07"
    (seq / "velodyne").mkdir(parents=True)
    clouds = [rng.normal(0, 5, (50 + 10 * k, 3)).astype(np.float32) for k in range(3)]
    for k, c in enumerate(clouds):
        write_velodyne_bin(seq / "velodyne" / f"{k:06d}.bin", c, rng.random(len(c)))
    lidar = np.stack([se3.from_rt(Rotation.from_rotvec([0, 0, 0.1 * k]).as_matrix(), [k, 0.5 * k, 0]) for k in range(3)])
    tr = " ".join(f"{v:.17g}" for v in TR[:3].ravel())
    (seq / "calib.txt").write_text("P0: " + " ".join(["0"] * 12) + "\nTr: " + tr + "\n")
    (tmp_path / "poses").mkdir()
    write_kitti_poses(tmp_path / "poses" / "07.txt", TR @ lidar @ np.linalg.inv(TR))  # camera-0 poses
    return seq, clouds, lidar


def test_bin_round_trip(tmp_path):
    xyz = np.array([[1.0, 2.0, 3.0], [-4.5, 0.25, 1e-3]], np.float32)
    write_velodyne_bin(tmp_path / "a.bin", xyz)
    np.testing.assert_array_equal(read_velodyne_bin(tmp_path / "a.bin"), xyz)
    (tmp_path / "bad.bin").write_bytes(b"\0" * 18)
    with pytest.raises(InputError, match="bad.bin: not a KITTI velodyne scan"):
        read_velodyne_bin(tmp_path / "bad.bin")


def test_sequence_loads_with_lidar_poses(sequence):
    seq, clouds, lidar = sequence
    assert detect_format(seq) == "kitti"
    scans = load_scans(seq)
    assert scans.num_scans == 3 and scans.pose_dof == 6 and scans.points.shape == (3, 70, 3)
    assert scans.valid.sum(1).tolist() == [50, 60, 70]
    np.testing.assert_allclose(scans.points[1][scans.valid[1]], clouds[1])
    np.testing.assert_allclose(scans.gt_poses, lidar, atol=1e-9)  # camera poses turned into LiDAR poses


def test_count_mismatch_names_the_file(sequence, tmp_path):
    seq, _, lidar = sequence
    write_kitti_poses(tmp_path / "two.txt", lidar[:2])
    with pytest.raises(InputError, match="two.txt: 2 ground-truth poses for 3 scans"):
        load_scans(seq, gt_path=tmp_path / "two.txt")
