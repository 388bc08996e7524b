"""One deepmapping command at a time per output folder.

``register`` and ``experiment`` hold an advisory lock (``flock``) on ``<folder>/.deepmapping.lock``
while they write there; a second command on the same folder refuses at once (``FolderBusy``)
instead of interleaving its files with the first one's. The kernel drops the lock when its
process ends, however it ends (``kill -9`` included), so a crashed run never leaves a stale
lock; the small hidden file itself stays (it records the holder's pid, for the message).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path

from deepmapping.errors import FolderBusy
from deepmapping.io.atomic import cannot_write

try:
    import fcntl
except ImportError:  # Windows: no flock; runs are not locked there
    fcntl = None

LOCK_NAME = ".deepmapping.lock"
_held: dict[str, list] = {}  # folders this process holds: real path -> [depth, open lock file]


@contextmanager
def folder_lock(folder):
    """Hold ``folder``'s lock for the ``with`` block; re-entrant within one process (an
    experiment's sweep holds the lock its runner took)."""
    key = os.path.realpath(folder)
    if key in _held:
        _held[key][0] += 1
    else:
        _held[key] = [1, _acquire(Path(folder))]
    try:
        yield
    finally:
        entry = _held[key]
        entry[0] -= 1
        if entry[0] == 0:
            del _held[key]
            if entry[1] is not None:
                entry[1].close()  # closing the file releases the lock


def _acquire(folder: Path):
    """The open lock file, locked; FolderBusy naming the holder's pid when another process has it."""
    if fcntl is None:
        return None
    path = folder / LOCK_NAME
    try:
        f = open(path, "a+")
    except OSError as e:
        raise cannot_write(path, e) from None
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        pid = f.read().strip() or "?"
        f.close()
        raise FolderBusy(f"{folder}: another deepmapping command is using this folder (pid {pid}); "
                         f"wait for it to finish or choose another --out") from None
    except OSError:  # a file system without flock (some network mounts): go on unlocked
        return f
    try:
        f.seek(0)
        f.truncate()
        f.write(f"{os.getpid()}\n")
        f.flush()
    except OSError as e:
        f.close()
        raise cannot_write(path, e) from None
    return f
