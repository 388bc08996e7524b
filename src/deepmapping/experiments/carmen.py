"""``deepmapping experiment carmen``: the Freiburg SLAM benchmark logs, scored on their relations.

For each log of the data folder (``--data``, default ``../shared/data/carmen``: ``<log>.clf.bz2``,
``.clf.gz`` or ``.clf``, ``<log>.relations``, ``corrected/``) the keyframes (``motion:0.5,15``)
are registered by each method, every scan of the log is placed from its nearest keyframe
(odometry, then ICP to the keyframes around it), and all relations of Kümmerle et al. 2009 are
scored: translational (m) and rotational (deg) errors, mean ± std and median, split at 10 s.
A log without the benchmark's relations file but with a corrected log (mit-csail) is scored on
relations derived from it (``evaluation.relations.derive_relations``: 3 000 random pairs of scans
at most 1 m apart, 40 % of them more than 10 s apart, seed 0); intel and fr079 are scored on
derived relations too (column "derived"), which shows how the two measures compare.

Methods: ``odometry`` (the log's poses), ``icp`` (incremental point-to-point ICP, each pair
started from odometry), ``dm-odometry`` / ``dm-icp`` (DeepMapping, default profile, warm-started
from odometry / from that ICP), ``loop-closure`` (incremental ICP with loop closures and
pose-graph optimization), ``dm-loop-closure`` (DeepMapping warm-started from it), and
``reference``: the corrected trajectory shipped with the benchmark
(``corrected/<name>-corrected.log.gz``), matched to the raw scans by their ranges; the other
rows are also scored on the relations the reference covers (both scans in the corrected log).
Each run is done in a fresh process of its own, so its wall time and peak RSS are its own.

Sites with a corrected log but no raw log (belgioioso, edmonton, fhw, freiburg-101: ``SIMULATED``)
are logs nobody tuned on: ``<site>-sim`` is the corrected log's scans with simulated wheel odometry
(``sim.odometry.simulated_log``, seed 0, written to a temporary folder by each run), scored on
relations derived from the corrected poses; methods ``odometry``, ``loop-closure`` and the default
(``dm-loop-closure``).
"""

from __future__ import annotations

import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from deepmapping.api import evaluate_relations, register
from deepmapping.config import load_config
from deepmapping.errors import ConfigError
from deepmapping.evaluation.relations import Relations, derive_relations, read_relations, score_relations
from deepmapping.experiments.base import Job, in_fresh_process
from deepmapping.experiments.report import write_report
from deepmapping.io.loaders import load_scans
from deepmapping.io.relations import corrected_trajectory
from deepmapping.methods.keyframes import place_all_scans
from deepmapping.sim.odometry import simulated_log

DATA = "carmen"  # the folder under ../shared/data
LOGS = ("intel", "fr079", "mit-csail")  # the logs with relations or a corrected log (derived relations)
CORRECTED = {"intel": "intel-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz",
             "mit-csail": "csail-corrected.log.gz"}
SIMULATED = {"belgioioso": "belgioioso-corrected.log.gz", "edmonton": "edmonton-corrected.log.gz",
             "fhw": "fhw-corrected.log.gz", "freiburg-101": "freiburg-101-corrected.log.gz"}
SIM_SUFFIX = "-sim"  # <site>-sim: a SIMULATED site's scans with simulated odometry
SIM_METHODS = ("odometry", "loop-closure", "dm-loop-closure")
METHODS = {  # name -> (method, warm start); "reference" is the corrected log
    "odometry": (None, "file"),
    "icp": ("icp-point", "file"),
    "dm-odometry": ("deepmapping", "file"),
    "dm-icp": ("deepmapping", "icp-point"),
    "loop-closure": ("loop-closure", "file"),
    "dm-loop-closure": ("deepmapping", "loop-closure"),
}
FULL = {"keyframes": "motion:0.5,15", "epochs": None}
QUICK = {"keyframes": "every:60", "epochs": 2}  # a smoke run in seconds, not a measurement


def log_file(data: Path, log: str) -> Path | None:
    """``<log>.clf.bz2`` (the benchmark's files), ``.clf.gz`` (the excerpts in tests/data) or ``.clf``."""
    for suffix in (".clf.bz2", ".clf.gz", ".clf"):
        if (Path(data) / f"{log}{suffix}").is_file():
            return Path(data) / f"{log}{suffix}"
    return None


