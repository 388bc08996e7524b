"""PLY files: write binary little-endian vertices (+ optional colours); read vertex x y z.

Reading supports ``ascii``, ``binary_little_endian`` and ``binary_big_endian``; other vertex
properties are skipped by type, other elements (faces, ...) are skipped and ignored.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO

import numpy as np

from deepmapping.errors import InputError
from deepmapping.io.atomic import atomic_write, read_user_file

__all__ = ["write_ply", "read_ply"]

_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write (N, 3) points (float32; (N, 2) gets z = 0) and optional (N, 3) uint8 colours.

    Format: binary_little_endian 1.0, element vertex with float x y z [uchar red green blue].
    Written atomically (temp file + os.replace).
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise ValueError(f"points must be (N, 3) (or (N, 2)), got shape {pts.shape}")
    n = pts.shape[0]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        col = np.asarray(colors)
        if col.shape != (n, 3):
            raise ValueError(f"colors must be (N, 3) uint8 with N = {n}, got shape {col.shape}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.zeros(n, dtype=np.dtype(fields))
    rec["x"] = pts[:, 0]
    rec["y"] = pts[:, 1]
    if pts.shape[1] == 3:
        rec["z"] = pts[:, 2]
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = (np.asarray(colors, dtype=np.uint8)[:, i] for i in range(3))
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {name}\n" for name, t in fields)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by deepmapping\n"
        f"element vertex {n}\n{props}end_header\n"
    ).encode("ascii")

    def _write(f: IO[bytes]) -> None:
        f.write(header)
        f.write(rec.tobytes())

    atomic_write(path, _write)


class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name = name
        self.count = count
        # (name, type) for scalars, (name, (count_type, item_type)) for lists
        self.props: list[tuple[str, str | tuple[str, str]]] = []

    @property
    def has_list(self) -> bool:
        return any(isinstance(t, tuple) for _, t in self.props)


def _parse_header(path: Path, raw: bytes) -> tuple[str, list[_Element], int]:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    nl = raw.find(b"\n", end)
    offset = len(raw) if nl < 0 else nl + 1
    try:
        lines = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError(f"{path}: PLY header is not ascii text") from None
    fmt = ""
    elements: list[_Element] = []
    for lineno, line in enumerate(lines[1:], start=2):
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        try:
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                if int(tok[2]) < 0:
                    raise ValueError
                elements.append(_Element(tok[1], int(tok[2])))
            elif tok[0] == "property":
                if not elements:
                    raise ValueError
                if tok[1] == "list":
                    ct, it = _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]
                    elements[-1].props.append((tok[4], (ct, it)))
                else:
                    elements[-1].props.append((tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError):
            raise InputError(f"{path}: invalid PLY header line {lineno}: {line[:40]!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements, offset


def _binary_element(path: Path, raw: bytes, offset: int, el: _Element, endian: str) -> tuple[np.ndarray | None, int]:
    """Parse one binary element; return (structured array of its scalar props or None, new offset)."""
    if not el.has_list:
        dtype = np.dtype([(f"p{i}", endian + t) for i, (_, t) in enumerate(el.props)])
        if dtype.itemsize == 0:  # an element without properties takes no bytes
            return None, offset
        need = el.count * dtype.itemsize
        if len(raw) - offset < need:
            raise InputError(f"{path}: truncated PLY data in element {el.name!r}")
        return np.frombuffer(raw, dtype=dtype, count=el.count, offset=offset), offset + need
    # elements with list properties: walk record by record (faces; rarely vertices); a record
    # takes at least one byte, so a count larger than the bytes left is a truncated file
    if el.count > len(raw) - offset:
        raise InputError(f"{path}: truncated PLY data in element {el.name!r}")
    scal = [(f"p{i}", endian + t) for i, (_, t) in enumerate(el.props) if not isinstance(t, tuple)]
    out = np.zeros(el.count, dtype=np.dtype(scal)) if scal else None
    try:
        for k in range(el.count):
            for i, (_, t) in enumerate(el.props):
                if isinstance(t, tuple):
                    ct, it = np.dtype(endian + t[0]), np.dtype(endian + t[1])
                    m = int(np.frombuffer(raw, ct, 1, offset)[0])
                    if m < 0:
                        raise InputError(f"{path}: negative list length in PLY element {el.name!r} record {k}")
                    offset += ct.itemsize + m * it.itemsize
                else:
                    dt = np.dtype(endian + t)
                    v = np.frombuffer(raw, dt, 1, offset)[0]
                    if out is not None:
                        out[f"p{i}"][k] = v
                    offset += dt.itemsize
    except ValueError:
        raise InputError(f"{path}: truncated PLY data in element {el.name!r}") from None
    if offset > len(raw):
        raise InputError(f"{path}: truncated PLY data in element {el.name!r}")
    return out, offset


def read_ply(path: str | os.PathLike) -> np.ndarray:
    """Read the vertex x, y, z of a PLY file as an (N, 3) float32 array (missing z -> 0).

    Raises InputError (``"<path>: <problem>"``) for a missing/unreadable file, a bad
    header, no vertex element or no x/y properties, truncated or non-numeric data.
    """
    path = Path(path)
    raw = read_user_file(path)
    fmt, elements, offset = _parse_header(path, raw)
    vidx = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vidx is None:
        raise InputError(f"{path}: PLY has no vertex element")
    vert = elements[vidx]
    names = [name for name, _ in vert.props]
    if "x" not in names or "y" not in names:
        raise InputError(f"{path}: PLY vertex has no x/y properties")
    if any(isinstance(t, tuple) for name, t in vert.props if name in ("x", "y", "z")):
        raise InputError(f"{path}: PLY vertex x/y/z must be scalar properties")
    axes = [names.index(a) for a in ("x", "y", "z") if a in names]

    if fmt == "ascii":
        try:
            text = raw[offset:].decode("ascii")
        except UnicodeDecodeError:
            raise InputError(f"{path}: PLY ascii data contains non-text bytes") from None
        lines = [ln for ln in text.splitlines() if ln.strip()]
        start = sum(e.count for e in elements[:vidx])
        rows = lines[start : start + vert.count]
        if len(rows) < vert.count:
            raise InputError(f"{path}: truncated PLY data ({len(rows)} vertex lines for {vert.count})")
        out = np.zeros((vert.count, 3), dtype=np.float32)
        # token index of each scalar prop (vertex list props shift later tokens per row)
        try:
            for k, ln in enumerate(rows):
                tok = ln.split()
                pos, where = 0, {}
                for i, (_, t) in enumerate(vert.props):
                    if isinstance(t, tuple):
                        m = int(tok[pos])
                        if m < 0:
                            raise ValueError
                        pos += 1 + m
                    else:
                        where[i] = pos
                        pos += 1
                if pos > len(tok):
                    raise IndexError
                for j, i in enumerate(axes):
                    out[k, j] = float(tok[where[i]])
        except (IndexError, ValueError):
            raise InputError(f"{path}: invalid PLY ascii vertex line {k}") from None
        return out

    endian = "<" if fmt == "binary_little_endian" else ">"
    for el in elements[:vidx]:
        _, offset = _binary_element(path, raw, offset, el, endian)
    rec, _ = _binary_element(path, raw, offset, vert, endian)
    assert rec is not None
    out = np.zeros((vert.count, 3), dtype=np.float32)
    for j, i in enumerate(axes):
        out[:, j] = rec[f"p{i}"]
    return out
