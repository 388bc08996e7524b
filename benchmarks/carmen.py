"""Freiburg SLAM benchmark logs: relations errors of DeepMapping and baselines.

    .venv/bin/python benchmarks/carmen.py                                  # intel and fr079, full
    .venv/bin/python benchmarks/carmen.py --logs fr079 --methods odometry,icp --keyframes every:50   # smoke

For each log in ``../shared/data/carmen`` (``<log>.clf.bz2`` + ``<log>.relations``) registers the
keyframes (``--keyframes``, default motion:0.5,15) with each method, places every scan of the log
from its nearest keyframe (odometry, then ICP to the keyframes around it), and scores all relations of Kümmerle et al. 2009:
translational (m) and rotational (deg) errors, mean ± std and median, split at 10 s.

methods: ``odometry`` (the log's poses), ``icp`` (incremental point-to-point ICP, each pair
started from odometry), ``dm-odometry`` / ``dm-icp`` (DeepMapping, default profile, warm-started
from odometry / from that ICP), ``loop-closure`` (incremental ICP with loop closures and
pose-graph optimization, methods.loop_closure), ``dm-loop-closure`` (DeepMapping warm-started from
it), and ``reference``: the corrected trajectory shipped with the
benchmark (``corrected/<name>-corrected.log.gz``), matched to the raw scans by their ranges.
Each run is its own process (one at a time, ``--threads`` torch threads): its wall time and peak
RSS are its own. Writes results.json and results.md into --out.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import date
from multiprocessing import get_context
from pathlib import Path

import numpy as np

CARMEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen"
CORRECTED = {"intel": "intel-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz"}


def log_file(data: Path, log: str) -> Path:
    """``<log>.clf.bz2`` (../shared/data/carmen), ``.clf.gz`` (the excerpts in tests/data) or ``.clf``."""
    for suffix in (".clf.bz2", ".clf.gz", ".clf"):
        if (data / f"{log}{suffix}").is_file():
            return data / f"{log}{suffix}"
    raise SystemExit(f"{data / log}.clf.bz2: file not found (nor .clf.gz, .clf)")


METHODS = {  # name -> (method, warm start)
    "odometry": (None, "file"),
    "icp": ("icp-point", "file"),
    "dm-odometry": ("deepmapping", "file"),
    "dm-icp": ("deepmapping", "icp-point"),
    "loop-closure": ("loop-closure", "file"),
    "dm-loop-closure": ("deepmapping", "loop-closure"),
}


def run_method(data: Path, log: str, name: str, keyframes: str, sets: dict, threads: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    if name == "reference":
        row = _reference(data, log)
    else:
        row = _register(data, log, name, keyframes, sets, threads)
    row["wall_s"] = time.perf_counter() - t0
    row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return row


def _register(data: Path, log: str, name: str, keyframes: str, sets: dict, threads: int) -> dict:
    from deepmapping.api import evaluate_relations, register
    from deepmapping.config import load_config
    from deepmapping.io.loaders import load_scans

    scans = load_scans(log_file(data, log), keyframes=keyframes)
    method, warm = METHODS[name]
    if method is None:
        row = evaluate_relations(scans, scans.init_poses) | {"keyframes": scans.num_scans}
        return row | {"on_reference": _on_reference(data, log, scans, scans.init_poses)}
    overrides = {"method": method, "warm_start.method": warm, "threads": threads}
    if method == "deepmapping":
        overrides |= sets
    result = register(scans, load_config("default", overrides=overrides))
    return result.metrics | {"keyframes": scans.num_scans, "runtime_s": result.runtime_s,
                             "on_reference": _on_reference(data, log, scans, result.poses)}


def _on_reference(data: Path, log: str, scans, poses) -> dict:
    """The errors on the relations the corrected reference covers (both scans in the corrected
    log): the like-for-like comparison with the reference row (intel: 90 of 2984)."""
    from deepmapping.evaluation.relations import Relations, read_relations, score_relations
    from deepmapping.io.carmen import match_scans, read_carmen
    from deepmapping.methods.keyframes import place_all_scans

    raw = read_carmen(log_file(data, log))
    idx = match_scans(read_carmen(data / "corrected" / CORRECTED[log]), raw)
    covered = {raw.stamps[k] for k in idx[idx >= 0]}
    rel = read_relations(data / f"{log}.relations")
    keep = [a in covered and b in covered for a, b in zip(rel.stamp_i, rel.stamp_j)]
    sub = Relations([a for a, k in zip(rel.stamp_i, keep) if k], [b for b, k in zip(rel.stamp_j, keep) if k],
                    rel.motion[np.array(keep)], rel.path)
    seq = scans.sequence
    return score_relations(sub, seq.stamps, place_all_scans(seq, poses))


def _reference(data: Path, log: str) -> dict:
    from deepmapping.evaluation.relations import read_relations, score_relations
    from deepmapping.io.carmen import match_scans, read_carmen

    raw = read_carmen(log_file(data, log))
    ref = read_carmen(data / "corrected" / CORRECTED[log])
    idx = match_scans(ref, raw)
    ok = idx >= 0
    scores = score_relations(read_relations(data / f"{log}.relations"), [raw.stamps[k] for k in idx[ok]],
                             ref.poses[ok])
    return {"relations": scores, "keyframes": int(ok.sum())}


def _cell(s: dict, what: str) -> str:
    unit = "m" if what == "trans" else "deg"
    if not s.get("count"):
        return "-"
    return f"{s[f'{what}_mean_{unit}']:.3f} ± {s[f'{what}_std_{unit}']:.3f} / {s[f'{what}_median_{unit}']:.3f}"


def markdown(results: dict, args) -> str:
    lines = ["# Freiburg SLAM benchmark logs: relations errors (Kümmerle et al. 2009)", "",
             f"{date.today()}, {platform.machine()}, {platform.processor() or 'cpu'}, {args.threads} torch "
             f"thread(s), keyframes `{args.keyframes}`; `python benchmarks/carmen.py {' '.join(args.argv)}`", "",
             "Errors: mean ± std / median over the relations whose two scans the trajectory has "
             "(`reference` covers only the scans of the corrected log). Short: relations spanning "
             "< 10 s, long: > 10 s (mostly loop closures).", ""]
    for log, rows in results.items():
        lines += [f"## {log}", "",
                  "| method | scans registered | relations scored | trans. (m) | rot. (deg) | short: trans. (m) "
                  "| long: trans. (m) | on the reference's relations: trans. (m) | rot. (deg) | wall (s) "
                  "| peak RSS (MB) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for name, r in rows.items():
            rel = r["relations"]
            sub = r.get("on_reference", rel)
            lines.append(f"| {name} | {r['keyframes']} | {rel['all'].get('count', 0)} of {rel['relations']} | "
                         f"{_cell(rel['all'], 'trans')} | {_cell(rel['all'], 'rot')} | {_cell(rel['short'], 'trans')} | "
                         f"{_cell(rel['long'], 'trans')} | {_cell(sub['all'], 'trans')} | {_cell(sub['all'], 'rot')} | "
                         f"{r['wall_s']:.0f} | {r['peak_rss_mb']:.0f} |")
        lines.append("")
    return "\n".join(lines)


def parse_sets(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", default="intel,fr079")
    ap.add_argument("--methods", default="reference," + ",".join(METHODS))
    ap.add_argument("--keyframes", default="motion:0.5,15")
    ap.add_argument("--set", action="append", default=[], help="override for the DeepMapping runs")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "carmen")
    ap.add_argument("--data", type=Path, default=CARMEN, help="folder of <log>.clf.bz2, <log>.relations, corrected/")
    args = ap.parse_args(argv)
    args.argv = argv if argv is not None else __import__("sys").argv[1:]
    sets = parse_sets(args.set)
    results: dict = {}
    for log in args.logs.split(","):
        results[log] = {}
        for name in args.methods.split(","):
            if name != "reference" and name not in METHODS:
                raise SystemExit(f"unknown method {name!r} (known: reference, {', '.join(METHODS)})")
            with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:  # fresh process: own RSS
                row = pool.submit(run_method, args.data, log, name, args.keyframes, sets, args.threads).result()
            results[log][name] = row
            a = row["relations"]["all"]
            print(f"{log:6s} {name:12s} {a.get('trans_mean_m', float('nan')):8.3f} m "
                  f"{a.get('rot_mean_deg', float('nan')):7.2f} deg  {row['wall_s']:6.0f} s "
                  f"{row['peak_rss_mb']:6.0f} MB", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    (args.out / "results.md").write_text(markdown(results, args))
    print(markdown(results, args))
    return results


if __name__ == "__main__":
    main()
