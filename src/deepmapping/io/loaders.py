"""Dataloaders: turn a folder of scans (+ optional poses) into a validated ScanSet.

Formats live in a registry so later formats (KITTI, CARMEN, 3DTK, ...) only need
``register_loader(name, loader, detector)`` (3D: "rgbd", "lidar", "bunny", "3dtk", "kitti",
"tum-rgbd", "7scenes" at the end; 2D logs: "carmen"):

- ``"authors"``: the DeepMapping authors' layout, a folder with ``000.pcd, 001.pcd, ...``
  and ``gt_pose.mat`` (key ``pose``, rows ``[x_px, y_px, theta]``). Points are px/512;
  the gt positions are divided by 512 to match; ``unit_scale=512``, ``unit="px"``.
- ``"folder"``: a folder of ``.pcd`` / ``.ply`` / ``.npy`` scans (npy: (N, 2) or (N, 3)),
  ``unit_scale=1``, ``unit="m"``. Ground truth from ``gt_path`` or, if present,
  ``gt_pose.txt`` / ``poses.txt`` in the folder (same units as the points).

Scans are sorted by file name in natural (numeric) order: ``2.pcd < 10.pcd``,
``000 < 001 < ... < 1000``. Only organized 2D scans are supported for now: every scan
must have the same number of points, and z (when present) must be 0. An all-zero point is
a beam without return (``valid=False``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import ConfigError, InputError
from deepmapping.io.clouds import pad_clouds
from deepmapping.io.pcd import read_pcd
from deepmapping.io.ply import read_ply
from deepmapping.io.poses import read_gt_mat, read_poses
from deepmapping.io.poses3d import read_poses_3d

__all__ = [
    "LOADERS",
    "DETECTORS",
    "SCAN_SUFFIXES",
    "AUTHORS_GT_NAME",
    "AUTHORS_SCALE",
    "register_loader",
    "detect_format",
    "load_scans",
    "load_authors",
    "load_folder",
    "read_scan_file",
    "natural_key",
]

Loader = Callable[[Path, "Path | None", "Path | None"], ScanSet]
Detector = Callable[[Path], bool]

SCAN_SUFFIXES = (".pcd", ".ply", ".npy", ".xyz")
AUTHORS_GT_NAME = "gt_pose.mat"
AUTHORS_SCALE = 512.0
FOLDER_GT_NAMES = ("gt_pose.txt", "poses.txt")
# pose files that may sit next to the scans and are never read as scans
_POSE_STEMS = {"gt_pose", "gt_poses", "pose", "poses", "init_pose", "init_poses"}
Z_TOL = 1e-6


def natural_key(name: str) -> list:
    """Sort key putting ``2.pcd`` before ``10.pcd`` (digit runs compared as numbers)."""
    return [(0, int(t), t) if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", name) if t]


def _scan_files(folder: Path, suffixes: tuple[str, ...] = SCAN_SUFFIXES) -> list[Path]:
    files = [
        p for p in folder.iterdir()
        if p.is_file() and p.suffix.lower() in suffixes and p.stem.lower() not in _POSE_STEMS
        and not p.name.startswith(".")
    ]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_scan_file(path: Path) -> tuple[np.ndarray, int]:
    """Read one scan file: returns ((N, 3) float32 x y z, coordinate dimension 2 or 3).

    The dimension is 2 for an (N, 2) .npy, 3 for an (N, 3) .npy and for PCD/PLY files.
    """
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        return read_pcd(path), 3
    if suffix == ".ply":
        return read_ply(path), 3
    if suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as e:
            raise InputError(f"{path}: cannot read .npy file ({type(e).__name__}: {e})".splitlines()[0]) from None
        if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] not in (2, 3):
            raise InputError(f"{path}: scan must be an (N, 2) or (N, 3) array, got shape {getattr(arr, 'shape', None)}")
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise InputError(f"{path}: scan must be numeric, got dtype {arr.dtype}")
        dim = arr.shape[1]
        out = np.zeros((arr.shape[0], 3), dtype=np.float32)
        out[:, :dim] = arr
        return out, dim
    if suffix == ".xyz":
        return _read_xyz(path), 3
    raise InputError(f"{path}: unsupported scan file type {suffix!r} (expected {', '.join(SCAN_SUFFIXES)})")


def _read_xyz(path: Path) -> np.ndarray:
    """A text ``.xyz`` cloud: ``x y z`` per line (more columns ignored, ``#`` comments skipped)."""
    rows = []
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        tok = line.split("#", 1)[0].replace(",", " ").split()
        if not tok:
            continue
        try:
            if len(tok) < 3:
                raise ValueError
            rows.append([float(t) for t in tok[:3]])
        except ValueError:
            raise InputError(f"{path}: line {lineno}: expected 'x y z'") from None
    return np.asarray(rows, dtype=np.float32).reshape(-1, 3)


class _ThreeD(Exception):
    """A scan of the folder has non-zero z: the folder holds 3D clouds."""


def _stack_scans(folder: Path, files: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    """Read, check and stack 2D organized scans; returns points (K, N, 2) f32, valid (K, N)."""
    pts_list: list[np.ndarray] = []
    first_dim: int | None = None
    for f in files:
        xyz, dim = read_scan_file(f)
        if first_dim is None:
            first_dim = dim
        elif dim != first_dim:
            raise InputError(
                f"{f}: scans of different dimension: {f.name} has {dim} columns, {files[0].name} has {first_dim}"
            )
        if xyz.shape[0] == 0:
            raise InputError(f"{f}: scan has no point")
        if not np.isfinite(xyz).all():
            raise InputError(f"{f}: contains NaN or inf coordinates")
        if np.abs(xyz[:, 2]).max() > Z_TOL:
            raise _ThreeD(f"{f}: 3D scans are not supported in this layout (non-zero z)")
        if pts_list and xyz.shape[0] != pts_list[0].shape[0]:
            raise InputError(
                f"{f}: scans of different sizes are not supported for organized 2D scans: "
                f"{f.name} has {xyz.shape[0]} points, {files[0].name} has {pts_list[0].shape[0]}"
            )
        pts_list.append(np.ascontiguousarray(xyz[:, :2]))
    points = np.stack(pts_list).astype(np.float32)
    valid = np.any(points != 0, axis=2)
    return points, valid


def _check_count(path: Path, poses: np.ndarray, k: int, label: str) -> None:
    if poses.shape[0] != k:
        raise InputError(f"{path}: {poses.shape[0]} {label} for {k} scans (counts differ)")


def _require_scans(folder: Path, files: list[Path], what: str) -> None:
    if not files:
        raise InputError(f"{folder}: no scan files ({what}) found")
    if len(files) < 2:
        raise InputError(f"{folder}: need at least two scans, got 1 ({files[0].name})")


def load_authors(folder: Path, gt_path: Path | None = None, init_path: Path | None = None) -> ScanSet:
    """Load the authors' layout: sorted ``*.pcd`` (x y, z = 0, px/512) + ``gt_pose.mat``.

    The ground truth (``gt_path`` if given, else ``folder/gt_pose.mat`` if it exists) is
    read as in the authors' convention: rows ``[x_px, y_px, theta]`` (.mat key ``pose``,
    or text / .npy with the same columns) and x, y are divided by 512. ``init_path`` poses
    are in the SAME units as the scan points (px/512), not divided.
    """
    _check_dir(folder)
    files = _scan_files(folder, (".pcd",))
    _require_scans(folder, files, "*.pcd")
    try:
        points, valid = _stack_scans(folder, files)
    except _ThreeD as e:
        raise InputError(str(e)) from None
    k = points.shape[0]
    gt = None
    gt_file = gt_path if gt_path is not None else folder / AUTHORS_GT_NAME
    if gt_path is not None or gt_file.exists():
        gt = read_gt_mat(gt_file) if gt_file.suffix.lower() == ".mat" else read_poses(gt_file)
        gt = gt.copy()
        gt[:, :2] /= AUTHORS_SCALE
        _check_count(gt_file, gt, k, "ground-truth poses")
    init = None
    if init_path is not None:
        init = read_poses(init_path)
        _check_count(init_path, init, k, "initial poses")
    return ScanSet(
        points=points, valid=valid, gt_poses=gt, init_poses=init,
        unit_scale=AUTHORS_SCALE, unit="px", ordered=True,
        names=[f.name for f in files], source=str(folder),
    ).validate()


def load_folder(folder: Path, gt_path: Path | None = None, init_path: Path | None = None) -> ScanSet:
    """Load a folder of ``.pcd`` / ``.ply`` / ``.npy`` 2D scans (metres, unit_scale 1).

    Ground truth: ``gt_path`` (text ``x y theta``, .mat key ``pose`` or .npy), else
    ``gt_pose.txt`` or ``poses.txt`` in the folder if present, else none. Both ground
    truth and ``init_path`` poses are in the same units as the scan points.
    Files named ``gt_pose*``, ``poses*``, ``init_pose*`` are never read as scans.
    """
    _check_dir(folder)
    files = _scan_files(folder)
    _require_scans(folder, files, ", ".join(SCAN_SUFFIXES))
    try:
        points, valid = _stack_scans(folder, files)
    except _ThreeD:
        return _load_clouds_folder(folder, files, gt_path, init_path)
    k = points.shape[0]
    if gt_path is None:
        gt_path = next((folder / n for n in FOLDER_GT_NAMES if (folder / n).is_file()), None)
    gt = None
    if gt_path is not None:
        gt = read_poses(gt_path)
        _check_count(gt_path, gt, k, "ground-truth poses")
    init = None
    if init_path is not None:
        init = read_poses(init_path)
        _check_count(init_path, init, k, "initial poses")
    return ScanSet(
        points=points, valid=valid, gt_poses=gt, init_poses=init,
        unit_scale=1.0, unit="m", ordered=True,
        names=[f.name for f in files], source=str(folder),
    ).validate()


def _load_clouds_folder(folder: Path, files: list[Path], gt_path, init_path) -> ScanSet:
    """A folder of 3D clouds (any z != 0): unorganized 6-DoF scans, metres; poses KITTI/TUM/.npy
    (``gt_path``, else ``poses.txt`` / ``gt_poses.txt`` in the folder)."""
    clouds = []
    for f in files:
        xyz, _ = read_scan_file(f)
        if xyz.shape[0] == 0:
            raise InputError(f"{f}: scan has no point")
        if not np.isfinite(xyz).all():
            raise InputError(f"{f}: contains NaN or inf coordinates")
        clouds.append(xyz)
    points, valid = pad_clouds(clouds)
    if gt_path is None:
        gt_path = next((folder / n for n in ("poses.txt", "gt_poses.txt") if (folder / n).is_file()), None)
    gt = read_poses_3d(gt_path) if gt_path is not None else None
    init = read_poses_3d(init_path) if init_path is not None else None
    for path, poses, label in ((gt_path, gt, "ground-truth poses"), (init_path, init, "initial poses")):
        if poses is not None:
            _check_count(path, poses, len(files), label)
    return ScanSet(points=points, valid=valid, gt_poses=gt, init_poses=init, unit_scale=1.0, unit="m",
                   ordered=True, names=[f.name for f in files], source=str(folder), pose_dof=6).validate()


def _is_authors(path: Path) -> bool:
    return path.is_dir() and (path / AUTHORS_GT_NAME).is_file() and bool(_scan_files(path, (".pcd",)))


def _is_folder(path: Path) -> bool:
    return path.is_dir() and bool(_scan_files(path))


LOADERS: dict[str, Loader] = {"authors": load_authors, "folder": load_folder}
# checked in order; the first detector returning True names the format
DETECTORS: list[tuple[str, Detector]] = [("authors", _is_authors), ("folder", _is_folder)]


def register_loader(name: str, loader: Loader, detector: Detector | None = None, first: bool = True) -> None:
    """Add (or replace) a format: ``loader(path, gt_path, init_path) -> ScanSet``.

    ``detector(path) -> bool`` lets ``detect_format`` pick it; inserted before the generic
    detectors when ``first`` is True.
    """
    LOADERS[name] = loader
    DETECTORS[:] = [(n, d) for n, d in DETECTORS if n != name]
    if detector is not None:
        if first:
            DETECTORS.insert(0, (name, detector))
        else:
            DETECTORS.append((name, detector))


def _check_exists(path: Path) -> None:
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")


def _check_dir(path: Path) -> None:
    _check_exists(path)
    if not path.is_dir():
        raise InputError(f"{path}: not a folder (expected a folder of scans)")


def detect_format(path: str | os.PathLike) -> str:
    """Name of the registered format that ``path`` looks like; InputError when none does."""
    path = Path(path)
    _check_exists(path)
    for name, det in DETECTORS:
        if det(path):
            return name
    _check_dir(path)
    raise InputError(f"{path}: no scan files ({', '.join(SCAN_SUFFIXES)}) found")


def load_scans(
    path: str | os.PathLike,
    fmt: str | None = None,
    gt_path: str | os.PathLike | None = None,
    init_path: str | os.PathLike | None = None,
    keyframes: str | None = None,
    non_keyframes: str | None = None,
    depth=None,
) -> ScanSet:
    """Load scans from ``path`` with the loader ``fmt`` (auto-detected when None).

    gt_path: ground-truth poses overriding the folder's own. For the authors' layout it
    is read like ``gt_pose.mat`` (px, x and y divided by 512); for the other formats it
    is in the units of the scan points.
    init_path: initial poses (warm start), text ``x y theta`` / .npy / .mat (K, 3), always
    in the SAME units as the scan points (for the authors' layout: px/512, not px).
    keyframes: for sequences read from one log (CARMEN), which scans to register
    (see :mod:`deepmapping.sequence`), and how the other scans are placed
    (``non_keyframes``: "icp" or "odometry"); other formats refuse both.
    depth: for depth-image folders (``DEPTH_FORMATS``), a ``io.depth.DepthOptions`` (frames, pixels,
    max depth, camera); other formats refuse one that is not the default.
    Returns a validated ScanSet (names = file names, source = folder path); every problem
    raises InputError (``"<path>: <problem>"``), an unknown ``fmt`` raises ConfigError.
    """
    path = Path(path)
    if fmt is None:
        fmt = detect_format(path)
    elif fmt not in LOADERS:
        raise ConfigError(f"{path}: unknown scan format {fmt!r} (known: {', '.join(sorted(LOADERS))})")
    else:
        _check_exists(path)
    extra = {k: v for k, v in (("keyframes", keyframes), ("non_keyframes", non_keyframes)) if v is not None}
    if extra and fmt not in KEYFRAME_FORMATS:
        raise ConfigError(f"{path}: keyframes apply to log formats ({', '.join(KEYFRAME_FORMATS)}), not {fmt!r}")
    if depth is not None and fmt in DEPTH_FORMATS:
        extra["depth"] = depth
    elif depth is not None and not depth.is_default():
        raise ConfigError(f"{path}: frame and pixel options apply to depth images ({', '.join(DEPTH_FORMATS)}), "
                          f"not {fmt!r}")
    return LOADERS[fmt](
        path,
        Path(gt_path) if gt_path is not None else None,
        Path(init_path) if init_path is not None else None,
        **extra,
    )


# -- 3D formats (modules imported on use, so `import deepmapping` stays light) -------------------
def _lazy(module: str, func: str) -> Callable:
    def call(*args, **kwargs):
        import importlib

        return getattr(importlib.import_module(f"deepmapping.io.{module}"), func)(*args, **kwargs)

    return call


register_loader("rgbd", _lazy("rgbd", "load_rgbd"), _lazy("rgbd", "is_rgbd_folder"))
register_loader("lidar", _lazy("lidar", "load_lidar"), _lazy("lidar", "is_lidar_folder"))
register_loader("bunny", _lazy("bunny", "load_bunny"), _lazy("bunny", "is_bunny_folder"))
register_loader("3dtk", _lazy("threedtk", "load_3dtk"), _lazy("threedtk", "is_3dtk_folder"))
register_loader("carmen", _lazy("carmen", "load_carmen"), _lazy("carmen", "is_carmen_file"))
register_loader("kitti", _lazy("kitti", "load_kitti"), _lazy("kitti", "is_kitti_folder"))
# depth-image layouts; registered last, so detected first (a TUM folder also has a depth/ subfolder)
register_loader("tum-rgbd", _lazy("tum_rgbd", "load_tum_rgbd"), _lazy("tum_rgbd", "is_tum_rgbd_folder"))
register_loader("7scenes", _lazy("sevenscenes", "load_7scenes"), _lazy("sevenscenes", "is_7scenes_folder"))
KEYFRAME_FORMATS = ("carmen",)
DEPTH_FORMATS = ("rgbd", "7scenes", "tum-rgbd")
