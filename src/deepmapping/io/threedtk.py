"""3DTK / slam6D scan folders (``scanNNN.3d``, ``.pose``, ``.frames``) -> an unorganized ScanSet.

3DTK numbers are centimetres in a left-handed frame (x right, y up, z forward); every scan is
in its scanner's frame (sensor at the origin: in the sample data all points have z >= 0,
a 180-degree fan around the origin, the ground ~40 cm below it at y < 0).

- ``.3d``: ``x y z [more columns]`` per line; leading lines that are not three numbers (an
  optional header) are skipped.
- ``.pose``: position, then Euler angles θx θy θz in degrees: p_world = Rx Ry Rz p + t with
  the usual rotation matrices. Checked on the sample: for scan002 it equals the first
  ``.frames`` matrix (algorithm code 0, the initial pose) to 4.9e-7 (6 printed digits) and the
  translation exactly; Rz Ry Rx is off by 1.6e-4, transposed rotations by 4e-2. scan001's
  first frame already has code 1 (after an ICP step): it differs from .pose by 0.38 cm.
- ``.frames``: one line per slam6D step: a column-major 4x4 matrix (16 numbers), then the
  algorithm code; the last line is slam6D's final pose (a reference, not ground truth).

Loaded frame: right-handed metres, p = 0.01 * (x, -y, z): x right, y DOWN, z forward, the
camera convention of the RGB-D data. This is a mirror, so a 3DTK pose (R, t) becomes
(S R S, 0.01 S t) with S = diag(1, -1, 1): still a rotation, only signs change.
``read_frames``/``write_frames`` do this conversion; write prints 12 significant digits of
the centimetre values, so write_frames(read_frames(f)) gives back f's numbers exactly.
Lengths are reported in cm (``unit_scale`` 100, 3DTK's own unit).
"""

from __future__ import annotations

import io
import os
import re
from pathlib import Path
from typing import IO

import numpy as np

from deepmapping.data import ScanSet
from deepmapping.errors import InputError
from deepmapping.geometry import se3
from deepmapping.io.atomic import atomic_write, read_user_text
from deepmapping.io.clouds import check_max_points, pad_clouds, subsample
from deepmapping.io.poses3d import check_rotations, read_poses_3d

__all__ = ["is_3dtk_folder", "read_3d", "read_pose", "write_pose", "read_frames", "write_frames", "load_3dtk"]

_SCAN = re.compile(r"^scan(\d+)\.(3d|xyz)$")
_S = np.diag([1.0, -1.0, 1.0, 1.0])  # the mirror y -> -y (its own inverse)


def _to_ours(poses_cm: np.ndarray) -> np.ndarray:
    out = _S @ poses_cm @ _S
    out[..., :3, 3] /= 100.0
    return out


def _to_3dtk(poses_m: np.ndarray) -> np.ndarray:
    out = _S @ np.asarray(poses_m, np.float64) @ _S
    out[..., :3, 3] *= 100.0
    return out


def _scan_files(folder: Path) -> list[Path]:
    found: dict[int, Path] = {}
    for p in folder.iterdir():
        if (m := _SCAN.match(p.name)) and (int(m.group(1)) not in found or m.group(2) == "3d"):
            found[int(m.group(1))] = p  # scanNNN.3d wins over scanNNN.xyz
    return [found[k] for k in sorted(found)]


def is_3dtk_folder(path: str | os.PathLike) -> bool:
    """True for a folder with ``scanNNN.3d`` (or ``.xyz``) files, the first with its ``.pose``."""
    path = Path(path)
    files = _scan_files(path) if path.is_dir() else []
    return bool(files) and files[0].with_suffix(".pose").is_file()




def _is_point(line: str) -> bool:
    """True when a line begins with three numbers."""
    tok = line.split()[:3]
    try:
        return len([float(t) for t in tok]) == 3
    except ValueError:
        return False


def read_3d(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) float64 points of a ``.3d`` file (uos: cm, left-handed, y up), or of a ``.xyz``
    file (right-handed, z up) turned into uos numbers as 3DTK does: (x, y, z) -> (-y, z, x)."""
    path = Path(path)
    lines = read_user_text(path).splitlines()
    start = 0
    while start < len(lines) and not _is_point(lines[start]):  # skip a header
        start += 1
    try:
        pts = np.loadtxt(io.StringIO("\n".join(lines[start:])), usecols=(0, 1, 2), ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise InputError(f"{path}: malformed point line ({str(e).splitlines()[-1][:80]})") from None
    if len(pts) == 0:
        raise InputError(f"{path}: no point")
    bad = np.nonzero(~np.isfinite(pts).all(axis=1))[0]
    if len(bad):
        raise InputError(f"{path}: line {start + bad[0] + 1}: NaN or inf coordinate")
    if path.suffix.lower() == ".xyz":
        pts = np.column_stack([-pts[:, 1], pts[:, 2], pts[:, 0]])
    return pts


def read_pose(path: str | os.PathLike) -> np.ndarray:
    """(4, 4) pose of a ``.pose`` file (x y z, θx θy θz degrees), in 3DTK's numbers."""
    from scipy.spatial.transform import Rotation

    path = Path(path)
    try:
        v = np.array([float(t) for t in read_user_text(path).split()])
    except ValueError:
        raise InputError(f"{path}: expected 6 numbers 'x y z' and 'θx θy θz' (degrees)") from None
    if v.shape != (6,) or not np.isfinite(v).all():
        raise InputError(f"{path}: expected 6 finite numbers 'x y z' and 'θx θy θz' (degrees), got {v.size}")
    rot = Rotation.from_euler("XYZ", v[3:], degrees=True).as_matrix()  # intrinsic XYZ = Rx Ry Rz
    return se3.from_rt(rot, v[:3])


