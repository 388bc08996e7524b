"""PCD (Point Cloud Library) files: write x y z binary/ascii, read x y z from ascii/binary.

Only the x, y, z fields are kept when reading; any other field (rgb, intensity, normals,
COUNT > 1 descriptors, padding ``_`` fields) is skipped using its SIZE/TYPE/COUNT.
``DATA binary_compressed`` is not supported (raises InputError). Binary data is
little-endian, as written by PCL and Open3D.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path
from typing import IO

import numpy as np

from deepmapping.errors import InputError
from deepmapping.io.atomic import atomic_write, read_user_file

__all__ = ["write_pcd", "read_pcd", "atomic_write"]

# (TYPE, SIZE) -> numpy little-endian scalar type
_PCD_TYPES: dict[tuple[str, int], str] = {
    ("F", 4): "<f4",
    ("F", 8): "<f8",
    ("U", 1): "u1",
    ("U", 2): "<u2",
    ("U", 4): "<u4",
    ("U", 8): "<u8",
    ("I", 1): "i1",
    ("I", 2): "<i2",
    ("I", 4): "<i4",
    ("I", 8): "<i8",
}
_HEADER_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_MAX_HEADER_LINES = 256


def _as_xyz(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise ValueError(f"points must be (N, 3) (or (N, 2), z = 0), got shape {pts.shape}")
    pts = pts.astype(np.float32, copy=False)
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.zeros((pts.shape[0], 1), np.float32)], axis=1)
    return np.ascontiguousarray(pts, dtype="<f4")


def write_pcd(path: str | os.PathLike, points: np.ndarray, binary: bool = True) -> None:
    """Write (N, 3) points (cast to float32) as a PCD v0.7 file with FIELDS x y z.

    ``binary=True`` (default) writes ``DATA binary``; ``binary=False`` writes ``DATA ascii``
    with 9 significant digits, which round-trips float32 exactly. An (N, 2) array is
    written with z = 0. The file is written atomically (temp file + os.replace).
    """
    pts = _as_xyz(points)
    n = pts.shape[0]
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        "FIELDS x y z\n"
        "SIZE 4 4 4\n"
        "TYPE F F F\n"
        "COUNT 1 1 1\n"
        f"WIDTH {n}\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {n}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    ).encode("ascii")

    def _write(f: IO[bytes]) -> None:
        f.write(header)
        if binary:
            f.write(pts.tobytes())
        else:
            lines = "".join(
                f"{float(x):.9g} {float(y):.9g} {float(z):.9g}\n" for x, y, z in pts.tolist()
            )
            f.write(lines.encode("ascii"))

    atomic_write(path, _write)


def _parse_header(path: Path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    """Return (header fields, byte offset of the data section)."""
    header: dict[str, list[str]] = {}
    pos = 0
    for lineno in range(1, _MAX_HEADER_LINES + 1):
        end = raw.find(b"\n", pos)
        if end < 0:
            if pos >= len(raw):
                break
            end = len(raw)
        line_b = raw[pos:end]
        pos = end + 1
        try:
            line = line_b.decode("ascii").strip()
        except UnicodeDecodeError:
            raise InputError(f"{path}: not a PCD file (non-text header at line {lineno})") from None
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        key = key.upper()
        if key not in _HEADER_KEYS:
            raise InputError(f"{path}: not a PCD file (unexpected header line {lineno}: {line[:40]!r})")
        header[key] = values
        if key == "DATA":
            return header, min(pos, len(raw))
    raise InputError(f"{path}: not a PCD file (no DATA line in the header)")


def _ints(path: Path, header: dict[str, list[str]], key: str) -> list[int]:
    try:
        return [int(v) for v in header[key]]
    except ValueError:
        raise InputError(f"{path}: invalid {key} line in the PCD header: {' '.join(header[key])!r}") from None


def read_pcd(path: str | os.PathLike) -> np.ndarray:
    """Read the x, y, z fields of a PCD file as an (N, 3) float32 array.

    Supports ``DATA ascii`` and ``DATA binary`` with any extra fields (skipped by their
    SIZE/TYPE/COUNT). A missing z field gives z = 0. Raises InputError
    (``"<path>: <problem>"``) for a missing/unreadable file, a malformed header,
    missing x or y fields, truncated data, or ``DATA binary_compressed``.
    """
    path = Path(path)
    raw = read_user_file(path)

    header, offset = _parse_header(path, raw)
    if "FIELDS" not in header or not header["FIELDS"]:
        raise InputError(f"{path}: PCD header has no FIELDS line")
    fields = header["FIELDS"]
    nf = len(fields)
    data_kind = (header["DATA"] or [""])[0].lower()

    counts = _ints(path, header, "COUNT") if "COUNT" in header else [1] * nf
    if "SIZE" in header:
        sizes = _ints(path, header, "SIZE")
    elif data_kind == "ascii":
        sizes = [4] * nf
    else:
        raise InputError(f"{path}: PCD header has no SIZE line")
    types = [t.upper() for t in header["TYPE"]] if "TYPE" in header else ["F"] * nf
    if not (len(sizes) == len(types) == len(counts) == nf):
        raise InputError(
            f"{path}: PCD header FIELDS/SIZE/TYPE/COUNT lengths differ "
            f"({nf}/{len(sizes)}/{len(types)}/{len(counts)})"
        )
    if any(c < 1 for c in counts):
        raise InputError(f"{path}: PCD header COUNT values must be >= 1")
    if "POINTS" in header:
        npts = _ints(path, header, "POINTS")
    elif "WIDTH" in header:
        width = _ints(path, header, "WIDTH")
        height = _ints(path, header, "HEIGHT") if "HEIGHT" in header else [1]
        if len(width) != 1 or len(height) != 1:
            raise InputError(f"{path}: invalid WIDTH/HEIGHT in the PCD header")
        npts = [width[0] * height[0]]
    else:
        raise InputError(f"{path}: PCD header has neither POINTS nor WIDTH")
    if len(npts) != 1 or npts[0] < 0:
        raise InputError(f"{path}: invalid POINTS in the PCD header")
    n = npts[0]

    lower = [f.lower() for f in fields]
    if "x" not in lower or "y" not in lower:
        raise InputError(f"{path}: PCD has no x/y fields (fields: {' '.join(fields)})")
    wanted = {axis: lower.index(axis) for axis in ("x", "y", "z") if axis in lower}

    if data_kind == "binary_compressed":
        raise InputError(f"{path}: PCD 'DATA binary_compressed' is not supported; save as binary or ascii")
    if data_kind == "binary":
        for i, (t, s) in enumerate(zip(types, sizes)):
            if (t, s) not in _PCD_TYPES:
                raise InputError(f"{path}: unsupported PCD field type {t}{s} for field {fields[i]!r}")
        point_size = sum(s * c for s, c in zip(sizes, counts))
        need = n * point_size
        avail = len(raw) - offset
        if avail < need:  # checked before anything is allocated: POINTS or COUNT may be huge
            raise InputError(
                f"{path}: truncated PCD data ({avail} bytes for {n} points of {point_size} bytes)"
            )
        if n == 0:
            return np.zeros((0, 3), dtype=np.float32)
        dt_fields = []
        for i, (t, s, c) in enumerate(zip(types, sizes, counts)):
            base = _PCD_TYPES[(t, s)]
            dt_fields.append((f"f{i}", base, (c,)) if c > 1 else (f"f{i}", base))
        dtype = np.dtype(dt_fields)  # packed, no alignment padding (as in PCD files)
        rec = np.frombuffer(raw, dtype=dtype, count=n, offset=offset)
        out = np.zeros((n, 3), dtype=np.float32)
        for j, axis in enumerate(("x", "y", "z")):
            if axis in wanted:
                col = rec[f"f{wanted[axis]}"]
                out[:, j] = col[:, 0] if col.ndim == 2 else col
        return out
    if data_kind == "ascii":
        ncols = sum(counts)
        starts = [0, *itertools.accumulate(counts)][:-1]  # Python ints: COUNT may be huge
        try:
            text = raw[offset:].decode("ascii")
        except UnicodeDecodeError:
            raise InputError(f"{path}: PCD ascii data contains non-text bytes") from None
        rows = [ln.split() for ln in text.splitlines() if ln.strip()]
        if len(rows) < n:
            raise InputError(f"{path}: truncated PCD data ({len(rows)} lines for {n} points)")
        rows = rows[:n]
        for i, r in enumerate(rows):
            if len(r) != ncols:
                raise InputError(
                    f"{path}: PCD ascii point {i} has {len(r)} values, expected {ncols}"
                )
        cols = [starts[wanted[a]] for a in ("x", "y", "z") if a in wanted]
        try:
            vals = np.array([[float(r[c]) for c in cols] for r in rows], dtype=np.float64).reshape(n, len(cols))
        except ValueError:
            raise InputError(f"{path}: PCD ascii data contains a non-numeric value") from None
        out = np.zeros((n, 3), dtype=np.float32)
        out[:, : len(cols)] = vals  # x, y always present; z is last when present
        return out
    raise InputError(f"{path}: unknown PCD DATA type {data_kind!r} (expected ascii or binary)")
