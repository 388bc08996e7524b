"""The 1D example of supplementary D (Fig. 14): optimizing x directly vs through an MLP.

``deepmapping experiment 1d``. Minimize L(x) = x²/2 + 5 sin(10x) + 20 sin(x) (many local
minima; the global one is at x ≈ -1.417, L ≈ -23.76) in two ways, with the same plain gradient
descent (no momentum), learning rate 2e-4 and 1000 iterations, from the same start:

* directly on x, starting at x0;
* through an MLP x = f_θ(z), FC(10)-FC(20)-FC(30)-FC(40)-FC(1), ELU after every layer but the
  last, one input and one output node; θ and the scalar input z are updated jointly, and
  x0 = f_θ0(z0) (the supplementary's construction of a common start).

What the supplementary leaves open, and our choice: θ0 is PyTorch's default initialization of
``nn.Linear`` under ``torch.manual_seed(seed)``; z0 is a fixed value per run. z0 matters: the
MLP's step in x is lr·‖∂x/∂(θ, z)‖²·L'(x), and ‖∂x/∂θ‖ grows with |z| (the first layer's
weight gradients are proportional to z). At z0 = 1 the MLP's steps are about as small as the
direct ones and both settle in the local minimum next to x0; at z0 ≈ 30 the MLP jumps between
basins (a "wider search range", as the supplementary observes) and often ends lower. The
experiment therefore sweeps z0 and the seed and reports both. Everything is float64 and
deterministic from (seed, z0).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from deepmapping.experiments.base import Job
from deepmapping.experiments.report import image, markdown_table, save_figure, write_report

FUNC = "deepmapping.experiments.one_d:run_1d"
LR = 2e-4
ITERATIONS = 1000
WIDTHS = (10, 20, 30, 40)
X_RANGE = (-6.0, 6.0)  # the plotted domain of L(x)
TIE = 1e-6  # |L_mlp - L_gd| below this: the same minimum


def loss_np(x):
    x = np.asarray(x, dtype=float)
    return 0.5 * x**2 + 5.0 * np.sin(10.0 * x) + 20.0 * np.sin(x)


def _loss_torch(x):
    import torch

    return 0.5 * x**2 + 5.0 * torch.sin(10.0 * x) + 20.0 * torch.sin(x)


def global_minimum(lo: float = -20.0, hi: float = 20.0, n: int = 400001) -> tuple[float, float]:
    """(x, L(x)) of the global minimum, on a fine grid (outside [-20, 20] x²/2 dominates)."""
    xs = np.linspace(lo, hi, n)
    i = int(np.argmin(loss_np(xs)))
    return float(xs[i]), float(loss_np(xs[i]))


def jobs(quick: bool) -> list[Job]:
    """quick: z0 in {1, 30} x seeds 0-3 (8 runs, about 1 s each); full: z0 in {1, 3, 10, 30, 100}
    x seeds 0-19 (100 runs). Each run is the supplementary's full size (1000 iterations)."""
    z0s, seeds = ((1.0, 30.0), range(4)) if quick else ((1.0, 3.0, 10.0, 30.0, 100.0), range(20))
    return [Job(f"z0={z0:g}_seed={s}", FUNC, {"seed": s, "z0": z0, "keep_path": s < 4}) for z0 in z0s for s in seeds]


