"""``deepmapping experiment robustness``: "less sensitive to initialization than ICP", measured.

Registration made harder step by step: only every ``stride``-th scan of the paper's 256-pose
trajectories is kept (stride 2, 4, 8, 12, 16), so that the steps and turns between consecutive
scans grow with the stride. Each method registers each thinned trajectory from no initial
poses: cold DeepMapping and cold direct optimization (profile ``cold``: the curriculum, no
classical registration), incremental ICP (point-to-point, point-to-plane), Go-ICP and PSO
(pairwise, time-matched as in the 2D suite). One run is :func:`exp_2d.run_trajectory` with a
stride. Report: success (ATE < 20 px) and median ATE against the stride, with the median step
and turn between consecutive scans at each stride.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from deepmapping.evaluation.metrics import SUCCESS_PX
from deepmapping.experiments import report as rep
from deepmapping.experiments.base import QUICK_CURRICULUM, Job
from deepmapping.experiments.exp_2d import BUDGET_S_PER_POSE, COLD, run_trajectory
from deepmapping.experiments.report import save_figure
from deepmapping.geometry import se2
from deepmapping.sim.dataset import paper_trajectory

METHODS = ("deepmapping-cold", "direct-cold", "icp-point", "icp-plane", "goicp", "pso")
TIME_MATCHED = ("goicp", "pso")
COLORS = {"deepmapping-cold": "tab:red", "direct-cold": "tab:orange", "icp-point": "tab:blue",
          "icp-plane": "tab:green", "goicp": "tab:purple", "pso": "tab:brown"}
FULL = {"trajectories": tuple(range(50, 60)), "strides": (2, 4, 8, 12, 16), "num_beams": 256, "epochs": None}
QUICK = {"trajectories": (50,), "strides": (4, 16), "num_beams": 64, "epochs": 20}  # cold rows: QUICK_CURRICULUM
QUICK_BUDGET_S = 2.0


def sizes(quick: bool) -> dict:
    return dict(QUICK if quick else FULL)


def jobs(quick: bool) -> list[Job]:
    """One job per (method, trajectory, stride)."""
    s = sizes(quick)
    out = []
    for t in s["trajectories"]:
        for stride in s["strides"]:
            k = math.ceil(256 / stride)
            budget = QUICK_BUDGET_S if quick else BUDGET_S_PER_POSE * k
            for method in METHODS:
                kwargs = {"trajectory": t, "method": method, "num_beams": s["num_beams"], "epochs": s["epochs"],
                          "stride": stride, "seed": 0, "time_budget_s": budget if method in TIME_MATCHED else None}
                if quick and method in COLD:
                    kwargs["cold_overrides"] = QUICK_CURRICULUM
                out.append(Job(f"{method}-t{t:02d}-s{stride:02d}", "deepmapping.experiments.robustness:run",
                               kwargs))
    return out


def run(trajectory: int, method: str, stride: int, num_beams: int = 256, epochs: int | None = None,
        time_budget_s: float | None = None, seed: int = 0, cold_overrides: dict | None = None) -> dict:
    """One thinned trajectory registered by one method: exp_2d's row, the stride, and the
    median step (px) and turn (deg) between consecutive kept scans; ``cold_overrides``: settings added
    to the cold rows' (quick runs)."""
    row = run_trajectory(trajectory, method, num_beams=num_beams, epochs=epochs, time_budget_s=time_budget_s,
                         seed=seed, stride=stride, cold_overrides=cold_overrides)
    gt = paper_trajectory(trajectory, num_beams=8).gt_poses[::stride]
    rel = se2.relative(gt[:-1], gt[1:])
    return row | {"stride": stride, "median_step_px": float(np.median(np.hypot(rel[:, 0], rel[:, 1])) * 512),
                  "median_turn_deg": float(np.degrees(np.median(np.abs(rel[:, 2]))))}


# ---------------------------------------------------------------------------------- report


def table(results: dict[str, dict], strides) -> tuple[list[str], list[list], dict]:
    """Rows per stride: the data's median step and turn, then success and median ATE per method."""
    rows, success = [], {m: [] for m in METHODS}
    for stride in strides:
        at = [r for r in results.values() if isinstance(r, dict) and r.get("stride") == stride]
        if not at:
            continue
        row = [stride, float(np.median([r["median_step_px"] for r in at])),
               float(np.median([r["median_turn_deg"] for r in at]))]
        for m in METHODS:
            runs = [r for r in at if r.get("method") == m]
            rate = float(np.mean([r["ate"] < SUCCESS_PX for r in runs])) if runs else float("nan")
            med = float(np.median([r["ate"] for r in runs])) if runs else float("nan")
            success[m].append((stride, rate))
            row.append("-" if not runs else f"{100 * rate:.0f} % ({len(runs)}), {med:.3g} px")
        rows.append(row)
    headers = ["stride", "median step (px)", "median turn (deg)", *METHODS]
    return headers, rows, success


def plot(path: Path, success: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for m, pts in success.items():
        pts = [(s, r) for s, r in pts if math.isfinite(r)]
        if pts:
            ax.plot(*zip(*pts), "o-", color=COLORS[m], label=m)
    ax.set_xlabel("stride (every n-th scan kept)")
    ax.set_ylabel(f"success (ATE < {SUCCESS_PX:g} px)")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    ax.legend()
    save_figure(fig, path)


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    s = sizes(quick)
    headers, rows, success = table(results, s["strides"])
    expected = len(s["trajectories"]) * len(s["strides"]) * len(METHODS)
    sections = [
        f"Every stride-th scan of the paper's 256-pose trajectories {s['trajectories'][0]}–{s['trajectories'][-1]} "
        f"({s['num_beams']} beams), registered from no initial poses. {len(results)} of {expected} runs finished. "
        f"Cells: success (ATE < {SUCCESS_PX:g} px, runs), median ATE. deepmapping-cold and direct-cold: profile "
        "`cold` (curriculum, no classical registration); goicp and pso: pairwise, time-matched "
        "(0.5 s per pose); icp-point and icp-plane: incremental ICP from the constant-velocity guess."
        + (" Quick size: checks that the experiment runs, not the claim." if quick else ""),
        "## Success against difficulty\n\n" + rep.markdown_table(headers, rows),
    ]
    if rows:
        plot(out / "success.png", success)
        sections.append(rep.image("success.png", "success rate against the stride"))
    else:
        (out / "success.png").unlink(missing_ok=True)
        sections.append("No finished run to plot.")
    return rep.write_report(out, "Robustness to large motions: cold DeepMapping against ICP, Go-ICP, PSO", sections)
