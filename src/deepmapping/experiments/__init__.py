"""Experiments of the paper, one command each (``deepmapping experiment NAME --out DIR``).

Each experiment module defines

* ``jobs(quick: bool) -> list[Job]``: the independent runs (a sweep), each a call of a plain
  function of this package that returns a JSON-able dict;
* ``report(out: Path, results: dict[str, dict], quick: bool) -> Path``: tables and pictures
  from the runs' results, written into ``out`` with ``report.md`` embedding them.

An experiment on real recordings also defines ``DATA``, the name of its folder under
``../shared/data`` (where the command is run), and takes ``jobs(quick, data)``: the folder
given with ``--data``, or that default (:func:`data_folder`).

:mod:`deepmapping.experiments.sweep` runs the jobs (a local process pool, or a Dask cluster),
keeps each finished run's result in ``out/runs/<key>.json`` and never redoes it.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from deepmapping.errors import ConfigError

SHARED_DATA = Path("..") / "shared" / "data"  # real recordings beside a clone of the repository

EXPERIMENTS = {  # NAME -> module under deepmapping.experiments
    "2d": "exp_2d",
    "avd": "exp_avd",
    "relocalization": "relocalization",
    "warm-start": "warm_start",
    "ablations": "ablations",
    "1d": "one_d",
    "robustness": "robustness",
    "carmen": "carmen",
    "real-3d": "real_3d",
    "threads": "threads",
    "speed": "speed",
}


def experiment_module(name: str):
    """The module of experiment ``name`` (a ConfigError naming the choices when unknown)."""
    if name not in EXPERIMENTS:
        raise ConfigError(f"unknown experiment '{name}' (choose from {', '.join(EXPERIMENTS)})")
    return importlib.import_module(f"deepmapping.experiments.{EXPERIMENTS[name]}")


def data_folder(name: str, module, data: str | Path | None) -> Path | None:
    """The data folder experiment ``name`` reads: ``data``, or ``../shared/data/<DATA>``;
    None for an experiment that reads none (a ConfigError when one is given to it anyway, or
    when the folder is missing)."""
    default = getattr(module, "DATA", None)
    if default is None:
        if data is not None:
            raise ConfigError(f"experiment '{name}' reads no data folder (it simulates its data); drop --data")
        return None
    folder = Path(data) if data is not None else SHARED_DATA / default
    if not folder.is_dir():
        hint = "" if data is not None else " (give the folder with --data)"
        raise ConfigError(f"{folder}: folder not found{hint}")
    return folder.resolve()
