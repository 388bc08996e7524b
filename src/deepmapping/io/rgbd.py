"""RGB-D trajectory folders (depth only, AVD-style, section 4.2) -> organized 3D ScanSets.

Layout (written by ``deepmapping.sim.rgbd.write_rgbd_dataset``)::

    traj/depth/000000.png ...   uint16 depth (z, not ray length), 1/depth_scale metres, 0 = no return
    traj/intrinsics.json        {"width", "height", "fx", "fy", "cx", "cy", "depth_scale", "max_depth_m"}
    traj/gt_poses.txt           optional: camera-to-world poses (KITTI / TUM / .npy via read_poses_3d)
    traj/meta.json              optional: {"pose_dof": 3 | 6, ...} (default 3)

Each depth pixel (u, v) with depth z is back-projected to the camera-frame point
(x, y, z) = ((u - cx) z / fx, (v - cy) z / fy, z) (OpenCV frame: x right, y down, z forward).
"""

from __future__ import annotations

import os
from pathlib import Path

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.io.depth import (
    DepthOptions,
    as_path,
    camera_from,
    depth_scanset,
    natural_sorted,
    read_depth_png,
    read_intrinsics_json,
    read_json,
    select_frames,
)
from deepmapping.io.poses3d import read_poses_3d

__all__ = ["is_rgbd_folder", "load_rgbd", "read_json", "read_intrinsics_json", "read_depth_png", "load_pose_files",
           "sorted_files"]


def sorted_files(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    """Files of ``folder`` ending in one of ``suffixes`` (no hidden ones), natural order (2 < 10)."""
    return natural_sorted(p for p in folder.iterdir()
                          if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith("."))


def is_rgbd_folder(path: str | os.PathLike) -> bool:
    """True for a folder holding ``intrinsics.json`` or a ``depth/`` subfolder."""
    path = Path(path)
    return path.is_dir() and ((path / "intrinsics.json").is_file() or (path / "depth").is_dir())


def load_pose_files(folder: Path, k: int, gt_path=None, init_path=None, gt_default: str | None = "gt_poses.txt"):
    """(gt, init) poses (K, 4, 4) or None; InputError naming the file when the count is not k.

    gt: ``gt_path``, else ``folder/gt_default`` when it exists (None: no default file)."""
    default = folder / gt_default if gt_default else None
    out = []
    for path in (Path(gt_path) if gt_path else (default if default is not None and default.is_file() else None),
                 Path(init_path) if init_path else None):
        poses = None if path is None else read_poses_3d(path)
        if poses is not None and len(poses) != k:
            raise InputError(f"{path}: {len(poses)} poses for {k} scans (counts differ)")
        out.append(poses)
    return out[0], out[1]


def _pose_dof(folder: Path) -> int:
    meta = read_json(folder / "meta.json", required=False)
    dof = meta.get("pose_dof", 3)
    if dof not in (3, 6):
        raise InputError(f"{folder / 'meta.json'}: pose_dof must be 3 or 6, got {dof!r}")
    return int(dof)


def load_rgbd(folder: str | os.PathLike, gt_path=None, init_path=None, stride: int = 1,
              depth: DepthOptions | None = None) -> ScanSet:
    """Back-project the depth images of ``folder`` into an organized ScanSet (metres, unit "mm").

    ``stride`` keeps every stride-th row and column: grid_shape = (ceil(H/s), ceil(W/s));
    ``depth`` (frames, pixels, max depth, camera; see io.depth) wins over it. Pose files hold a
    pose for every image of the folder; the selected frames keep theirs.
    """
    folder = as_path(folder)
    if stride < 1:
        raise InputError(f"{folder}: stride must be >= 1, got {stride}")
    opts = depth or DepthOptions()
    json_path = folder / "intrinsics.json"
    cam = camera_from(opts.intrinsics, [json_path], None, 1000.0, json_path)
    depth_dir = folder / "depth"
    files = sorted_files(depth_dir, (".png",)) if depth_dir.is_dir() else []
    if len(files) < 2:
        raise InputError(f"{depth_dir}: need at least two depth PNGs, found {len(files)}")
    gt, init = load_pose_files(folder, len(files), gt_path, init_path)
    idx = select_frames(depth_dir, len(files), opts)
    return depth_scanset(folder, [files[i] for i in idx], cam, opts, None if gt is None else gt[idx],
                         None if init is None else init[idx], _pose_dof(folder), default_stride=stride)
