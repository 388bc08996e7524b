"""TUM RGB-D folders -> organized 6-DoF depth ScanSets (metres, reported in mm).

Layout (Sturm et al., IROS 2012; one folder per sequence, e.g. ``rgbd_dataset_freiburg1_xyz``)::

    seq/depth.txt          '#' comments, then 'timestamp file' per line (file: depth/<timestamp>.png)
    seq/depth/*.png        uint16 depth (z), 5000 per metre, 0 = no data
    seq/groundtruth.txt    optional: TUM trajectory 'timestamp tx ty tz qx qy qz qw' (camera to
                           world, motion capture, ~100 Hz)
    seq/camera-intrinsics.txt or seq/intrinsics.json   optional: the camera, replacing the default

Each depth frame takes the ground-truth pose with the nearest timestamp; frames with none within
``MAX_DT_S`` (20 ms, as TUM's associate.py) are dropped and the ScanSet's notes say how many.
The camera defaults to the values TUM gives for turning its depth images into points, the same
for every sequence (fx = fy = 525, cx = 319.5, cy = 239.5: the depth images are registered to the
colour camera by OpenNI's factory calibration); ``--intrinsics fr1|fr2|fr3`` picks TUM's own
calibration of that Kinect's colour camera instead (without its lens distortion).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.io.atomic import read_user_text
from deepmapping.io.depth import INTRINSICS_PRESETS, DepthOptions, as_path, camera_from, depth_scanset, select_frames
from deepmapping.io.poses3d import read_tum_trajectory
from deepmapping.io.rgbd import load_pose_files

__all__ = ["is_tum_rgbd_folder", "load_tum_rgbd", "read_depth_list", "match_timestamps", "MAX_DT_S"]

MAX_DT_S = 0.02  # a depth frame and its ground-truth pose are at most this far apart in time


def is_tum_rgbd_folder(path: str | os.PathLike) -> bool:
    """True for a folder holding ``depth.txt`` and a ``depth/`` subfolder."""
    path = Path(path)
    return path.is_dir() and (path / "depth.txt").is_file() and (path / "depth").is_dir()


def read_depth_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    """``depth.txt`` -> (timestamps (S,) strictly increasing, image paths); InputError naming it."""
    stamps, files = [], []
    for lineno, line in enumerate(read_user_text(path).splitlines(), start=1):
        tok = line.split("#", 1)[0].split()
        if not tok:
            continue
        if len(tok) != 2:
            raise InputError(f"{path}: line {lineno}: expected 'timestamp file', got {len(tok)} fields")
        try:
            t = float(tok[0])
        except ValueError:
            raise InputError(f"{path}: line {lineno}: the timestamp is not a number") from None
        if not np.isfinite(t) or (stamps and t <= stamps[-1]):
            raise InputError(f"{path}: line {lineno}: timestamps must be finite and increasing")
        stamps.append(t)
        files.append(path.parent / tok[1])
    if not stamps:
        raise InputError(f"{path}: no depth frame listed")
    return np.array(stamps), files


def match_timestamps(query: np.ndarray, ref: np.ndarray, max_dt: float = MAX_DT_S) -> np.ndarray:
    """For each query time, the index of the nearest ``ref`` time, or -1 when none is within ``max_dt``."""
    order = np.argsort(ref, kind="stable")
    r = ref[order]
    hi = np.clip(np.searchsorted(r, query), 0, len(r) - 1)
    lo = np.clip(hi - 1, 0, len(r) - 1)
    best = np.where(np.abs(r[lo] - query) <= np.abs(r[hi] - query), lo, hi)
    return np.where(np.abs(r[best] - query) <= max_dt, order[best], -1)


def _ground_truth(path: Path, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray, str | None]:
    """(kept frame positions, their poses, a note or None): frames matched to a pose within MAX_DT_S."""
    gt_stamps, poses = read_tum_trajectory(path)
    match = match_timestamps(stamps, gt_stamps)
    keep = np.flatnonzero(match >= 0)
    if len(keep) < 2:
        raise InputError(f"{path}: {len(keep)} of {len(stamps)} depth frames have a pose within "
                         f"{MAX_DT_S * 1000:g} ms (timestamps of another sequence?)")
    dropped = len(stamps) - len(keep)
    note = (f"{path}: {dropped} of {len(stamps)} depth frames have no pose within {MAX_DT_S * 1000:g} ms "
            f"and were left out") if dropped else None
    return keep, poses[match[keep]], note


def load_tum_rgbd(folder: str | os.PathLike, gt_path=None, init_path=None,
                  depth: DepthOptions | None = None) -> ScanSet:
    """The depth frames of a TUM RGB-D sequence as a 6-DoF ScanSet, ground truth matched by time
    (``gt_path``: another TUM trajectory). ``init_path``: one pose per frame kept after matching
    (KITTI / TUM / .npy), before ``--frames`` / ``--every``."""
    folder = as_path(folder)
    opts = depth or DepthOptions()
    stamps, files = read_depth_list(folder / "depth.txt")
    keep, gt, note = np.arange(len(files)), None, None
    gt_file = Path(gt_path) if gt_path else folder / "groundtruth.txt"
    if gt_path or gt_file.is_file():
        keep, gt, note = _ground_truth(gt_file, stamps)
    _, init = load_pose_files(folder, len(keep), None, init_path, gt_default=None)
    cam = camera_from(opts.intrinsics, [folder / "camera-intrinsics.txt", folder / "intrinsics.json"],
                      INTRINSICS_PRESETS["tum"], 5000.0, folder / "camera-intrinsics.txt")
    idx = select_frames(folder / "depth.txt", len(keep), opts)
    for f in (files[keep[i]] for i in idx):
        if not f.is_file():
            raise InputError(f"{f}: file not found (listed in {folder / 'depth.txt'})")
    scans = depth_scanset(folder, [files[keep[i]] for i in idx], cam, opts,
                          None if gt is None else gt[idx], None if init is None else init[idx])
    scans.notes = [note] if note else []
    return scans