def read_frames(path: str | os.PathLike, return_codes: bool = False):
    """(M, 4, 4) poses of a ``.frames`` file in the loaded frame (metres, y down); with
    ``return_codes`` also the (M,) algorithm codes (-1 where a line has none)."""
    path = Path(path)
    mats, codes, lines = [], [], []
    for lineno, line in enumerate(read_user_text(path).splitlines(), start=1):
        tok = line.split()
        if not tok:
            continue
        try:
            if len(tok) not in (16, 17):
                raise ValueError
            v = [float(t) for t in tok]
        except ValueError:
            raise InputError(f"{path}: line {lineno}: expected 16 matrix numbers and an algorithm code") from None
        m = np.array(v[:16]).reshape(4, 4).T
        if not np.isfinite(m).all() or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-6:
            raise InputError(f"{path}: line {lineno}: not a finite homogeneous 4x4 matrix")
        if len(v) == 17 and not (v[16].is_integer() and abs(v[16]) < 2**31):
            raise InputError(f"{path}: line {lineno}: the algorithm code must be an integer, got {tok[16][:20]!r}")
        mats.append(m)
        codes.append(int(v[16]) if len(v) == 17 else -1)
        lines.append(lineno)
    if not mats:
        raise InputError(f"{path}: no frame")

    poses = _to_ours(check_rotations(path, np.stack(mats), lines))
    return (poses, np.array(codes)) if return_codes else poses


def write_frames(path: str | os.PathLike, poses, code=1) -> None:
    """Write (M, 4, 4) poses (loaded frame) as a ``.frames`` file, atomically; ``code``: one
    algorithm code for every line or one per line (slam6D: 0 initial, 1 ICP, 2 ICP inactive)."""
    mats = _to_3dtk(poses)
    if mats.ndim != 3 or mats.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (M, 4, 4), got {mats.shape}")
    codes = np.broadcast_to(np.asarray(code, dtype=np.int64), (len(mats),))
    lines = [" ".join(f"{x + 0.0:.12g}" for x in m.T.ravel()) + f" {c}\n" for m, c in zip(mats, codes)]

    def _write(f: IO[bytes]) -> None:
        f.write("".join(lines).encode("ascii"))

    atomic_write(path, _write)


def write_pose(path: str | os.PathLike, pose) -> None:
    """Write one (4, 4) pose (loaded frame: metres, y down) as a 3DTK ``.pose`` file (line 1:
    position in cm, line 2: θx θy θz in degrees with R = Rx·Ry·Rz), atomically."""
    from scipy.spatial.transform import Rotation

    m = _to_3dtk(np.asarray(pose, dtype=np.float64)[None])[0]
    angles = Rotation.from_matrix(m[:3, :3]).as_euler("XYZ", degrees=True)
    text = " ".join(f"{v + 0.0:.12g}" for v in m[:3, 3]) + "\n" + " ".join(f"{v + 0.0:.12g}" for v in angles) + "\n"
    atomic_write(path, lambda f: f.write(text.encode("ascii")))


def _poses(folder: Path, files: list[Path], path, suffix: str, what: str) -> np.ndarray:
    """Poses from ``path`` (read_poses_3d, loaded frame) or each scan's .pose / last .frames."""
    if path is not None:
        poses = read_poses_3d(path)
        if len(poses) != len(files):
            raise InputError(f"{path}: {len(poses)} {what} for {len(files)} scans (counts differ)")
        return poses
    if suffix == ".pose":
        return _to_ours(np.stack([read_pose(f.with_suffix(".pose")) for f in files]))
    return np.stack([read_frames(f.with_suffix(".frames"))[-1] for f in files])


def load_3dtk(folder: str | os.PathLike, gt_path=None, init_path=None, max_points: int | None = 20000,
              seed: int = 0, use_frames: bool = False, min_range: float = 0.48,
              max_range: float = 32.76) -> ScanSet:
    """Read every ``scanNNN.3d`` of ``folder`` (numeric order) into a ScanSet (metres, y down).

    Points outside [min_range, max_range] metres are dropped (3DTK's viewer defaults in
    config.ini: 48 cm is the robot itself, 3276.x cm marks no return); then at most
    ``max_points`` random points per scan (seeded; None keeps all, padding with invalid points).
    init = the .pose files (odometry), or with ``use_frames`` the last .frames matrices;
    gt = the last .frames matrices (slam6D's result) when every scan has one, else None.
    ``gt_path`` / ``init_path`` override them (read_poses_3d, in the loaded frame).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    files = _scan_files(folder)
    if len(files) < 2:
        raise InputError(f"{folder}: need at least two scanNNN.3d files, found {len(files)}")
    check_max_points(folder, max_points)
    rng = np.random.default_rng(seed)
    clouds = []
    for f in files:
        xyz = read_3d(f) * [0.01, -0.01, 0.01]
        r = np.linalg.norm(xyz, axis=1)
        xyz = xyz[(r >= min_range) & (r <= max_range)]
        if len(xyz) == 0:
            raise InputError(f"{f}: no point between {min_range} m and {max_range} m from the scanner")
        clouds.append(subsample(xyz, max_points, rng))
    points, valid = pad_clouds(clouds)
    has_frames = all(f.with_suffix(".frames").is_file() for f in files)
    gt = _poses(folder, files, gt_path, ".frames", "reference poses") if gt_path or has_frames else None
    init = _poses(folder, files, init_path, ".frames" if use_frames else ".pose", "initial poses")
    return ScanSet(points=points, valid=valid, gt_poses=gt, init_poses=init, unit_scale=100.0, unit="cm",
                   ordered=True, names=[f.stem for f in files], source=str(folder), grid_shape=None,
                   pose_dof=6, recorded_poses=init_path is None and not use_frames).validate()
