"""Trivial jobs to check that a sweep's executor works (used by the tests; handy to check a cluster)."""

from __future__ import annotations

import os
import socket
from pathlib import Path


def echo(value: float, fail_times: int = 0, marker: str | None = None) -> dict:
    """Return ``value`` squared and where it ran. With ``marker``: raise on the first
    ``fail_times`` calls (counted in the marker file), to exercise retries."""
    if fail_times:
        path = Path(marker)
        calls = int(path.read_text()) if path.exists() else 0
        path.write_text(str(calls + 1))
        if calls < fail_times:
            raise RuntimeError(f"planned failure {calls + 1} of {fail_times}")
    return {"value": value, "square": value * value, "host": socket.gethostname(), "pid": os.getpid()}
