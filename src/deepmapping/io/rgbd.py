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

import json
import os
from pathlib import Path

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.io.poses3d import read_poses_3d

__all__ = ["is_rgbd_folder", "load_rgbd", "read_json", "read_depth_png", "load_pose_files", "sorted_files"]

_INTR_KEYS = ("width", "height", "fx", "fy", "cx", "cy")


def sorted_files(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    """Files of ``folder`` ending in one of ``suffixes`` (no hidden ones), natural order (2 < 10)."""
    from deepmapping.io.loaders import natural_key

    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.name))


def is_rgbd_folder(path: str | os.PathLike) -> bool:
    """True for a folder holding ``intrinsics.json`` or a ``depth/`` subfolder."""
    path = Path(path)
    return path.is_dir() and ((path / "intrinsics.json").is_file() or (path / "depth").is_dir())


def read_json(path: Path, required: bool = True) -> dict:
    """A JSON object from ``path``; {} when absent and not ``required``; InputError otherwise."""
    if not path.is_file():
        if required:
            raise InputError(f"{path}: file not found")
        return {}
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:  # RecursionError: nested too deep
        raise InputError(f"{path}: invalid JSON ({type(e).__name__}: {e})".splitlines()[0]) from None
    if not isinstance(obj, dict):
        raise InputError(f"{path}: expected a JSON object")
    return obj


def _intrinsics(path: Path) -> dict:
    intr = read_json(path)
    missing = [k for k in _INTR_KEYS if k not in intr]
    if missing:
        raise InputError(f"{path}: missing keys {', '.join(missing)}")
    try:
        out = {k: float(intr[k]) for k in _INTR_KEYS}
        out["depth_scale"] = float(intr.get("depth_scale", 1000.0))
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer too large for a float
        raise InputError(f"{path}: intrinsics must be numbers") from None
    if not all(np.isfinite(v) for v in out.values()) or min(out["fx"], out["fy"], out["depth_scale"]) <= 0:
        raise InputError(f"{path}: fx, fy and depth_scale must be positive finite numbers")
    return out


def read_depth_png(path: Path) -> np.ndarray:
    """(H, W) uint16 depth image; InputError naming the file if unreadable or not 16-bit grey."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            img.load()
            mode = img.mode
            arr = np.array(img)
    except Exception as e:  # PIL raises OSError, SyntaxError, ValueError, ... on corrupt data
        raise InputError(f"{path}: cannot read PNG ({type(e).__name__}: {e})".splitlines()[0]) from None
    if not mode.startswith("I;16") or arr.ndim != 2:
        raise InputError(f"{path}: depth must be a 16-bit single-channel PNG (uint16 mm), got mode {mode}")
    return arr.astype(np.uint16)


def load_pose_files(folder: Path, k: int, gt_path=None, init_path=None, gt_default: str = "gt_poses.txt"):
    """(gt, init) poses (K, 4, 4) or None; InputError naming the file when the count is not k."""
    out = []
    for path in (Path(gt_path) if gt_path else (folder / gt_default if (folder / gt_default).is_file() else None),
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


def load_rgbd(folder: str | os.PathLike, gt_path=None, init_path=None, stride: int = 1) -> ScanSet:
    """Back-project every depth image of ``folder`` into an organized ScanSet (metres, unit "mm").

    ``stride`` keeps every stride-th row and column: grid_shape = (ceil(H/s), ceil(W/s)).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    if stride < 1:
        raise InputError(f"{folder}: stride must be >= 1, got {stride}")
    intr = _intrinsics(folder / "intrinsics.json")
    depth_dir = folder / "depth"
    files = sorted_files(depth_dir, (".png",)) if depth_dir.is_dir() else []
    if len(files) < 2:
        raise InputError(f"{depth_dir}: need at least two depth PNGs, found {len(files)}")
    images = [read_depth_png(f) for f in files]
    for f, img in zip(files, images):
        if img.shape != images[0].shape:
            raise InputError(f"{f}: image size {img.shape[1]}x{img.shape[0]} differs from "
                             f"{files[0].name} ({images[0].shape[1]}x{images[0].shape[0]})")
    h, w = images[0].shape
    if (w, h) != (int(intr["width"]), int(intr["height"])):
        raise InputError(f"{files[0]}: image is {w}x{h} but intrinsics.json says {intr['width']:g}x{intr['height']:g}")
    z = np.stack(images)[:, ::stride, ::stride].astype(np.float64) / intr["depth_scale"]
    v, u = np.mgrid[0:h:stride, 0:w:stride].astype(np.float64)
    pts = np.stack([(u - intr["cx"]) * z / intr["fx"], (v - intr["cy"]) * z / intr["fy"], z], axis=-1)
    k, hs, ws = z.shape
    gt, init = load_pose_files(folder, k, gt_path, init_path)
    return ScanSet(
        points=pts.reshape(k, hs * ws, 3).astype(np.float32), valid=(z > 0).reshape(k, hs * ws),
        gt_poses=gt, init_poses=init, unit_scale=1000.0, unit="mm", ordered=True,
        names=[f.name for f in files], source=str(folder), grid_shape=(hs, ws), pose_dof=_pose_dof(folder),
    ).validate()
