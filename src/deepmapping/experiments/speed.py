"""``deepmapping experiment speed``: time to accuracy on simulated 256-scan 2D trajectories.

    deepmapping experiment speed --out DIR --jobs 1 --threads 2    # 5 trajectories, ~25 min on 2 cores
    deepmapping experiment speed --out DIR --quick                 # a smoke run, not a measurement

For every trajectory (procedural map t % 3, trajectory seed t, 256 poses x 256 beams, ideal
scanner: the paper's data settings) each run writes the scans to a temporary folder in the
authors' layout, then registers them in a fresh process, as ``deepmapping register`` does: load
the folder, register (warm start included, with a checkpoint), write the run folder. Wall time
counts from loading to the written results. Reported per method, median and worst over the
trajectories: the wall time at which the ATE reaches 20, 10, 5.7 and 3 px *and stays there to
the end of the run*, the final ATE, optimizer steps per second, epochs per minute and the
process's peak RSS. Runs that share the cores slow each other down: measure with ``--jobs 1``.

The scaling check registers one 1024-scan trajectory and the first 256 scans of it (default
profile), to check that the cost grows about linearly with the number of scans.

Report: the table, the scaling line and ``ate_vs_time.png`` (ATE against wall time, one colour
per method, as the paper's Fig. 1). ``--quick``: one trajectory of 12 scans, every method with
3 epochs of training, the paper profile with a 2 s budget, the scaling check at 24 vs 12 scans.
"""

from __future__ import annotations

import re
import resource
import shutil
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from scipy.io import loadmat, savemat

from deepmapping.api import register
from deepmapping.config import load_config
from deepmapping.experiments.base import Job, in_fresh_process
from deepmapping.experiments.report import image, save_figure, write_report
from deepmapping.io.loaders import load_scans
from deepmapping.output.run_dir import write_run
from deepmapping.sim.dataset import simulate, write_authors_layout
from deepmapping.sim.maps import procedural_indoor_map

THRESHOLDS = (20.0, 10.0, 5.7, 3.0)
METHODS = {  # name -> (profile, overrides); the paper profile gets a time budget
    "icp-point": ("default", {"method": "icp-point"}),
    "icp-plane": ("default", {"method": "icp-plane"}),
    "deepmapping (default)": ("default", {}),
    "deepmapping (default, warm start icp-point)": ("default", {"warm_start.method": "icp-point"}),
    "direct (default)": ("default", {"method": "direct"}),
    "deepmapping (paper profile, time budget)": ("paper", {"optim.eval_every": 1}),
}
# sizes; "settings": the overrides of every trained run (not the ICP ones)
FULL = {"trajectories": 5, "poses": 256, "paper_budget_s": 120.0, "scaling": 1024, "settings": {}}
QUICK = {"trajectories": 1, "poses": 12, "paper_budget_s": 2.0, "scaling": 24, "settings": {"optim.epochs": 3}}
FILE = "ate_vs_time.png"


def sizes(quick: bool) -> dict:
    return dict(QUICK if quick else FULL)


def method_key(name: str) -> str:
    """A method's part of a run key: "deepmapping (default)" -> "deepmapping-default"."""
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def jobs(quick: bool) -> list[Job]:
    """One run per (trajectory, method): ``t<T>-<method>``; then ``scaling-small`` and ``scaling-big``."""
    s = sizes(quick)
    out = [Job(f"t{t}-{method_key(name)}", "deepmapping.experiments.speed:run",
               {"trajectory": t, "method": name, "poses": s["poses"], "paper_budget_s": s["paper_budget_s"],
                "settings": s["settings"]})
           for t in range(s["trajectories"]) for name in METHODS]
    for which, first in (("small", s["poses"]), ("big", None)):
        out.append(Job(f"scaling-{which}", "deepmapping.experiments.speed:run_scaling",
                       {"scans": s["scaling"], "first": first, "settings": s["settings"]}))
    return out


