"""2D pose files: text ``x y theta`` per line, MATLAB ``gt_pose.mat`` (key ``pose``), .npy.

Every reader returns a (K, 3) float64 array ``[x, y, theta]`` and raises InputError
(``"<path>: <problem>"``) on a missing, corrupt or malformed file. Writers are atomic.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import IO

import numpy as np

from deepmapping.errors import InputError
from deepmapping.io.pcd import atomic_write

__all__ = [
    "read_pose_text",
    "write_pose_text",
    "read_gt_mat",
    "write_gt_mat",
    "read_poses_npy",
    "write_poses_npy",
    "read_poses",
]


def _check_file(path: Path) -> None:
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if not path.is_file():
        raise InputError(f"{path}: not a file")


def _as_poses(poses: np.ndarray) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"poses must be (K, 3) [x, y, theta], got shape {arr.shape}")
    return arr


def read_pose_text(path: str | os.PathLike) -> np.ndarray:
    """Read a text file with one ``x y theta`` pose per line (whitespace or comma separated).

    ``#`` starts a comment (whole line or trailing); blank lines are ignored. A line with
    a column count other than 3, a non-numeric or non-finite value raises InputError
    naming the line number. An empty file (no pose) also raises InputError.
    """
    path = Path(path)
    _check_file(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read pose text file ({e})") from None
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].replace(",", " ").strip()
        if not line:
            continue
        tok = line.split()
        if len(tok) != 3:
            raise InputError(f"{path}: line {lineno}: expected 3 columns (x y theta), got {len(tok)}")
        try:
            vals = [float(t) for t in tok]
        except ValueError:
            raise InputError(f"{path}: line {lineno}: non-numeric value in {line!r}") from None
        if not np.isfinite(vals).all():
            raise InputError(f"{path}: line {lineno}: NaN or inf value")
        rows.append(vals)
    if not rows:
        raise InputError(f"{path}: no pose found (expected lines of 'x y theta')")
    return np.array(rows, dtype=np.float64)


def write_pose_text(path: str | os.PathLike, poses: np.ndarray, header: str = "x y theta") -> None:
    """Write (K, 3) poses, one ``x y theta`` line each at full precision (%.17g), atomically.

    ``header`` is written as a leading ``#`` comment line (may hold several lines).
    """
    arr = _as_poses(poses)
    head = "".join(f"# {h}\n" for h in header.splitlines()) if header else ""
    body = "".join(f"{x:.17g} {y:.17g} {t:.17g}\n" for x, y, t in arr.tolist())
    data = (head + body).encode("utf-8")
    atomic_write(path, lambda f: f.write(data))


def read_gt_mat(path: str | os.PathLike, key: str = "pose") -> np.ndarray:
    """Read the (K, 3) pose matrix stored under ``key`` (default ``pose``) in a MATLAB file.

    This is the authors' ``gt_pose.mat`` (rows ``[x_px, y_px, theta_rad]``); no unit
    conversion is applied here. MATLAB v7.3 (HDF5) files are not supported.
    """
    path = Path(path)
    _check_file(path)
    from scipy.io import loadmat

    try:
        mat = loadmat(str(path))
    except NotImplementedError:
        raise InputError(f"{path}: MATLAB v7.3 (HDF5) files are not supported; re-save with -v7") from None
    except Exception as e:  # scipy raises ValueError, MatReadError, TypeError, OSError ...
        raise InputError(f"{path}: cannot read MATLAB file ({type(e).__name__}: {e})".splitlines()[0]) from None
    if key not in mat:
        keys = ", ".join(k for k in mat if not k.startswith("__")) or "none"
        raise InputError(f"{path}: no variable {key!r} in the MATLAB file (variables: {keys})")
    try:
        arr = np.asarray(mat[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{path}: variable {key!r} is not a numeric matrix") from None
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise InputError(f"{path}: variable {key!r} must be K x 3 [x y theta], got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{path}: variable {key!r} contains NaN or inf")
    return arr


def write_gt_mat(path: str | os.PathLike, poses: np.ndarray, key: str = "pose") -> None:
    """Write (K, 3) float64 poses to a MATLAB v5 file under ``key`` (default ``pose``), atomically."""
    arr = _as_poses(poses)
    from scipy.io import savemat

    buf = io.BytesIO()
    savemat(buf, {key: arr})
    data = buf.getvalue()
    atomic_write(path, lambda f: f.write(data))


def read_poses_npy(path: str | os.PathLike) -> np.ndarray:
    """Read a (K, 3) pose array from a .npy file (no pickles)."""
    path = Path(path)
    _check_file(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:
        raise InputError(f"{path}: cannot read .npy file ({type(e).__name__}: {e})".splitlines()[0]) from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise InputError(f"{path}: poses must be a K x 3 [x y theta] array, got shape {getattr(arr, 'shape', None)}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{path}: poses must be numeric, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise InputError(f"{path}: poses contain NaN or inf")
    return arr


def write_poses_npy(path: str | os.PathLike, poses: np.ndarray) -> None:
    """Save (K, 3) float64 poses as .npy, atomically (the path is used as given, no suffix added)."""
    arr = _as_poses(poses)

    def _write(f: IO[bytes]) -> None:
        np.save(f, arr, allow_pickle=False)

    atomic_write(path, _write)


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """Read (K, 3) poses choosing the reader by suffix: .mat, .npy, anything else = text."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mat":
        return read_gt_mat(path)
    if suffix == ".npy":
        return read_poses_npy(path)
    return read_pose_text(path)
