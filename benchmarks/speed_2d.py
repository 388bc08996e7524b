"""Speed benchmark: time to accuracy on simulated 256-scan 2D trajectories.

    .venv/bin/python benchmarks/speed_2d.py                      # 5 trajectories, ~25 min on 2 cores
    .venv/bin/python benchmarks/speed_2d.py --trajectories 1 --paper-budget 30 --no-scaling   # a quick look

For every trajectory (procedural map t % 3, trajectory seed t, 256 poses x 256 beams, ideal
scanner: the paper's data settings) it writes the scans to disk in the authors' layout, then
runs each method in a fresh process, as `deepmapping register` does: load the folder,
register (warm start included), write the run folder. Wall time counts from loading to the
written results. Reported per method, median and worst over the trajectories: the wall time
at which the ATE reaches 20, 10, 5.7 and 3 px *and stays there to the end of the run*, the
final ATE, optimizer steps per second, epochs per minute and the process's peak RSS.

`--scaling K` adds one K-scan trajectory and the first 256 scans of it, default profile, to
check that the cost grows about linearly with the number of scans.

Writes results.json, results.md (markdown tables) and ate_vs_time.png (ATE against wall time,
one colour per method, as the paper's Fig. 1) into --out.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import date
from multiprocessing import get_context
from pathlib import Path

import numpy as np

THRESHOLDS = (20.0, 10.0, 5.7, 3.0)
METHODS = {  # name -> (profile, overrides); the paper profile gets a time budget
    "icp-point": ("default", {"method": "icp-point"}),
    "icp-plane": ("default", {"method": "icp-plane"}),
    "deepmapping (default)": ("default", {}),
    "deepmapping (default, warm start icp-point)": ("default", {"warm_start.method": "icp-point"}),
    "direct (default)": ("default", {"method": "direct"}),
    "deepmapping (paper profile, time budget)": ("paper", {"optim.eval_every": 1}),
}


def run_method(data: str, out: str, profile: str, overrides: dict, threads: int) -> dict:
    """One registration in this (fresh) process: load, register, write; wall time and curve."""
    import resource

    import torch

    from deepmapping.api import register
    from deepmapping.config import load_config
    from deepmapping.io.loaders import load_scans
    from deepmapping.output.run_dir import write_run

    torch.set_num_threads(threads)
    cfg = load_config(profile, overrides=overrides | {"threads": threads})
    t0 = time.perf_counter()
    curve: list[tuple[float, float]] = []
    scans = load_scans(data)
    Path(out).mkdir(parents=True, exist_ok=True)
    res = register(scans, cfg, checkpoint=Path(out) / "checkpoint.pt",
                   on_log=lambda row: curve.append((time.perf_counter() - t0, row["ate"])))
    write_run(Path(out), scans, res, {"data": data})
    wall = time.perf_counter() - t0
    curve.append((wall, res.metrics["ate"]))
    h = res.history or {}
    steps, train_s = (h.get("iteration") or [0])[-1], (h.get("time_s") or [0.0])[-1]
    return {"ate": res.metrics["ate"], "point_distance": res.metrics["point_distance"], "wall_s": wall,
            "num_scans": scans.num_scans, "epochs": (h.get("epoch") or [0])[-1], "steps": steps,
            "train_s": train_s, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "curve": curve}


def time_to_reach(curve: list, threshold: float) -> float | None:
    """Earliest wall time from which every later ATE is <= threshold (None: not at the end)."""
    reached = None
    for t, ate in curve:
        if ate is None or ate > threshold:
            reached = None
        elif reached is None:
            reached = t
    return reached


def simulate_to_disk(root: Path, t: int, poses: int) -> Path:
    from deepmapping.sim.dataset import simulate, write_authors_layout
    from deepmapping.sim.maps import procedural_indoor_map

    folder = root / f"traj{t}_K{poses}"
    if not (folder / "gt_pose.mat").exists():
        occ = procedural_indoor_map(t % 3)
        write_authors_layout(folder, simulate(occ, poses, seed=t), occ=occ)
    return folder


def prefix_copy(src: Path, dst: Path, k: int) -> Path:
    """The first k scans of an authors'-layout folder (for the scaling check)."""
    import shutil

    from scipy.io import loadmat, savemat

    if not (dst / "gt_pose.mat").exists():
        dst.mkdir(parents=True, exist_ok=True)
        for i in range(k):
            shutil.copy(src / f"{i:03d}.pcd", dst / f"{i:03d}.pcd")
        savemat(dst / "gt_pose.mat", {"pose": loadmat(src / "gt_pose.mat")["pose"][:k]})
    return dst


