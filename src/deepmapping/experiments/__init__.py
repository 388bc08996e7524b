"""Experiments of the paper, one command each (``deepmapping experiment NAME --out DIR``).

Each experiment module defines

* ``jobs(quick: bool) -> list[Job]``: the independent runs (a sweep), each a call of a plain
  function of this package that returns a JSON-able dict;
* ``report(out: Path, results: dict[str, dict], quick: bool) -> Path``: tables and pictures
  from the runs' results, written into ``out`` with ``report.md`` embedding them.

:mod:`deepmapping.experiments.sweep` runs the jobs (a local process pool, or a Dask cluster),
keeps each finished run's result in ``out/runs/<key>.json`` and never redoes it.
"""

from __future__ import annotations

import importlib

from deepmapping.errors import ConfigError

EXPERIMENTS = {  # NAME -> module under deepmapping.experiments
    "2d": "exp_2d",
    "avd": "exp_avd",
    "relocalization": "relocalization",
    "warm-start": "warm_start",
    "ablations": "ablations",
    "1d": "one_d",
    "robustness": "robustness",
}


def experiment_module(name: str):
    """The module of experiment ``name`` (a ConfigError naming the choices when unknown)."""
    if name not in EXPERIMENTS:
        raise ConfigError(f"unknown experiment '{name}' (choose from {', '.join(EXPERIMENTS)})")
    return importlib.import_module(f"deepmapping.experiments.{EXPERIMENTS[name]}")
