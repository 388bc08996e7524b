"""Compare every 2D method on simulated 256-scan trajectories: ATE, point distance, runtime.

    .venv/bin/python benchmarks/compare_2d.py --seeds 0 --out benchmarks/results/compare_2d

Writes results.json, results.md (a markdown table) and ate_vs_time.png (ATE against wall
time for the trained methods, as the paper's Fig. 1) into --out. Each run goes through the
public `register` API with the settings printed in the table.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
from datetime import date
from pathlib import Path

import numpy as np

from deepmapping.api import register
from deepmapping.config import load_config
from deepmapping.sim.dataset import simulate
from deepmapping.sim.maps import procedural_indoor_map

RUNS = {  # name -> (profile, overrides)
    "icp-point": ("default", {"method": "icp-point"}),
    "icp-plane": ("default", {"method": "icp-plane"}),
    "direct (default profile, warm start icp-plane)": ("default", {"method": "direct"}),
    "deepmapping (default profile, warm start icp-plane)": ("default", {}),
    "deepmapping (default profile, warm start icp-point)": ("default", {"warm_start.method": "icp-point"}),
}


def run_one(scans, profile, overrides, max_time_s):
    if max_time_s:
        overrides = overrides | {"optim.max_time_s": max_time_s}
    cfg = load_config(profile, overrides=overrides)
    res = register(scans, cfg)
    hist = res.history or {}
    return {"ate": res.metrics["ate"], "point_distance": res.metrics["point_distance"],
            "runtime_s": res.runtime_s, "epochs": (hist.get("epoch") or [0])[-1],
            "curve": {"time_s": hist.get("time_s", []), "ate": hist.get("ate", [])}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--poses", type=int, default=256)
    ap.add_argument("--noise", type=float, default=0.0, help="range noise std (px)")
    ap.add_argument("--max-time", type=float, default=None, help="time budget per trained run (s)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/compare_2d"))
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for seed in args.seeds:
        scans = simulate(procedural_indoor_map(seed % 3), args.poses, seed=seed, range_noise_px=args.noise)
        for name, (profile, over) in RUNS.items():
            r = run_one(scans, profile, over | {"seed": seed}, args.max_time)
            results.setdefault(name, []).append(r)
            print(f"seed {seed} {name}: ATE {r['ate']:.2f} px, {r['runtime_s']:.1f} s", flush=True)
    meta = {"date": str(date.today()), "machine": f"{platform.processor() or platform.machine()}, "
            f"{args.threads} torch threads", "python": platform.python_version(), "torch": torch.__version__,
            "poses": args.poses, "noise_px": args.noise, "seeds": args.seeds,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    (args.out / "results.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    (args.out / "results.md").write_text(table(results, meta))
    plot(results, args.out / "ate_vs_time.png")
    print(table(results, meta))


def table(results, meta) -> str:
    lines = [f"{meta['poses']} scans x 256 beams, range noise {meta['noise_px']} px, seeds {meta['seeds']}; "
             f"{meta['date']}, {meta['machine']}, torch {meta['torch']}", "",
             "| method | median ATE (px) | worst ATE (px) | median point dist. (px) | median runtime (s) |",
             "|---|---|---|---|---|"]
    for name, rs in results.items():
        ate = [r["ate"] for r in rs]
        lines.append(f"| {name} | {np.median(ate):.2f} | {max(ate):.2f} | "
                     f"{np.median([r['point_distance'] for r in rs]):.2f} | "
                     f"{np.median([r['runtime_s'] for r in rs]):.1f} |")
    return "\n".join(lines) + "\n"


def plot(results, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4.5))
    ax = fig.add_subplot()
    for name, rs in results.items():
        for i, r in enumerate(rs):
            t, a = r["curve"]["time_s"], r["curve"]["ate"]
            if t:
                ax.plot(t, a, label=name if i == 0 else None)
            else:
                ax.axhline(r["ate"], ls="--", lw=0.8, color="grey" if "point" in name else "black",
                           label=name if i == 0 else None)
    ax.set(xlabel="wall time (s)", ylabel="ATE (px)", yscale="log", title="ATE against wall time")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)


if __name__ == "__main__":
    main()