def corrected_file(data: Path, log: str) -> Path | None:
    path = Path(data) / "corrected" / CORRECTED[log]
    return path if path.is_file() else None


def benchmark_relations(data: Path, log: str) -> Path | None:
    path = Path(data) / f"{log}.relations"
    return path if path.is_file() else None


def reference_trajectory(data: Path, log: str) -> tuple[list[str], np.ndarray] | None:
    """The corrected log's poses at the raw log's timestamps (None without a corrected log)."""
    corrected = corrected_file(data, log)
    return None if corrected is None else corrected_trajectory(corrected, log_file(data, log))


def jobs(quick: bool, data: str) -> list[Job]:
    """One run per (log, method) for each log of ``data`` that has its relations or a corrected
    log; ``reference`` where the corrected log is there."""
    s = QUICK if quick else FULL
    logs = [g for g in LOGS if log_file(data, g) and (benchmark_relations(data, g) or corrected_file(data, g))]
    simulated = [site + SIM_SUFFIX for site, name in SIMULATED.items() if (Path(data) / "corrected" / name).is_file()]
    if not logs and not simulated:
        raise ConfigError(f"{data}: no log with its relations or a corrected log "
                          f"({', '.join(f'{g}.clf.bz2 + {g}.relations' for g in LOGS)})")
    out = []
    for log in logs + simulated:
        names = list(SIM_METHODS) if log in simulated else (["reference"] if corrected_file(data, log) else []) + list(
            METHODS)
        out += [Job(f"{log}-{name}", "deepmapping.experiments.carmen:run",
                    {"data": data, "log": log, "name": name} | s) for name in names]
    return out


def run(data: str, log: str, name: str, keyframes: str, epochs: int | None = None) -> dict:
    """One method on one log, in a fresh process (its own wall time and peak RSS; in this one
    where it may have no children: a daemonic worker of a Dask cluster)."""
    import torch

    row = in_fresh_process(_run_here, data, log, name, keyframes, epochs, torch.get_num_threads())
    return row | {"log": log, "name": name, "keyframes_rule": keyframes}