def summarize(runs: list[dict]) -> dict:
    """Median and worst over trajectories of everything the table shows."""
    out = {"n": len(runs)}
    for key in ("ate", "point_distance", "wall_s", "peak_rss_mb"):
        vals = [r[key] for r in runs]
        out[key] = (float(np.median(vals)), float(max(vals)))
    trained = [r for r in runs if r["steps"]]
    out["steps_per_s"] = float(np.median([r["steps"] / r["train_s"] for r in trained])) if trained else None
    out["epochs_per_min"] = float(np.median([60 * r["epochs"] / r["train_s"] for r in trained])) if trained else None
    for th in THRESHOLDS:
        times = [time_to_reach(r["curve"], th) for r in runs]
        hit = [t for t in times if t is not None]
        median = float(np.median([t if t is not None else np.inf for t in times]))
        out[f"t{th:g}"] = (median, max(times, key=lambda t: np.inf if t is None else t), len(hit))
    return out


def fmt_time(med_worst_hits: tuple, n: int) -> str:
    med, worst, hits = med_worst_hits
    if hits == 0:
        return "never"
    m = "never" if not np.isfinite(med) else f"{med:.1f}"
    w = "never" if worst is None else f"{worst:.1f}"
    return f"{m} / {w}" + ("" if hits == n else f" ({hits}/{n})")