def run(trajectory: int, method: str, poses: int = 256, paper_budget_s: float = 120.0,
        settings: dict | None = None) -> dict:
    """Trajectory ``trajectory`` (``poses`` scans) registered by ``method`` in a fresh process."""
    profile, overrides = METHODS[method]
    if profile == "paper":
        overrides = overrides | {"optim.max_time_s": paper_budget_s}
    if not method.startswith("icp"):
        overrides = overrides | (settings or {})
    with TemporaryDirectory(prefix="deepmapping-speed-") as tmp:
        data = simulate_to_disk(Path(tmp), trajectory, poses)
        row = _fresh(str(data), str(Path(tmp) / "run"), profile, overrides | {"seed": trajectory})
    return row | {"method": method, "trajectory": trajectory}


def run_scaling(scans: int, first: int | None = None, settings: dict | None = None) -> dict:
    """The scaling check: trajectory 0 of ``scans`` scans (or its first ``first``), default profile."""
    with TemporaryDirectory(prefix="deepmapping-speed-") as tmp:
        data = simulate_to_disk(Path(tmp), 0, scans)
        if first is not None:
            data = prefix_copy(data, Path(tmp) / f"traj0_K{scans}_first{first}", first)
        row = _fresh(str(data), str(Path(tmp) / "run"), "default", {"seed": 0} | (settings or {}))
    return row | {"scaling": "big" if first is None else "small", "trajectory": 0}


def _fresh(data: str, out: str, profile: str, overrides: dict) -> dict:
    """:func:`run_method` in a fresh process (its own wall time and peak RSS; in this one where
    it may have no children: a daemonic worker of a Dask cluster)."""
    import torch

    return in_fresh_process(run_method, data, out, profile, overrides, torch.get_num_threads())


def run_method(data: str, out: str, profile: str, overrides: dict, threads: int) -> dict:
    """One registration in this (fresh) process: load, register, write; wall time and curve."""
    import torch

    torch.set_num_threads(threads)
    cfg = load_config(profile, overrides=overrides | {"threads": threads})
    t0 = time.perf_counter()
    curve: list[tuple[float, float]] = []
    scans = load_scans(data)
    Path(out).mkdir(parents=True, exist_ok=True)
    res = register(scans, cfg, checkpoint=Path(out) / "checkpoint.pt",
                   on_log=lambda row: curve.append((time.perf_counter() - t0, row["ate"])))
    written = write_run(Path(out), scans, res, {"data": data})
    wall = time.perf_counter() - t0
    curve.append((wall, res.metrics["ate"]))
    h = res.history or {}
    steps, train_s = (h.get("iteration") or [0])[-1], (h.get("time_s") or [0.0])[-1]
    return {"ate": res.metrics["ate"], "point_distance": res.metrics["point_distance"], "wall_s": wall,
            "num_scans": scans.num_scans, "epochs": (h.get("epoch") or [0])[-1], "steps": steps,
            "train_s": train_s, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "curve": curve, "profile": profile, "overrides": overrides, "threads": threads,
            "torch": torch.__version__, "run_files": sorted(Path(p).name for p in written)}


def simulate_to_disk(root: Path, t: int, poses: int) -> Path:
    """Trajectory ``t`` (map t % 3, seed t) of ``poses`` scans in the authors' layout under ``root``."""
    folder = root / f"traj{t}_K{poses}"
    if not (folder / "gt_pose.mat").exists():
        occ = procedural_indoor_map(t % 3)
        write_authors_layout(folder, simulate(occ, poses, seed=t), occ=occ)
    return folder


def prefix_copy(src: Path, dst: Path, k: int) -> Path:
    """The first k scans of an authors'-layout folder (for the scaling check)."""
    if not (dst / "gt_pose.mat").exists():
        dst.mkdir(parents=True, exist_ok=True)
        for i in range(k):
            shutil.copy(src / f"{i:03d}.pcd", dst / f"{i:03d}.pcd")
        savemat(dst / "gt_pose.mat", {"pose": loadmat(src / "gt_pose.mat")["pose"][:k]})
    return dst


# ---------------------------------------------------------------------------------- report


