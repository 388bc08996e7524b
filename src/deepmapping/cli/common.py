"""Shared CLI helpers: settings from flags, one-line errors."""

from __future__ import annotations

import sys

import yaml

from deepmapping.errors import ConfigError


def parse_sets(items: list[str] | None) -> dict:
    """--set optim.epochs=100 --set mnet.hidden=[64,64] -> {"optim.epochs": 100, ...} (YAML values)."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            out[key.strip()] = yaml.safe_load(value)
        except (yaml.YAMLError, ValueError, RecursionError):  # e.g. --set mnet.hidden=[64
            raise ConfigError(f"--set {key.strip()}: cannot read the value {value[:40]!r} (YAML)") from None
    return out


def fail(message: str, code: int = 2) -> None:
    from deepmapping.cli.progress import console

    console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    sys.exit(code)
