"""KITTI odometry sequences: ``velodyne/NNNNNN.bin`` (float32 x y z reflectance) + poses.

Layout (one sequence folder, as in ``dataset/sequences/00``)::

    00/velodyne/000000.bin ...   scans, metres, in the LiDAR frame
    00/calib.txt                 optional; its ``Tr:`` line maps LiDAR to camera 0
    00/poses.txt or ../../poses/00.txt   optional ground truth (KITTI text, camera 0 poses)

Ground-truth poses of KITTI are those of camera 0; with ``Tr`` they become LiDAR poses:
T_lidar = inv(Tr) · T_cam · Tr. Without calib.txt they are used as they are.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.io.atomic import read_user_file
from deepmapping.io.clouds import check_max_points, pad_clouds, subsample
from deepmapping.io.pcd import atomic_write
from deepmapping.io.poses3d import check_rotations, read_poses_3d

__all__ = ["is_kitti_folder", "read_velodyne_bin", "write_velodyne_bin", "read_calib_tr", "load_kitti", "DEFAULT_MAX_POINTS"]

DEFAULT_MAX_POINTS = 20000


def is_kitti_folder(path: str | os.PathLike) -> bool:
    vel = Path(path) / "velodyne"
    return vel.is_dir() and any(p.suffix == ".bin" for p in vel.iterdir())


def read_velodyne_bin(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) float32 points of one KITTI scan (the reflectance column is dropped)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    size = path.stat().st_size
    if size == 0 or size % 16:
        raise InputError(f"{path}: not a KITTI velodyne scan ({size} bytes is not a multiple of 16: x y z r float32)")
    xyz = np.fromfile(path, dtype="<f4").reshape(-1, 4)[:, :3]
    if not np.isfinite(xyz).all():
        raise InputError(f"{path}: contains NaN or inf coordinates")
    return xyz


def read_calib_tr(path: str | os.PathLike) -> np.ndarray | None:
    """The 4x4 LiDAR-to-camera-0 transform of a KITTI ``calib.txt`` (None if it has no Tr line)."""
    path = Path(path)
    for lineno, line in enumerate(read_user_file(path).decode("utf-8", errors="replace").splitlines(), start=1):
        key, _, rest = line.partition(":")
        if key.strip() == "Tr":
            try:
                vals = np.array([float(v) for v in rest.split()])
            except ValueError:
                vals = np.zeros(0)
            if vals.shape != (12,):
                raise InputError(f"{path}:{lineno}: Tr needs 12 numbers")
            if not np.isfinite(vals).all():
                raise InputError(f"{path}:{lineno}: Tr contains NaN or inf")

            tr = np.vstack([vals.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
            return check_rotations(path, tr[None], [lineno])[0]  # a rigid transform (it is inverted)
    return None


def _gt_file(folder: Path, gt_path) -> Path | None:
    if gt_path is not None:
        return Path(gt_path)
    for cand in (folder / "poses.txt", folder.parent.parent / "poses" / f"{folder.name}.txt"):
        if cand.is_file():
            return cand
    return None


def load_kitti(folder: str | os.PathLike, gt_path=None, init_path=None, max_points: int | None = DEFAULT_MAX_POINTS,
               seed: int = 0):
    """A KITTI sequence as an unorganized 6-DoF ScanSet (metres), each scan subsampled to
    ``max_points`` (None = all)."""
    folder = Path(folder)
    files = sorted((folder / "velodyne").glob("*.bin"))
    if len(files) < 2:
        raise InputError(f"{folder / 'velodyne'}: need at least two .bin scans, found {len(files)}")
    check_max_points(folder, max_points)
    rng = np.random.default_rng(seed)
    points, valid = pad_clouds([subsample(read_velodyne_bin(f), max_points, rng) for f in files])
    tr = read_calib_tr(folder / "calib.txt") if (folder / "calib.txt").is_file() else None

    def poses(path, label):
        p = read_poses_3d(path)
        if len(p) != len(files):
            raise InputError(f"{path}: {len(p)} {label} for {len(files)} scans (counts differ)")
        return p if tr is None else np.linalg.inv(tr) @ p @ tr

    gt_file = _gt_file(folder, gt_path)
    gt = poses(gt_file, "ground-truth poses") if gt_file is not None else None
    init = poses(init_path, "initial poses") if init_path is not None else None
    return ScanSet(points=points, valid=valid, gt_poses=gt, init_poses=init, unit_scale=1.0, unit="m",
                   ordered=True, names=[f.name for f in files], source=str(folder), pose_dof=6).validate()


def write_velodyne_bin(path: str | os.PathLike, xyz, reflectance=None) -> None:
    """Write (N, 3) points as a KITTI ``.bin`` (float32 x y z r; r = 0 by default), atomically."""
    xyz = np.asarray(xyz, dtype=np.float32)
    r = np.zeros(len(xyz), np.float32) if reflectance is None else np.asarray(reflectance, np.float32)
    data = np.column_stack([xyz, r]).astype("<f4").tobytes()
    atomic_write(path, lambda f: f.write(data))
