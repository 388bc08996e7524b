"""3D pose files: KITTI text (3x4 row-major per line), TUM text, and .npy (K, 4, 4).

Every reader returns (K, 4, 4) float64 sensor-to-world matrices and raises InputError
(``"<path>: <problem>"``, one line) on a missing or malformed file: wrong column count on
a line, non-numeric, NaN/inf values, or a rotation block that is not a rotation
(|det - 1| or |R^T R - I| above ``ROT_TOL``). Writers are atomic.

- KITTI: ``r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz`` per line.
- TUM: ``timestamp tx ty tz qx qy qz qw``; writers use the frame index as timestamp.
Lines starting with ``#`` and blank lines are ignored in both.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO

import numpy as np

from deepmapping.errors import InputError
from deepmapping.geometry import se3
from deepmapping.io.atomic import atomic_write, read_user_file, read_user_text

__all__ = [
    "read_kitti_poses", "write_kitti_poses", "read_tum_poses", "read_tum_trajectory", "write_tum_poses",
    "read_poses_npy_3d", "write_poses_npy_3d", "read_poses_3d", "write_poses_3d",
]

ROT_TOL = 1e-3


def _rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of the non-comment, non-blank lines of a text file."""
    text = read_user_text(path)
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append((lineno, line.replace(",", " ").split()))
    if not rows:
        raise InputError(f"{path}: no pose found")
    return rows


def _numbers(path: Path, rows: list[tuple[int, list[str]]], ncols: int, what: str) -> np.ndarray:
    out = np.empty((len(rows), ncols))
    for i, (lineno, tok) in enumerate(rows):
        if len(tok) != ncols:
            raise InputError(f"{path}: line {lineno}: expected {ncols} columns ({what}), got {len(tok)}")
        try:
            out[i] = [float(t) for t in tok]
        except ValueError:
            raise InputError(f"{path}: line {lineno}: non-numeric value") from None
        if not np.isfinite(out[i]).all():
            raise InputError(f"{path}: line {lineno}: NaN or inf value")
    return out


def check_rotations(path: Path, poses: np.ndarray, lines: list[int] | None = None) -> np.ndarray:
    """``poses`` (K, 4, 4), or InputError naming ``path`` and the line (or pose) whose rotation block is not one."""
    rot = poses[:, :3, :3]
    det = np.linalg.det(rot)
    orth = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((np.abs(det - 1.0) > ROT_TOL) | (orth > ROT_TOL))
    if bad.size:
        i = int(bad[0])
        where = f"line {lines[i]}" if lines else f"pose {i}"
        raise InputError(f"{path}: {where}: not a rotation matrix (det {det[i]:.4g})")
    return poses


def read_kitti_poses(path: str | os.PathLike) -> np.ndarray:
    """KITTI odometry text (12 numbers per line, 3x4 row-major) -> (K, 4, 4)."""
    path = Path(path)
    rows = _rows(path)
    vals = _numbers(path, rows, 12, "KITTI 3x4 row-major")
    poses = se3.identity((len(rows),))
    poses[:, :3, :] = vals.reshape(-1, 3, 4)
    return check_rotations(path, poses, [r[0] for r in rows])


def read_tum_poses(path: str | os.PathLike) -> np.ndarray:
    """TUM text (``timestamp x y z qx qy qz qw``) -> (K, 4, 4); quaternions are normalized."""
    return read_tum_trajectory(path)[1]


