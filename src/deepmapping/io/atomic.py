"""Atomic file writes (a reader never sees a half-written file) and reading users' input files."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import IO, Callable

from deepmapping.errors import InputError, OutputError


def _file_mode() -> int:
    """The mode a plain open() would give a new file (0o666 less the umask); mkstemp's is 0o600."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


FILE_MODE = _file_mode()


def atomic_write(path: str | os.PathLike, writer: Callable[[IO[bytes]], None]) -> None:
    """Write a file atomically: ``writer(f)`` fills a temp file in the same folder, then os.replace.

    A reader never sees a half-written file; on error the temp file is removed and the
    previous content of ``path`` (if any) is left untouched. A failed write (disk full,
    read-only folder, no permission) raises ``OutputError`` naming ``path``: the CLI prints
    it as one line.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    except OSError as e:
        raise cannot_write(path, e) from None
    try:
        with os.fdopen(fd, "wb") as f:
            writer(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError):
            raise cannot_write(path, e) from None
        raise


def cannot_write(path, e: OSError) -> OSError:
    """``OutputError("<path>: cannot write (<reason>)")`` for an OSError raised while writing ``path``."""
    if isinstance(e, OutputError):
        return e
    return OutputError(f"{path}: cannot write ({e.strerror or e})")


def make_folder(path) -> Path:
    """``mkdir -p path``; OutputError naming it when it cannot be created (read-only, a file there)."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"{path}: exists and is not a folder") from None
    except OSError as e:
        raise OutputError(f"{path}: cannot create the folder ({e.strerror or e})") from None
    return path


def read_user_file(path) -> bytes:
    """The bytes of a user's input file; InputError naming the file when it cannot be read."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if not path.is_file():
        raise InputError(f"{path}: not a file")
    try:
        return path.read_bytes()
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror or e})") from None


def read_user_text(path) -> str:
    """A user's text file as str (UTF-8); InputError naming the file when it cannot be read."""
    try:
        return read_user_file(path).decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a UTF-8 text file") from None


def write_text(path, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def _jsonable(x):
    import numpy as np

    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(type(x))


def write_json(path, data) -> None:
    """``data`` as indented JSON (NumPy scalars and arrays allowed), atomically."""
    write_text(path, json.dumps(data, indent=2, default=_jsonable) + "\n")
