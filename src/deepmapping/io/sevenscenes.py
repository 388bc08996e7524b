"""7-Scenes / 3DMatch RGB-D folders -> organized 6-DoF depth ScanSets (metres, reported in mm).

Layout (Microsoft's 7-Scenes, 3DMatch's RGB-D sequences, TSDF-fusion demos)::

    seq/frame-000000.depth.png   uint16 depth (z) in mm; 0 and 65535 = no measurement
    seq/frame-000000.pose.txt    optional: 4x4 camera-to-world matrix, metres (OpenCV camera axes)
    seq/camera-intrinsics.txt    3x3 K of the depth camera (also looked for one folder up, where
                                 3DMatch keeps it next to its seq-NN folders)

Colour images (``frame-*.color.png``) are ignored. Pose files are the ground truth: every depth
image has one, or none has. 7-Scenes itself ships no K file: ``--intrinsics 7scenes`` gives its
published depth camera (fx = fy = 585, cx = 320, cy = 240).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.io.atomic import read_user_text
from deepmapping.io.depth import DepthOptions, as_path, camera_from, depth_scanset, natural_sorted, select_frames
from deepmapping.io.poses3d import check_rotations
from deepmapping.io.rgbd import load_pose_files

__all__ = ["is_7scenes_folder", "load_7scenes", "read_pose_matrix", "frame_files"]

FRAME_RE = re.compile(r"^frame-(\d+)\.depth\.png$", re.IGNORECASE)
K_NAME = "camera-intrinsics.txt"


def frame_files(folder: Path) -> list[Path]:
    """The ``frame-NNNNNN.depth.png`` files of ``folder``, by frame number."""
    return natural_sorted(p for p in folder.iterdir() if FRAME_RE.match(p.name) and p.is_file())


def is_7scenes_folder(path: str | os.PathLike) -> bool:
    """True for a folder holding ``frame-*.depth.png`` images."""
    path = Path(path)
    return path.is_dir() and any(FRAME_RE.match(p.name) for p in path.iterdir())


def read_pose_matrix(path: Path) -> np.ndarray:
    """One ``frame-*.pose.txt``: a 4x4 rigid matrix (16 numbers); InputError naming the file otherwise."""
    try:
        vals = np.array([float(t) for t in read_user_text(path).split()], dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: expected a 4x4 pose matrix (16 numbers)") from None
    if vals.size != 16:
        raise InputError(f"{path}: expected a 4x4 pose matrix (16 numbers), got {vals.size}")
    pose = vals.reshape(4, 4)
    if not np.isfinite(pose).all():
        raise InputError(f"{path}: NaN or inf in the pose (a frame the tracker lost?)")
    if np.abs(pose[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise InputError(f"{path}: the last row of a pose must be 0 0 0 1")
    return check_rotations(path, pose[None])[0]


def _frame_poses(files: list[Path], idx: np.ndarray) -> np.ndarray | None:
    """Each selected frame's ``.pose.txt``; None when the folder has no pose file at all."""
    poses = [f.with_name(f.name[: -len(".depth.png")] + ".pose.txt") for f in files]
    have = [p.is_file() for p in poses]
    if not any(have):
        return None
    if not all(have):
        missing = poses[have.index(False)]
        raise InputError(f"{missing}: file not found ({sum(have)} pose files for {len(files)} depth images)")
    return np.stack([read_pose_matrix(poses[i]) for i in idx])


def load_7scenes(folder: str | os.PathLike, gt_path=None, init_path=None, depth: DepthOptions | None = None) -> ScanSet:
    """The depth images of a 7-Scenes folder as a 6-DoF ScanSet; ground truth from the pose files
    (or ``gt_path``: one file with a pose per depth image, KITTI / TUM / .npy)."""
    folder = as_path(folder)
    opts = depth or DepthOptions()
    files = frame_files(folder)
    if len(files) < 2:
        raise InputError(f"{folder}: need at least two frame-*.depth.png images, found {len(files)}")
    cam = camera_from(opts.intrinsics, [folder / K_NAME, folder.parent / K_NAME], None, 1000.0, folder / K_NAME)
    gt, init = load_pose_files(folder, len(files), gt_path, init_path, gt_default=None)
    idx = select_frames(folder, len(files), opts)
    gt = _frame_poses(files, idx) if gt is None else gt[idx]
    return depth_scanset(folder, [files[i] for i in idx], cam, opts, gt, None if init is None else init[idx])
