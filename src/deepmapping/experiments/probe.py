"""Trivial jobs to check that a sweep's executor works (used by the tests; handy to check a cluster)."""

from __future__ import annotations

import os
import socket
from pathlib import Path


def echo(value: float, fail_times: int = 0, marker: str | None = None, die_times: int = 0) -> dict:
    """Return ``value`` squared and where it ran. With ``marker``: raise on the first
    ``fail_times`` calls (counted in the marker file), to exercise retries; or, with
    ``die_times``, kill the process itself (SIGKILL, as the out-of-memory killer does) on the
    first ``die_times`` calls, to exercise a sweep's worker dying mid-run."""
    if die_times:
        path = Path(marker)
        calls = int(path.read_text()) if path.exists() else 0
        path.write_text(str(calls + 1))
        if calls < die_times:
            import signal

            os.kill(os.getpid(), signal.SIGKILL)
    if fail_times:
        path = Path(marker)
        calls = int(path.read_text()) if path.exists() else 0
        path.write_text(str(calls + 1))
        if calls < fail_times:
            raise RuntimeError(f"planned failure {calls + 1} of {fail_times}")
    return {"value": value, "square": value * value, "host": socket.gethostname(), "pid": os.getpid()}
