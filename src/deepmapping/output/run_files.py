"""The files every run folder has, 2D or 3D: the effective settings and the training log."""

from __future__ import annotations

from pathlib import Path

from deepmapping.io.atomic import write_text


def write_config(out: Path, result_config) -> None:
    import yaml

    write_text(out / "config.yaml", yaml.safe_dump(result_config.model_dump(), sort_keys=False))


def write_history_csv(path: Path, history: dict) -> None:
    """One row per log; the rollbacks and the scans the review moved (events, not columns) are in run.json."""
    keys = [k for k in history if isinstance(history[k], list) and k not in ("rollbacks", "reviewed")]
    rows = [",".join(keys)]
    for vals in zip(*(history[k] for k in keys)):
        rows.append(",".join("" if v is None else repr(v) for v in vals))
    write_text(path, "\n".join(rows) + "\n")
