"""A sweep's unit of work: one call of a plain function, identified by a key."""

from __future__ import annotations

import importlib
import re
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import current_process, get_context

# A quick (smoke) run's cold-start curriculum: fewer steps and heading hypotheses a stage, small wide
# searches; the cold rows then take seconds, not half a minute each (not a measurement).
QUICK_CURRICULUM = {"curriculum.steps": 10, "curriculum.hypotheses": 8, "curriculum.wide_hypotheses": 256,
                    "curriculum.wide_refine": 2, "curriculum.small_wide_hypotheses": 256,
                    "curriculum.small_wide_refine": 2}


@dataclass(frozen=True)
class Job:
    """``func`` ("package.module:function") called with ``kwargs`` returns a JSON-able dict.

    ``key`` names the run (its result file is ``runs/<key>.json``): letters, digits, ``-_.=``.
    """

    key: str
    func: str
    kwargs: dict = field(default_factory=dict)

    def __post_init__(self):
        if not re.fullmatch(r"[A-Za-z0-9_.=-]+", self.key):
            raise ValueError(f"job key {self.key!r}: use letters, digits and -_.= only")


def call_job(func: str, kwargs: dict, threads: int = 1) -> dict:
    """Run one job in this process (the worker side of every executor)."""
    import os

    # OpenMP pools (Open3D's ICP, NumPy's BLAS) of a worker: as many threads as torch's, set
    # before they are first imported in this (spawned) process
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    import torch

    torch.set_num_threads(threads)
    module, name = func.split(":")
    return getattr(importlib.import_module(module), name)(**kwargs)


def in_fresh_process(func, *args):
    """``func(*args)`` in a fresh spawned process, so that its wall time and peak RSS are its own;
    in this process where it may have no children (a daemonic worker of a Dask cluster)."""
    if current_process().daemon:
        return func(*args)
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        return pool.submit(func, *args).result()