def read_tum_trajectory(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """TUM text -> (timestamps (K,) float64, poses (K, 4, 4)), for matching poses to frames by time."""
    path = Path(path)
    rows = _rows(path)
    vals = _numbers(path, rows, 8, "TUM timestamp x y z qx qy qz qw")
    norms = np.linalg.norm(vals[:, 4:], axis=1)
    if (norms < 1e-6).any():
        raise InputError(f"{path}: line {rows[int(np.argmax(norms < 1e-6))][0]}: zero quaternion")
    return vals[:, 0].copy(), se3.from_xyz_quat(vals[:, 1:])


def read_poses_npy_3d(path: str | os.PathLike) -> np.ndarray:
    """(K, 4, 4) or (K, 3, 4) numeric .npy (no pickles) -> (K, 4, 4)."""
    path = Path(path)
    read_user_file(path)  # existence / readability, with the usual messages
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:
        raise InputError(f"{path}: cannot read .npy file ({type(e).__name__}: {e})".splitlines()[0]) from None
    shape = getattr(arr, "shape", None)
    if not isinstance(arr, np.ndarray) or arr.ndim != 3 or arr.shape[1:] not in ((4, 4), (3, 4)) or not len(arr):
        raise InputError(f"{path}: poses must be a K x 4 x 4 array, got shape {shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{path}: poses must be numeric, got dtype {arr.dtype}")
    if not np.isfinite(arr).all():
        raise InputError(f"{path}: poses contain NaN or inf")
    poses = se3.identity((len(arr),))
    poses[:, :3, :] = arr[:, :3, :]
    if arr.shape[1] == 4 and np.abs(arr[:, 3, :] - [0, 0, 0, 1]).max() > ROT_TOL:
        raise InputError(f"{path}: last row of every pose must be [0 0 0 1]")
    return check_rotations(path, poses)


def _sniff_columns(path: Path) -> int:
    return len(_rows(path)[0][1])


def read_poses_3d(path: str | os.PathLike) -> np.ndarray:
    """Read (K, 4, 4) poses: .npy; .tum = TUM; other text: 12 columns = KITTI, 8 = TUM."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        return read_poses_npy_3d(path)
    if suffix == ".tum":
        return read_tum_poses(path)
    ncols = _sniff_columns(path)
    if ncols == 8:
        return read_tum_poses(path)
    if ncols == 12:
        return read_kitti_poses(path)
    raise InputError(f"{path}: expected 12 columns (KITTI 3x4) or 8 (TUM t x y z qx qy qz qw), got {ncols}")


def _as_poses(poses) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (K, 4, 4), got shape {arr.shape}")
    return arr


def _write_text(path, lines: list[str]) -> None:
    data = "".join(line + "\n" for line in lines).encode("utf-8")
    atomic_write(path, lambda f: f.write(data))


def write_kitti_poses(path: str | os.PathLike, poses) -> None:
    """Write (K, 4, 4) poses as KITTI text (12 numbers per line, %.17g), atomically."""
    arr = _as_poses(poses)
    _write_text(path, [" ".join(f"{v:.17g}" for v in p[:3].ravel()) for p in arr])


def write_tum_poses(path: str | os.PathLike, poses, timestamps=None) -> None:
    """Write (K, 4, 4) poses as TUM text, full precision; timestamps default to the frame index
    (strings are written as given, e.g. a log's timestamps, so they match exactly)."""
    arr = _as_poses(poses)
    ts = list(range(len(arr))) if timestamps is None else list(timestamps)
    if len(ts) != len(arr):
        raise ValueError(f"{len(ts)} timestamps for {len(arr)} poses")
    q = se3.to_xyz_quat(arr)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [" ".join([t if isinstance(t, str) else f"{t:.17g}"] + [f"{v:.17g}" for v in row])
              for t, row in zip(ts, q)]
    _write_text(path, lines)


def write_poses_npy_3d(path: str | os.PathLike, poses) -> None:
    """Save (K, 4, 4) float64 poses as .npy, atomically (path used as given)."""
    arr = _as_poses(poses)

    def _write(f: IO[bytes]) -> None:
        np.save(f, arr, allow_pickle=False)

    atomic_write(path, _write)


def write_poses_3d(path: str | os.PathLike, poses, fmt: str | None = None) -> None:
    """Write (K, 4, 4) poses; ``fmt`` "kitti" | "tum" | "npy", default by suffix (.npy, .tum, else KITTI)."""
    fmt = fmt or {".npy": "npy", ".tum": "tum"}.get(Path(path).suffix.lower(), "kitti")
    writers = {"kitti": write_kitti_poses, "tum": write_tum_poses, "npy": write_poses_npy_3d}
    if fmt not in writers:
        raise ValueError(f"unknown pose format {fmt!r} (kitti, tum, npy)")
    writers[fmt](path, poses)