def time_to_reach(curve: list, threshold: float) -> float | None:
    """Earliest wall time from which every later ATE is <= threshold (None: not at the end)."""
    reached = None
    for t, ate in curve:
        if ate is None or ate > threshold:
            reached = None
        elif reached is None:
            reached = t
    return reached


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
             f"(ideal scanner); torch {meta['torch']}, {meta['threads']} torch thread(s) a run, each run in a fresh "
             f"process. Paper profile: {meta['paper_budget_s']:g} s training budget. Times are wall time from loading "
             "to the point from which the ATE stays below the threshold (n/N: reached on only n trajectories).", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, s in summary.items():
        n = s["n"]
        cells = [name, *[fmt_time(s[f"t{th:g}"], n) for th in THRESHOLDS],
                 f"{s['ate'][0]:.2f} / {s['ate'][1]:.2f}", f"{s['wall_s'][0]:.1f} / {s['wall_s'][1]:.1f}",
                 "-" if s["steps_per_s"] is None else f"{s['steps_per_s']:.1f}",
                 "-" if s["epochs_per_min"] is None else f"{s['epochs_per_min']:.1f}",
                 f"{s['peak_rss_mb'][0]:.0f} / {s['peak_rss_mb'][1]:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def scaling_line(scaling: dict) -> str:
    if not {"small", "big"} <= set(scaling):
        return ""
    small, big = scaling["small"], scaling["big"]
    return (f"Scaling (default profile, one trajectory, the first {small['num_scans']} scans vs all "
            f"{big['num_scans']}): wall {small['wall_s']:.1f} s vs {big['wall_s']:.1f} s "
            f"(x{big['wall_s'] / small['wall_s']:.2f}), ATE {small['ate']:.2f} vs {big['ate']:.2f} px, "
            f"peak RSS {small['peak_rss_mb']:.0f} vs {big['peak_rss_mb']:.0f} MB.")


def plot(results: dict[str, list[dict]], path: Path, budgets=(60, 120)) -> None:
    """ATE against wall time, one colour per method, one line per trajectory (a dot for ICP)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5))
    ax = fig.add_subplot()
    colors = dict(zip(results, [f"C{i}" for i in range(len(results))]))
    left = 0.8  # below it only where a run ended sooner (the quick size)
    for name, runs in results.items():
        for i, r in enumerate(runs):
            points = [(t, a) for t, a in r["curve"] if a is not None]
            if not points:
                continue
            t, a = zip(*points)
            left = min(left, 0.9 * (t[0] if r["steps"] else t[-1]))
            kw = {"color": colors[name], "label": name if i == 0 else None}
            if r["steps"]:
                ax.plot(t, a, lw=1, alpha=0.8, **kw)
            else:
                ax.plot(t[-1:], a[-1:], "o", ms=5, **kw)
    for th in THRESHOLDS[2:]:
        ax.axhline(th, color="grey", lw=0.6, ls=":")
    for budget in budgets:
        ax.axvline(budget, color="grey", lw=0.6, ls="--")
    ax.set(xlabel="wall time from loading (s)", ylabel="ATE (px)", yscale="log", xscale="log", xlim=(left, None),
           title="ATE against wall time (one line per trajectory)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    """The time-to-accuracy table (methods in the order of METHODS), the scaling line, the plot."""
    s = sizes(quick)
    rows = [r for r in results.values() if isinstance(r, dict) and r.get("method") in METHODS]
    by_method = {name: sorted((r for r in rows if r["method"] == name), key=lambda r: r["trajectory"])
                 for name in METHODS}
    by_method = {name: runs for name, runs in by_method.items() if runs}
    scaling = {r["scaling"]: r for r in results.values() if isinstance(r, dict) and "scaling" in r}
    sections = []
    if quick:
        trained = ", ".join(f"`{k}={v}`" for k, v in s["settings"].items())
        sections.append(f"Quick size: a smoke run, not a measurement ({s['poses']} scans; trained runs {trained}).")
    if by_method:
        threads = sorted({r.get("threads") for r in rows} - {None})
        meta = {"trajectories": len({r["trajectory"] for r in rows}), "poses": s["poses"],
                "paper_budget_s": s["paper_budget_s"], "torch": rows[0].get("torch", "?"),
                "threads": "/".join(map(str, threads)) or "?"}
        sections.append(table({name: summarize(runs) for name, runs in by_method.items()}, meta))
    else:
        sections.append("No finished run of a method yet.")
    if scaling_line(scaling):
        sections.append(scaling_line(scaling))
    if by_method:
        plot(by_method, Path(out) / FILE, budgets=(s["paper_budget_s"] / 2, s["paper_budget_s"]))
        sections.append(image(FILE, "ATE against wall time"))
    return write_report(out, "Speed: time to accuracy on simulated 2D trajectories", sections)
