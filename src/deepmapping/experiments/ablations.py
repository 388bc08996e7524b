"""``deepmapping experiment ablations`` (supplementary A, Figs. 10-13): network architectures.

L-Net feature extractor (CNN vs PointNet), M-Net architecture (MLP vs ResMLP), M-Net depth
(4-7 hidden layers of width 64) and width (32-128 at depth 4), each registering the same
simulated 2D trajectories with the paper's networks and loss (profile ``paper``: atrous-CNN
L-Net, MLP M-Net, lambda = 10, Adam lr 1e-3 constant) at a feasible cost (BASE: fewer epochs,
a random subset of beams per step, fewer free-space samples; the same for every variant).

The supplementary ran these ablations on the AVD (box plots of the final ATE); here they run
on simulated 2D trajectories (trajectory ``t``: procedural map ``t % 3``, seed ``1000 + t``,
as ``warm_start``), with the ATE logged during the optimization. Depth = the number of hidden
FC layers (each with a ReLU) before the output FC(1); the paper's M-Net
FC(64)-FC(512)-FC(512)-FC(256)-FC(128)-FC(1) has depth 5.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from deepmapping.config import load_config
from deepmapping.experiments.base import Job
from deepmapping.experiments.report import image, markdown_table, runs_by, summary, write_report
from deepmapping.experiments.warm_start import curve_plot, registration_curve, trajectory_2d

PROFILE = "paper"
# the same for every variant: the paper's networks and loss at a feasible cost
BASE = {"warm_start.method": "none", "loss.beams_per_scan": 64, "loss.free_samples": 4, "optim.batch_size": 32}
VARIANTS: dict[str, dict] = {  # name -> overrides on top of PROFILE + BASE
    "paper": {},  # CNN L-Net C(64)-C(128)-C(1024), MLP M-Net FC(64)-FC(512)-FC(512)-FC(256)-FC(128)
    "pointnet": {"lnet.extractor": "pointnet"},  # FC(64)-FC(128)-FC(256)-FC(1024) per point
    "resmlp": {"mnet.kind": "resmlp", "mnet.hidden": [64, 64, 64, 128, 128]},  # RB(64)x3-RB(128)x2
    **{f"depth{d}-width64": {"mnet.hidden": [64] * d} for d in (4, 5, 6, 7)},
    **{f"depth4-width{w}": {"mnet.hidden": [w] * 4} for w in (32, 96, 128)},
}
GROUPS: dict[str, tuple[str, dict[str, str]]] = {  # name -> (title, {label: variant})
    "lnet": ("L-Net feature extractor (cf. Fig. 10)", {"CNN (paper)": "paper", "PointNet": "pointnet"}),
    "mnet": ("M-Net architecture (cf. Fig. 11)", {"MLP (paper)": "paper", "ResMLP": "resmlp"}),
    "depth": ("M-Net depth, width 64 (cf. Fig. 12)", {f"depth {d}": f"depth{d}-width64" for d in (4, 5, 6, 7)}),
    "width": ("M-Net width, depth 4 (cf. Fig. 13)", {f"width {w}": f"depth4-width{w}" for w in (32, 64, 96, 128)}),
}
FULL = {"trajectories": [1, 2, 3, 4, 5], "poses": 32, "beams": 256, "epochs": 300, "eval_every": 10}
QUICK = {"trajectories": [1], "poses": 16, "beams": 64, "epochs": 6, "eval_every": 2}


def sizes(quick: bool) -> dict:
    return dict(QUICK if quick else FULL)


def jobs(quick: bool) -> list[Job]:
    s = sizes(quick)
    kw = {k: s[k] for k in ("poses", "beams", "epochs", "eval_every")}
    return [Job(f"traj{t}-{v}", "deepmapping.experiments.ablations:run", {"trajectory": t, "variant": v} | kw)
            for t in s["trajectories"] for v in VARIANTS]


def variant_overrides(variant: str) -> dict:
    """PROFILE overrides of ``variant`` (BASE, then the variant's own)."""
    return BASE | VARIANTS[variant]


def run(trajectory: int, variant: str, poses: int, beams: int, epochs: int, eval_every: int, seed: int = 0) -> dict:
    """DeepMapping with architecture ``variant`` on simulated 2D trajectory ``trajectory``."""
    import torch

    from deepmapping.solver.model import DeepMappingModel

    scans = trajectory_2d(trajectory, poses, beams)
    overrides = variant_overrides(variant) | {"optim.epochs": epochs, "optim.eval_every": eval_every, "seed": seed}
    cfg = load_config(PROFILE, overrides=overrides)
    model = DeepMappingModel(cfg, torch.zeros(1, 8, 2), torch.zeros(1, 3))
    params = {"lnet_params": sum(p.numel() for p in model.lnet.parameters()),
              "mnet_params": sum(p.numel() for p in model.mnet.parameters())}
    return registration_curve(scans, PROFILE, overrides) | params | {
        "trajectory": trajectory, "variant": variant, "poses": poses, "beams": beams}


# -- report --------------------------------------------------------------------------------


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    s = sizes(quick)
    by_variant = runs_by(results, "variant", VARIANTS)
    n = len(s["trajectories"])
    sections = [
        f"{'Quick smoke run (not the paper sizes): ' if quick else ''}{n} simulated 2D "
        f"trajector{'y' if n == 1 else 'ies'} ({', '.join(map(str, s['trajectories']))}) "
        f"of {s['poses']} poses x {s['beams']} beams "
        f"(trajectory t on procedural map t % 3), DeepMapping from a cold start (identity poses, as the paper), "
        f"{s['epochs']} epochs, ATE logged every {s['eval_every']} epochs.",
        f"Settings: profile `{PROFILE}` (the paper's networks and loss: atrous-CNN L-Net "
        "C(64)-C(128)-C(1024)-M-FC(512)-FC(256)-FC(3), MLP M-Net FC(64)-FC(512)-FC(512)-FC(256)-FC(128)-FC(1), "
        "lambda = 10, Adam lr 1e-3 constant), not our fast `default` profile (Fourier-feature M-Net, warm start), "
        f"with these changes for every variant to keep the cost feasible on CPUs: "
        f"{', '.join(f'`{k}={v}`' for k, v in BASE.items())}, and {s['epochs']} epochs instead of 3000. "
        "The supplementary ran the ablations on the AVD (final ATE box plots); these run on 2D scans. "
        "Depth = hidden FC layers before the output FC(1) (the paper's M-Net has depth 5); ResMLP = "
        "RB(64)-RB(64)-RB(64)-RB(128)-RB(128), RB(n) two FC(n) layers with a skip connection "
        "(`mnet.kind resmlp`).",
    ]
    rows = []
    for g, (title, members) in GROUPS.items():
        curve_plot(out / f"ablation_{g}.png", {label: by_variant[v] for label, v in members.items()}, title)
        sections.append(f"## {title}\n\n" + image(f"ablation_{g}.png", title))
        for label, v in members.items():
            runs = by_variant[v]
            final = summary([r["final_ate"] for r in runs])
            best = summary([_best(r["ate"]) for r in runs])
            late = summary([_late(r["ate"]) for r in runs])
            nets = f"{runs[0]['lnet_params']:,} / {runs[0]['mnet_params']:,}" if runs else "-"
            rows.append([title.split(" (")[0], label, f"{len(runs)}/{n}",
                         summary([r["init_ate"] for r in runs])["median"], final["median"], final["mean"],
                         late["median"], best["median"], nets, summary([r["runtime_s"] for r in runs])["mean"]])
    table = markdown_table(["ablation", "variant", "runs", "start ATE (px, median)", "final ATE (px, median)",
                            "final ATE (px, mean)", "end ATE (px, median; a run's = median of its last 5 logs)",
                            "lowest ATE on the way (px, median)", "parameters (L-Net / M-Net)",
                            "runtime (s, mean)"], rows)
    sections.insert(2, "## Final ATE\n\n" + table)
    return write_report(out, "Ablations (supplementary A, Figs. 10-13)", sections)


def _late(ate: list, n: int = 5) -> float:
    """The median of the last ``n`` logged ATEs: the end of a run, less the noise of its last step
    (the paper's constant learning rate leaves the poses moving)."""
    v = [x for x in ate[-n:] if x is not None and np.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def _best(ate: list) -> float:
    v = [x for x in ate if x is not None and np.isfinite(x)]
    return float(min(v)) if v else math.nan