def run_1d(seed: int, z0: float, lr: float = LR, iterations: int = ITERATIONS, keep_path: bool = True) -> dict:
    """Plain gradient descent on x and on (θ, z) of x = f_θ(z), from x0 = f_θ0(z0)."""
    import torch
    from torch import nn

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        layers: list[nn.Module] = []
        prev = 1
        for w in WIDTHS:
            layers += [nn.Linear(prev, w), nn.ELU()]
            prev = w
        mlp = nn.Sequential(*layers, nn.Linear(prev, 1)).double()
    z = torch.tensor([[float(z0)]], dtype=torch.float64, requires_grad=True)
    params = [*mlp.parameters(), z]
    with torch.no_grad():
        x0 = float(mlp(z))

    # direct: x <- x - lr L'(x)
    x = torch.tensor(x0, dtype=torch.float64, requires_grad=True)
    gd_path = [x0]
    for _ in range(iterations):
        (g,) = torch.autograd.grad(_loss_torch(x), x)
        with torch.no_grad():
            x -= lr * g
        gd_path.append(float(x.detach()))

    # through the MLP: (θ, z) <- (θ, z) - lr ∇ L(f_θ(z)); x_t = f_θt(z_t) is where L is evaluated
    mlp_path = []
    for _ in range(iterations):
        xt = mlp(z)[0, 0]
        mlp_path.append(float(xt.detach()))
        grads = torch.autograd.grad(_loss_torch(xt), params)
        with torch.no_grad():
            for p, g in zip(params, grads):
                p -= lr * g
    with torch.no_grad():
        x_mlp = float(mlp(z))
        z_star = float(z)
        zs = torch.linspace(z_star - 6.0, z_star + 6.0, 241, dtype=torch.float64)[:, None]
        curve = _loss_torch(mlp(zs)[:, 0]).numpy()
    mlp_path.append(x_mlp)
    if not (math.isfinite(x_mlp) and math.isfinite(gd_path[-1])):
        raise FloatingPointError(f"diverged: x_gd={gd_path[-1]}, x_mlp={x_mlp}")
    out = {
        "seed": seed, "z0": float(z0), "lr": lr, "iterations": iterations, "x0": x0, "loss_x0": float(loss_np(x0)),
        "x_gd": gd_path[-1], "loss_gd": float(loss_np(gd_path[-1])),
        "x_mlp": x_mlp, "loss_mlp": float(loss_np(x_mlp)), "z_star": z_star,
        "range_gd": [min(gd_path), max(gd_path)], "range_mlp": [min(mlp_path), max(mlp_path)],
        "parameters": int(sum(p.numel() for p in mlp.parameters())),
    }
    if keep_path:
        out |= {"path_gd": gd_path, "path_mlp": mlp_path, "z_curve": [zs[0, 0].item(), zs[-1, 0].item()],
                "loss_of_f_star": curve.tolist()}
    return out


# ---------------------------------------------------------------------------------------- report


def outcome(r: dict) -> str:
    d = r["loss_mlp"] - r["loss_gd"]
    return "tie" if abs(d) <= TIE else "mlp lower" if d < 0 else "gd lower"


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    out = Path(out)
    xg, lg = global_minimum()
    sections = [
        "Supplementary D, Fig. 14: L(x) = x²/2 + 5 sin(10x) + 20 sin(x), plain gradient descent "
        f"(lr {LR:g}, {ITERATIONS} iterations) on x directly vs on θ and z of an MLP "
        "x = f_θ(z), FC(10)-FC(20)-FC(30)-FC(40)-FC(1) with ELU, from the same start x0 = f_θ0(z0). "
        f"Global minimum: x = {xg:.3f}, L = {lg:.2f}. θ0: PyTorch's default initialization from the seed; "
        "z0 is not given in the supplementary, so it is swept: it sets the MLP's effective step size "
        "(see the module docstring). Same sizes for quick and full runs per run (each about 1 s); full "
        "runs sweep more seeds and z0." + (" Quick run: 4 seeds, z0 in {1, 30}." if quick else "")
    ]
    if not results:
        sections.append("No finished runs.")
        return write_report(out, "1D example: gradient descent on x vs through an MLP", sections)
    by_z0: dict[float, list[dict]] = {}
    for r in results.values():
        by_z0.setdefault(r["z0"], []).append(r)
    summary = []
    for z0, runs in sorted(by_z0.items()):
        outs = [outcome(r) for r in runs]
        summary.append([f"{z0:g}", len(runs), outs.count("mlp lower"), outs.count("tie"), outs.count("gd lower"),
                        float(np.median([r["loss_gd"] for r in runs])), float(np.median([r["loss_mlp"] for r in runs])),
                        float(np.median([np.ptp(r["range_gd"]) for r in runs])),
                        float(np.median([np.ptp(r["range_mlp"]) for r in runs])),
                        sum(abs(r["x_mlp"] - xg) < 0.05 for r in runs), sum(abs(r["x_gd"] - xg) < 0.05 for r in runs)])
    sections.append("## Summary by z0\n\n" + markdown_table(
        ["z0", "runs", "MLP lower", "same minimum", "GD lower", "median L (GD)", "median L (MLP)",
         "median x range searched (GD)", "median x range searched (MLP)", "global min found (MLP)",
         "global min found (GD)"], summary))
    rows = [[r["z0"], r["seed"], r["x0"], r["x_gd"], r["loss_gd"], r["x_mlp"], r["loss_mlp"], r["z_star"], outcome(r)]
            for r in sorted(results.values(), key=lambda r: (r["z0"], r["seed"]))]
    sections.append("## The minima found, per run\n\n" + markdown_table(
        ["z0", "seed", "x0", "x* (GD)", "L (GD)", "x* (MLP)", "L (MLP)", "z*", "outcome"], rows))
    for z0, runs in sorted(by_z0.items()):
        shown = sorted((r for r in runs if "path_gd" in r), key=lambda r: r["seed"])[:4]
        if shown:
            pic = _figure(out / f"fig14_z0={z0:g}.png", z0, shown, xg, lg)
            sections.append(f"## z0 = {z0:g}\n\n" + image(pic.name, f"Fig. 14, z0 = {z0:g}"))
    return write_report(out, "1D example: gradient descent on x vs through an MLP", sections)


