"""AVD-like 3D benchmark (paper §4.2 and supplementary C, Table 2).

    .venv/bin/python benchmarks/avd_3d.py                        # 10 trajectories x 16 frames
    .venv/bin/python benchmarks/avd_3d.py --trajectories 2 --frames 8 --set optim.epochs=20   # smoke run

Simulates AVD-like trajectories (`deepmapping simulate --kind rgbd`: 300 mm grid, 12 views
per position 30 deg apart, random moves and turns, 80x60 depth images), registers each with
every method and reports, per method: the success rate (ATE < 450 mm, the paper's
criterion), the median and mean ATE, the median point distance and rotation RMSE, and the
mean runtime. "identity" is no registration at all (every pose at the origin): it shows how
much of the 450 mm criterion a method must earn. Each run is done in its own process
(`--jobs` at a time, one torch thread each). Writes results.json and results.md into --out.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import date
from multiprocessing import get_context
from pathlib import Path

import numpy as np

METHODS = {  # name -> (profile, overrides)
    "multiway": ("default-3d", {"method": "multiway"}),
    "icp-plane": ("default-3d", {"method": "icp-plane"}),
    "icp-planar": ("default-3d", {"method": "icp-planar"}),
    "deepmapping": ("default-3d", {}),  # warm start "auto" = icp-planar on these
    "deepmapping-cold": ("default-3d", {"warm_start.method": "none"}),
    "direct": ("default-3d", {"method": "direct"}),
    "direct-cold": ("default-3d", {"method": "direct", "warm_start.method": "none"}),
}
# success %, real AVD; the paper's DeepMapping and direct runs start cold (no warm start)
PAPER_TABLE_2 = {"deepmapping-cold": 80.0, "direct-cold": 77.1, "multiway": 58.1}


def run_method(data: str, profile: str, overrides: dict, threads: int) -> dict:
    import torch

    from deepmapping.api import register
    from deepmapping.config import load_config
    from deepmapping.io.loaders import load_scans

    torch.set_num_threads(threads)
    scans = load_scans(data)
    if profile == "identity":
        from deepmapping.api import evaluate_poses

        return evaluate_poses(scans, np.tile(np.eye(4), (scans.num_scans, 1, 1))) | {"runtime_s": 0.0}
    cfg = load_config(profile, overrides=overrides | {"threads": threads})
    return register(scans, cfg).metrics


def summarize(rows: list[dict]) -> dict:
    ate = np.array([r["ate"] for r in rows])
    return {
        "runs": len(rows),
        "success_pct": 100.0 * np.mean([r["success"] for r in rows]),
        "ate_median": float(np.median(ate)), "ate_mean": float(ate.mean()),
        "point_distance_median": float(np.median([r["point_distance"] for r in rows])),
        "rotation_rmse_median_deg": float(np.median([r["rotation_rmse_deg"] for r in rows])),
        "success_rot5_pct": 100.0 * np.mean([r["success"] and r["rotation_rmse_deg"] < 5.0 for r in rows]),
        "runtime_mean_s": float(np.mean([r["runtime_s"] for r in rows])),
    }


def markdown(summary: dict, args) -> str:
    lines = [f"# AVD-like 3D benchmark ({args.trajectories} trajectories x {args.frames} frames)", "",
             f"{date.today()}, {platform.machine()}, {args.jobs} job(s) x 1 torch thread; "
             f"`python benchmarks/avd_3d.py {' '.join(args.argv)}`", "",
             "| method | success (ATE < 450 mm) | paper (Table 2, real AVD) | success and rot. RMSE < 5 deg "
             "| median ATE (mm) | mean ATE (mm) | median point dist. (mm) | median rot. RMSE (deg) | mean runtime (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, s in summary.items():
        paper = f"{PAPER_TABLE_2[name]:.1f} %" if name in PAPER_TABLE_2 else "-"
        lines.append(f"| {name} | {s['success_pct']:.0f} % | {paper} | {s['success_rot5_pct']:.0f} % | "
                     f"{s['ate_median']:.0f} | {s['ate_mean']:.0f} | {s['point_distance_median']:.0f} | "
                     f"{s['rotation_rmse_median_deg']:.1f} | {s['runtime_mean_s']:.1f} |")
    return "\n".join(lines) + "\n"


def parse_sets(items: list[str]) -> dict:
    import yaml

    return {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in items)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trajectories", type=int, default=10)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--set", action="append", default=[], help="override for the DeepMapping/direct runs")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "avd_3d")
    args = ap.parse_args(argv)
    args.argv = argv if argv is not None else __import__("sys").argv[1:]
    from deepmapping.sim.rgbd import write_rgbd_dataset

    folders = write_rgbd_dataset(args.out / "data", num_trajectories=args.trajectories, frames=args.frames,
                                 seed=args.seed)
    sets = parse_sets(args.set)
    plan = {"identity": ("identity", {})}
    plan |= {m: (METHODS[m][0], METHODS[m][1] | (sets if m.split("-")[0] in ("deepmapping", "direct") else {}))
             for m in args.methods.split(",")}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        futures = {(m, str(f)): pool.submit(run_method, str(f), p, o, 1) for m, (p, o) in plan.items() for f in folders}
        rows = {key: fut.result() for key, fut in futures.items()}
    results = {m: [rows[m, str(f)] | {"data": str(f)} for f in folders] for m in plan}
    summary = {m: summarize(r) for m, r in results.items()}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps({"summary": summary, "runs": results}, indent=1, default=float))
    (args.out / "results.md").write_text(markdown(summary, args))
    print(markdown(summary, args))
    print(f"total {time.perf_counter() - t0:.0f} s")
    return summary


if __name__ == "__main__":
    main()