def _run_here(data: str, log: str, name: str, keyframes: str, epochs: int | None, threads: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    row = _reference(Path(data), log) if name == "reference" else _register(Path(data), log, name, keyframes, epochs,
                                                                              threads)
    return row | {"wall_s": time.perf_counter() - t0, "threads": threads,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def _register(data: Path, log: str, name: str, keyframes: str, epochs: int | None, threads: int) -> dict:
    if log.endswith(SIM_SUFFIX):
        with tempfile.TemporaryDirectory() as tmp:
            path, relations, _ = simulated_log(data / "corrected" / SIMULATED[log.removesuffix(SIM_SUFFIX)], tmp)
            scans = load_scans(path, keyframes=keyframes)
            poses, row = _poses(scans, name, epochs, threads)
            return row | {"relations": evaluate_relations(scans, poses, relations)["relations"],
                          "relations_source": "derived", "derived": None, "on_reference": None,
                          "keyframes": scans.num_scans}
    scans = load_scans(log_file(data, log), keyframes=keyframes)
    poses, row = _poses(scans, name, epochs, threads)
    return row | _scores(data, log, scans, poses) | {"keyframes": scans.num_scans}


def _poses(scans, name: str, epochs: int | None, threads: int) -> tuple[np.ndarray, dict]:
    method, warm = METHODS[name]
    if method is None:
        poses, row = scans.init_poses, {}
    else:
        overrides = {"method": method, "warm_start.method": warm, "threads": threads}
        if method == "deepmapping" and epochs is not None:
            overrides["optim.epochs"] = epochs
        result = register(scans, load_config("default", overrides=overrides))
        poses, row = result.poses, {"runtime_s": result.runtime_s}
    return poses, row


def _scores(data: Path, log: str, scans, poses) -> dict:
    """"relations": on the benchmark's file, else on the derived ones; "derived": on the derived ones;
    "on_reference": on the benchmark relations the corrected log covers."""
    ref = reference_trajectory(data, log)
    on_derived = None if ref is None else _score(scans, poses, derive_relations(*ref))
    bench = benchmark_relations(data, log)
    main = evaluate_relations(scans, poses, bench)["relations"] if bench else on_derived
    return {"relations": main, "relations_source": "benchmark" if bench else "derived", "derived": on_derived,
            "on_reference": _on_reference(bench, ref, scans, poses) if bench else None}


def _score(scans, poses, relations: Relations) -> dict:
    seq = scans.sequence
    return score_relations(relations, seq.stamps, place_all_scans(seq, poses))


def _on_reference(bench: Path, ref: tuple | None, scans, poses) -> dict | None:
    """The errors on the relations the corrected reference covers (both scans in the corrected
    log): the like-for-like comparison with the reference row (intel: 90 of 2984)."""
    if ref is None:
        return None
    covered = set(ref[0])
    rel = read_relations(bench)
    keep = [a in covered and b in covered for a, b in zip(rel.stamp_i, rel.stamp_j)]
    sub = Relations([a for a, k in zip(rel.stamp_i, keep) if k], [b for b, k in zip(rel.stamp_j, keep) if k],
                    rel.motion[np.array(keep)], rel.path)
    return _score(scans, poses, sub)


def _reference(data: Path, log: str) -> dict:
    stamps, poses = reference_trajectory(data, log)
    derived = score_relations(derive_relations(stamps, poses), stamps, poses)
    bench = benchmark_relations(data, log)
    scores = score_relations(read_relations(bench), stamps, poses) if bench else derived
    return {"relations": scores, "relations_source": "benchmark" if bench else "derived", "derived": derived,
            "keyframes": len(stamps)}


def _cell(s: dict | None, what: str) -> str:
    unit = "m" if what == "trans" else "deg"
    if not s or not s.get("count"):
        return "-"
    return f"{s[f'{what}_mean_{unit}']:.3f} ± {s[f'{what}_std_{unit}']:.3f} / {s[f'{what}_median_{unit}']:.3f}"


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    """A relations table per log (the methods in the order of the runs)."""
    rule = (QUICK if quick else FULL)["keyframes"]
    sections = [f"Keyframes `{rule}`{' (quick: a smoke run, not a measurement)' if quick else ''}. Errors: "
                "mean ± std / median over the relations whose two scans the trajectory has (`reference` "
                "covers only the scans of the corrected log), on the benchmark's relations where the log has "
                "them, else on relations derived from its corrected log (3 000 random pairs of scans at most "
                "1 m apart, 40 % over 10 s; the reference scores 0 on them). Short: relations spanning < 10 s, "
                "long: > 10 s (mostly loop closures). Wall time and peak RSS: each run in its own process."]
    for log in [*LOGS, *(site + SIM_SUFFIX for site in SIMULATED)]:
        rows = [r for r in results.values() if r.get("log") == log]
        if not rows:
            continue
        order = ["reference", *METHODS]
        rows.sort(key=lambda r: order.index(r["name"]))
        source = rows[0].get("relations_source", "benchmark")
        what = " with simulated odometry (seed 0)" if log.endswith(SIM_SUFFIX) else ""
        lines = [f"## {log}{what} ({source} relations)", "",
                 "| method | scans registered | relations scored | trans. (m) | rot. (deg) | short: trans. (m) "
                 "| long: trans. (m) | on the reference's relations: trans. (m) | rot. (deg) "
                 "| derived: short (m) | derived: long (m) | wall (s) | peak RSS (MB) |",
                 "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            rel = r["relations"]
            sub = r.get("on_reference", rel) or {}
            der = r.get("derived") or {}
            lines.append(f"| {r['name']} | {r['keyframes']} | {rel['all'].get('count', 0)} of {rel['relations']} | "
                         f"{_cell(rel['all'], 'trans')} | {_cell(rel['all'], 'rot')} | "
                         f"{_cell(rel['short'], 'trans')} | {_cell(rel['long'], 'trans')} | "
                         f"{_cell(sub.get('all'), 'trans')} | {_cell(sub.get('all'), 'rot')} | "
                         f"{_cell(der.get('short'), 'trans')} | {_cell(der.get('long'), 'trans')} | "
                         f"{r['wall_s']:.0f} | {r['peak_rss_mb']:.0f} |")
        sections.append("\n".join(lines))
    return write_report(out, "Freiburg SLAM benchmark logs: relations errors (Kümmerle et al. 2009)", sections)
