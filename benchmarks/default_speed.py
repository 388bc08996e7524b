"""What a user waits for: the whole default `deepmapping register` command, per stage.

    .venv/bin/python benchmarks/default_speed.py                       # 2D 256 scans, RGB-D 16 frames, 5 runs each
    .venv/bin/python benchmarks/default_speed.py --cases 2d-256 --runs 1   # a quick look
    .venv/bin/python benchmarks/default_speed.py --cases 2d-256 --profile fast --out benchmarks/results/default_speed_fast
    .venv/bin/python benchmarks/default_speed.py --cases carmen --runs 1   # a 4 934-scan CARMEN log (long)

Each run is a fresh `deepmapping register DATA --out RUN` process with no other flags (plus
`--set` values given here, to compare settings), timed from start to exit. Reported per case,
median and worst over the runs: wall time, the stages the command itself writes to run.json
(loading, warm start, cold-start placements, training, results and pictures), epochs run (the
stopping rule may end training before the budget), peak memory, and the final error (ATE, or
the Freiburg relations error for a log). Cases:

- ``2d-256``: a simulated 256-scan trajectory (procedural map 0, seed 3, the authors' layout);
- ``2d-1024``: 1024 scans of the same kind, for the scaling check (not in the default list);
- ``rgbd-16`` / ``rgbd-50``: 16 frames (every 3rd of frames 150-195) / all 50 of ../shared's
  7-Scenes sample;
- ``carmen``: ../shared's fr079 log, 4 934 scans (its default: loop-closure warm start).

Writes results.json and results.md into --out.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import resource
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
DM = str(Path(sys.executable).parent / "deepmapping")
STAGES = ("load_s", "warm_start_s", "curriculum_s", "training_s", "write_s")


def case_args(case: str, data_root: Path) -> list[str]:
    """The data argument (and data-selection flags) of `deepmapping register` for a case."""
    if case.startswith("2d-"):
        k = int(case.split("-")[1])
        folder = data_root / f"sim2d_{k}"
        if not (folder / "gt_pose.mat").exists():
            subprocess.run([DM, "simulate", str(folder), "--poses", str(k), "--seed", "3"], check=True,
                           capture_output=True)
        return [str(folder)]
    if case == "rgbd-16":
        return [str(SHARED / "7scenes-redkitchen"), "--frames", "0:46", "--every", "3"]
    if case == "rgbd-50":
        return [str(SHARED / "7scenes-redkitchen")]
    if case == "carmen":
        return [str(SHARED / "carmen" / "fr079.clf.bz2")]
    raise SystemExit(f"unknown case {case!r}")


def run_once(args: list[str], out: Path, sets: list[str], profile: str | None = None) -> dict:
    """One fresh process; wall time, its run.json stages and metrics, its peak memory."""
    extra = [a for s in sets for a in ("--set", s)] + (["--profile", profile] if profile else [])
    t0 = time.perf_counter()
    proc = subprocess.run([DM, "register", *args, "--out", str(out), *extra], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
    info = json.loads((out / "run.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").exists() else {}
    history = (out / "history.csv").read_text().splitlines() if (out / "history.csv").exists() else []
    epochs = float(history[-1].split(",")[1]) if len(history) > 1 else 0.0
    rel = metrics.get("relations", {}).get("all", {})  # a log: the Freiburg relations error (m)
    error = metrics.get("ate", rel.get("trans_mean_m"))
    return {"wall_s": wall, **{k: info["timings"].get(k, 0.0) for k in STAGES},
            "peak_rss_mb": info["timings"]["peak_rss_mb"], "epochs": epochs, "error": error,
            "unit": info.get("unit"), "stop_reason": info.get("stop_reason", "")}


def summary_row(case: str, runs: list[dict]) -> str:
    def mw(key, fmt="{:.1f}"):
        vals = [r[key] for r in runs if r[key] is not None]
        return "–" if not vals else f"{fmt.format(np.median(vals))} / {fmt.format(max(vals))}"

    cells = [case, str(len(runs)), mw("wall_s"), *[mw(k) for k in STAGES], mw("epochs", "{:.0f}"),
             mw("peak_rss_mb", "{:.0f}"), mw("error", "{:.3g}") + f" {runs[0]['unit'] or ''}"]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=["2d-256", "rgbd-16"])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a setting for every run")
    ap.add_argument("--profile", default=None, help="a profile for every run (default: the command's own)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/default_speed"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results_path = args.out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    for case in args.cases:
        data = case_args(case, args.out / "data")
        runs = results.setdefault(case, [])
        while len(runs) < args.runs:  # resumes: runs already recorded are kept
            run_dir = args.out / "runs" / f"{re.sub(r'[^a-z0-9]+', '_', case)}_{len(runs)}"
            r = run_once(data, run_dir, args.set, args.profile)
            runs.append(r)
            results_path.write_text(json.dumps(results, indent=1))
            print(f"{case} run {len(runs)}: wall {r['wall_s']:.1f} s, training {r['training_s']:.1f} s, "
                  f"{r['epochs']:.0f} epochs, error {r['error']}, peak {r['peak_rss_mb']:.0f} MB", flush=True)
    head = ["case", "runs", "wall (s)", "loading", "warm start", "placements", "training", "results + pictures",
            "epochs", "peak RSS (MB)", "final error"]
    meta = (f"Median / worst over the runs; {date.today()}, {platform.machine()}, {platform.python_version()}, "
            f"children's peak RSS {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024:.0f} MB; "
            f"profile: {args.profile or 'the default'}, settings: {args.set or 'none'}. Stage times in s.")
    lines = [meta, "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += [summary_row(case, runs) for case, runs in results.items() if runs]
    (args.out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
