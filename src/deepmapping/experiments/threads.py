"""``deepmapping experiment threads``: reproducibility across torch thread counts.

The default 2D command (profile ``default``: DeepMapping warm-started by point-to-plane ICP) on
the paper's trajectory 0 (128 poses), seeds 0-4, each with 1 and with 2 torch threads. A fixed
seed and thread count give bit-identical poses (tests/test_solver.py, tests/test_cli.py);
between thread counts float sums run in another order, so runs part and end in nearby minima.
Reported: the final ATE per seed and thread count, the difference between thread counts next
to the spread between seeds. Each run sets its own thread count (the sweep's ``--threads`` is
not used): measure with ``--jobs 1`` so that the 2-thread runs have two idle cores.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepmapping.api import register
from deepmapping.config import load_config
from deepmapping.experiments.base import Job
from deepmapping.experiments.report import markdown_table, write_report
from deepmapping.sim.dataset import paper_trajectory

FULL = {"trajectory": 0, "seeds": (0, 1, 2, 3, 4), "threads": (1, 2), "num_poses": None, "num_beams": 256,
        "epochs": None}
QUICK = {"trajectory": 0, "seeds": (0, 1), "threads": (1, 2), "num_poses": 16, "num_beams": 64, "epochs": 5}


def jobs(quick: bool) -> list[Job]:
    """One run per (seed, thread count): ``s<seed>-t<threads>``."""
    s = QUICK if quick else FULL
    kw = {k: s[k] for k in ("trajectory", "num_poses", "num_beams", "epochs")}
    return [Job(f"s{seed}-t{th}", "deepmapping.experiments.threads:run", kw | {"seed": seed, "threads": th})
            for seed in s["seeds"] for th in s["threads"]]


def run(trajectory: int, seed: int, threads: int, num_poses: int | None = None, num_beams: int = 256,
        epochs: int | None = None) -> dict:
    """The default profile on ``trajectory`` with ``seed`` and ``threads`` torch threads (the
    registration sets them from the config)."""
    scans = paper_trajectory(trajectory, num_poses=num_poses, num_beams=num_beams)
    overrides: dict = {"seed": seed, "threads": threads}
    if epochs is not None:
        overrides["optim.epochs"] = epochs
    result = register(scans, load_config("default", overrides=overrides))
    return {"trajectory": trajectory, "seed": seed, "threads": threads, "num_poses": scans.num_scans,
            "ate": float(result.metrics["ate"]), "runtime_s": float(result.runtime_s)}


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    """ATE by seed (columns) and thread count (rows), and the difference between thread counts."""
    s = QUICK if quick else FULL
    ate = {(r["seed"], r["threads"]): r["ate"] for r in results.values()}
    seeds = [seed for seed in s["seeds"] if any((seed, th) in ate for th in s["threads"])]
    rows = [[f"ATE, {th} thread{'s' if th > 1 else ''} (px)", *(ate.get((seed, th), float("nan")) for seed in seeds)]
            for th in s["threads"]]
    diffs = [abs(ate[seed, s["threads"][0]] - ate[seed, s["threads"][1]]) if all((seed, th) in ate for th in s["threads"])
             else float("nan") for seed in seeds]
    rows.append(["difference (px)", *diffs])
    known = [d for d in diffs if np.isfinite(d)]
    one = [ate[seed, s["threads"][0]] for seed in seeds if (seed, s["threads"][0]) in ate]
    size = "quick: a smoke run, not a measurement; " if quick else ""
    intro = (f"{size}trajectory {s['trajectory']} of the paper's data, profile `default`. Largest difference between "
             f"thread counts {max(known):.3g} px, median {float(np.median(known)):.3g} px; spread between seeds at "
             f"{s['threads'][0]} thread: {min(one):.3g}-{max(one):.3g} px." if known and one else size)
    table = markdown_table(["seed", *map(str, seeds)], rows)
    return write_report(out, "Reproducibility across thread counts", [intro, table])