def table(summary: dict, meta: dict) -> str:
    head = ["method", *[f"time to {th:g} px (s)" for th in THRESHOLDS], "final ATE (px)", "wall (s)",
            "steps/s", "epochs/min", "peak RSS (MB)"]
    lines = [f"Median / worst over {meta['trajectories']} simulated trajectories of {meta['poses']} scans x 256 beams "
             f"(ideal scanner); {meta['date']}, {meta['machine']}, torch {meta['torch']}. Paper profile: "
             f"{meta['paper_budget_s']:g} s training budget. Times are wall time from loading to the point from "
             "which the ATE stays below the threshold (n/N: reached on only n trajectories).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, s in summary.items():
        n = s["n"]
        cells = [name, *[fmt_time(s[f"t{th:g}"], n) for th in THRESHOLDS],
                 f"{s['ate'][0]:.2f} / {s['ate'][1]:.2f}", f"{s['wall_s'][0]:.1f} / {s['wall_s'][1]:.1f}",
                 "-" if s["steps_per_s"] is None else f"{s['steps_per_s']:.1f}",
                 "-" if s["epochs_per_min"] is None else f"{s['epochs_per_min']:.1f}",
                 f"{s['peak_rss_mb'][0]:.0f} / {s['peak_rss_mb'][1]:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def scaling_table(scaling: dict) -> str:
    if not scaling:
        return ""
    small, big = scaling["small"], scaling["big"]
    return (f"\nScaling (default profile, one trajectory, the first {small['num_scans']} scans vs all "
            f"{big['num_scans']}): wall {small['wall_s']:.1f} s vs {big['wall_s']:.1f} s "
            f"(x{big['wall_s'] / small['wall_s']:.2f}), ATE {small['ate']:.2f} vs {big['ate']:.2f} px, "
            f"peak RSS {small['peak_rss_mb']:.0f} vs {big['peak_rss_mb']:.0f} MB.\n")


def plot(results: dict, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5))
    ax = fig.add_subplot()
    colors = dict(zip(results, [f"C{i}" for i in range(len(results))]))
    for name, runs in results.items():
        for i, r in enumerate(runs):
            t, a = zip(*[(t, a) for t, a in r["curve"] if a is not None])
            kw = {"color": colors[name], "label": name if i == 0 else None}
            if r["steps"]:
                ax.plot(t, a, lw=1, alpha=0.8, **kw)
            else:
                ax.plot(t[-1:], a[-1:], "o", ms=5, **kw)
    for th in THRESHOLDS[2:]:
        ax.axhline(th, color="grey", lw=0.6, ls=":")
    for budget in (60, 120):
        ax.axvline(budget, color="grey", lw=0.6, ls="--")
    ax.set(xlabel="wall time from loading (s)", ylabel="ATE (px)", yscale="log", xscale="log", xlim=(0.8, None),
           title="ATE against wall time (one line per trajectory)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)


def parse_args():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trajectories", type=int, default=5)
    ap.add_argument("--poses", type=int, default=256)
    ap.add_argument("--paper-budget", type=float, default=120.0, help="training time of the paper profile (s)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS), metavar="NAME")
    ap.add_argument("--scaling", type=int, default=1024, help="scans of the scaling check")
    ap.add_argument("--no-scaling", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="setting for every trained run, e.g. optim.epochs=3 for a smoke test")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--replot", action="store_true", help="only redraw the figure from --out/results.json")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/speed_2d"))
    return ap.parse_args()


def main() -> None:
    args = parse_args()
    if args.replot:
        plot(json.loads((args.out / "results.json").read_text())["results"], args.out / "ate_vs_time.png")
        return
    import torch

    from deepmapping.cli.common import parse_sets

    extra = parse_sets(args.set)
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, list] = {m: [] for m in args.methods}
    scaling: dict = {}
    with ProcessPoolExecutor(1, mp_context=get_context("spawn"), max_tasks_per_child=1) as pool:
        for t in range(args.trajectories):
            data = simulate_to_disk(args.out / "data", t, args.poses)
            for name in args.methods:
                profile, over = METHODS[name]
                if profile == "paper":
                    over = over | {"optim.max_time_s": args.paper_budget}
                if not name.startswith("icp"):
                    over = over | extra
                run_dir = str(args.out / "runs" / f"traj{t}" / re.sub(r"[^a-z0-9]+", "_", name).strip("_"))
                r = pool.submit(run_method, str(data), run_dir, profile, over | {"seed": t}, args.threads).result()
                results[name].append(r)
                print(f"trajectory {t} {name}: ATE {r['ate']:.2f} px, wall {r['wall_s']:.1f} s, "
                      f"peak RSS {r['peak_rss_mb']:.0f} MB", flush=True)
        if not args.no_scaling:
            big = simulate_to_disk(args.out / "data", 0, args.scaling)
            small = prefix_copy(big, args.out / "data" / f"traj0_K{args.scaling}_first{args.poses}", args.poses)
            for key, folder in (("small", small), ("big", big)):
                scaling[key] = pool.submit(run_method, str(folder), str(args.out / "runs" / f"scaling_{key}"),
                                           "default", {"seed": 0} | extra, args.threads).result()
                print(f"scaling {key}: {scaling[key]['num_scans']} scans, ATE {scaling[key]['ate']:.2f} px, "
                      f"wall {scaling[key]['wall_s']:.1f} s", flush=True)
    meta = {"date": str(date.today()), "machine": f"{platform.machine()}, {args.threads} torch threads",
            "python": platform.python_version(), "torch": torch.__version__, "poses": args.poses,
            "trajectories": args.trajectories, "paper_budget_s": args.paper_budget, "settings": extra}
    from deepmapping.output.run_dir import write_text as write_atomic

    summary = {name: summarize(runs) for name, runs in results.items()}
    write_atomic(args.out / "results.json", json.dumps({"meta": meta, "summary": summary, "results": results,
                                                        "scaling": scaling}, indent=1))
    md = table(summary, meta) + scaling_table(scaling)
    write_atomic(args.out / "results.md", md)
    plot(results, args.out / "ate_vs_time.png")
    print(md)


if __name__ == "__main__":
    main()