def _figure(path: Path, z0: float, runs: list[dict], xg: float, lg: float) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(runs), figsize=(4.2 * len(runs), 10.5), squeeze=False)
    for col, r in enumerate(runs):
        gd, mlp = np.asarray(r["path_gd"]), np.asarray(r["path_mlp"])
        lo = min(X_RANGE[0], gd.min(), r["x_mlp"]) - 0.2
        hi = max(X_RANGE[1], gd.max(), r["x_mlp"]) + 0.2
        ax = axes[0, col]
        xs = np.linspace(lo, hi, 4000)
        ax.plot(xs, loss_np(xs), "k-", lw=0.8, label="L(x)")
        inside = mlp[(mlp >= lo) & (mlp <= hi)]
        ax.plot(inside, loss_np(inside), "*", color="tab:green", ms=4, alpha=0.5,
                label=f"x during the MLP's iterations ({np.sum((mlp < lo) | (mlp > hi))} off the plot)")
        ax.plot(gd, loss_np(gd), "-", color="tab:cyan", lw=2, label="x during direct GD")
        ax.plot([r["x0"]], [r["loss_x0"]], "kx", ms=8, label="start x0")
        ax.plot([r["x_gd"]], [r["loss_gd"]], "o", color="tab:cyan", mec="k", ms=9, label="direct GD optimum")
        ax.plot([r["x_mlp"]], [r["loss_mlp"]], "o", mfc="none", mec="tab:red", mew=2, ms=11, label="MLP optimum x*")
        ax.plot([xg], [lg], "v", color="gray", ms=6, label="global minimum")
        ax.set_xlim(lo, hi)
        ax.set_xlabel("x")
        ax.set_title(f"seed {r['seed']}: L(GD) {r['loss_gd']:.2f}, L(MLP) {r['loss_mlp']:.2f}", fontsize=9)
        ax.grid(True, alpha=0.3)
        if col == 0:
            ax.set_ylabel("L(x)")
            ax.legend(fontsize=6, loc="upper center")
        ax = axes[1, col]
        z_lo, z_hi = r["z_curve"]
        zs = np.linspace(z_lo, z_hi, len(r["loss_of_f_star"]))
        ax.plot(zs, r["loss_of_f_star"], "--", color="tab:blue", label="L(f_θ*(z))")
        ax.plot([r["z_star"]], [r["loss_mlp"]], "+", color="tab:red", ms=12, mew=2, label="z*")
        ax.set_xlabel("z")
        ax.grid(True, alpha=0.3)
        if col == 0:
            ax.set_ylabel("L(f_θ*(z))")
            ax.legend(fontsize=7)
        ax = axes[2, col]
        ax.plot(loss_np(gd[:-1]), color="tab:cyan", label="direct GD")
        ax.plot(loss_np(mlp[:-1]), color="tab:green", lw=0.8, label="through the MLP")
        ax.axhline(lg, color="gray", ls=":", lw=1)
        ax.set_xlabel("iteration")
        ax.grid(True, alpha=0.3)
        if col == 0:
            ax.set_ylabel("L at the current x")
            ax.legend(fontsize=7)
    fig.suptitle(f"Supplementary D / Fig. 14, z0 = {z0:g} (lr {LR:g}, {ITERATIONS} iterations)", fontsize=11)
    fig.tight_layout()
    save_figure(fig, path)
    return path
