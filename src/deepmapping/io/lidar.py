"""LiDAR trajectory folders -> unorganized 3D ScanSets.

Layout (written by ``deepmapping.sim.lidar.write_lidar_dataset``)::

    traj/scans/000000.ply ...   x y z in the sensor frame (metres); .pcd also accepted
    traj/gt_poses.txt           optional: sensor-to-world poses (KITTI / TUM / .npy via read_poses_3d)
    traj/meta.json              optional: {"pose_dof": 3 | 6, ...} (default 6)

Scans have different sizes: they are padded with invalid all-zero points to the largest
one, or randomly subsampled (seeded) to at most ``max_points`` points each.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.io.clouds import check_max_points, pad_clouds, subsample
from deepmapping.io.pcd import read_pcd
from deepmapping.io.ply import read_ply
from deepmapping.io.rgbd import load_pose_files, read_json, sorted_files

__all__ = ["is_lidar_folder", "load_lidar"]

_SUFFIXES = (".ply", ".pcd")


def is_lidar_folder(path: str | os.PathLike) -> bool:
    """True for a folder with a ``scans/`` subfolder holding .ply or .pcd files."""
    scans = Path(path) / "scans"
    return scans.is_dir() and any(p.suffix.lower() in _SUFFIXES for p in scans.iterdir())


def _read_cloud(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".pcd":
        xyz = read_pcd(path)
    else:
        xyz = read_ply(path)
    if xyz.shape[0] == 0:
        raise InputError(f"{path}: scan has no point")
    if not np.isfinite(xyz).all():
        raise InputError(f"{path}: contains NaN or inf coordinates")
    return xyz


def load_lidar(folder: str | os.PathLike, gt_path=None, init_path=None, max_points: int | None = None,
               seed: int = 0) -> ScanSet:
    """Read every scan of ``folder/scans`` into a padded, unorganized ScanSet (metres, unit "m")."""
    folder = Path(folder)
    scans_dir = folder / "scans"
    if not scans_dir.is_dir():
        raise InputError(f"{scans_dir}: folder not found")
    files = sorted_files(scans_dir, _SUFFIXES)
    if len(files) < 2:
        raise InputError(f"{scans_dir}: need at least two scans (.ply/.pcd), found {len(files)}")
    check_max_points(folder, max_points)
    rng = np.random.default_rng(seed)
    points, valid = pad_clouds([subsample(_read_cloud(f), max_points, rng) for f in files])
    gt, init = load_pose_files(folder, len(files), gt_path, init_path)
    dof = read_json(folder / "meta.json", required=False).get("pose_dof", 6)
    if dof not in (3, 6):
        raise InputError(f"{folder / 'meta.json'}: pose_dof must be 3 or 6, got {dof!r}")
    return ScanSet(points=points, valid=valid, gt_poses=gt, init_poses=init, unit_scale=1.0, unit="m",
                   ordered=True, names=[f.name for f in files], source=str(folder), grid_shape=None,
                   pose_dof=int(dof)).validate()
