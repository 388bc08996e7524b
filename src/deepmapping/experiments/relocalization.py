"""Re-localization with the "trained" L-Net (§4.1, "Generalization of L-Net", Fig. 7).

``deepmapping experiment relocalization``: register a simulated 2D trajectory with
DeepMapping, then simulate a scan at every cell of a grid of free positions and feed it to the
trained L-Net (``Result.localize``). The error of the pose it returns, against the true pose of
that scan, is drawn as a colour image over the map with the training trajectory on it; a table
gives the median errors near and far from the trajectory.

What the L-Net is given. In the paper the L-Net is a function of the scan alone, so it can
place a scan with no prior. The default profile's L-Net refines a warm start
(T = T_init ∘ f(S, T_init)), which a new scan does not have. This experiment therefore
registers from a **cold start** (``warm_start.method = "none"``: T_init = identity for every
scan) with a **scan-only L-Net** (``lnet.pose_input_freqs = 0``): T = f(S), the paper's
formulation, and a new scan is localized with the same identity prior (``localize(points,
valid)`` with ``init=None``). Three changes to the default profile make the cold start
converge: the L-Net learns at the full rate (``lnet.lr_factor = 1``; the default's 0.1 is for
small corrections of a warm start), the M-Net's Fourier bands open coarse to fine over the
first half (``mnet.coarse_to_fine = 0.5``), and the Chamfer term between temporal neighbours
weighs more and reaches two scans on each side (``loss.chamfer_weight = 50``,
``loss.chamfer_window = 2``; measured on 32-pose trajectories: ATE 1.2 / 1.8 px instead of
18 / 22 px with the default λ = 10, w = 1). The rest is the default profile (standardized
L-Net features, Fourier M-Net, 64 beams per scan per step).

Trajectory length. With these settings the cold start registers short trajectories reliably
(32 poses: 6 of 6 tried, ATE 0.9-1.8 px), 64 poses sometimes (on 512 px maps 2 of 5 under
20 px, 2.3 and 13.5 px; the others 35-81 px), and long ones not at all: 128 poses on a 512 px
map ended at 162 px after 1000 epochs; 256 poses on a 1024 px map stayed at the identity's
~220 px (800 epochs with λ = 10, w = 1; still 216 px after 350 epochs with λ = 50, w = 2).
The full run therefore uses 32- and 64-pose trajectories, not the paper's 256 poses, and the report separates
the L-Nets whose registration succeeded (ATE < 20 px): one
that did not register its own trajectory says nothing about re-localization.

Frames. The registered frame is arbitrary (cold start), so the registered trajectory is
aligned rigidly to the ground truth (positions, as for the ATE) and that one transform is
applied to every re-localized pose before its error is measured: errors are in px of the map,
and include the registration's own error (its ATE is the floor near the trajectory).

Headings of the grid scans: ``nearest`` = the heading of the nearest training pose (the
paper: re-localization works "close to the training trajectory and [with] a similar
orientation"), ``random`` = uniform in [-180°, 180°), drawn from the run's seed.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from deepmapping.api import register
from deepmapping.config import load_config, profile_changes
from deepmapping.evaluation.metrics import SUCCESS_PX
from deepmapping.experiments.base import Job
from deepmapping.experiments.report import image, markdown_table, save_figure, write_report
from deepmapping.geometry import se2
from deepmapping.geometry.alignment import align_poses_2d
from deepmapping.sim.dataset import PX_SCALE, simulate
from deepmapping.sim.maps import procedural_indoor_map
from deepmapping.sim.scanner import simulate_scans
from deepmapping.sim.trajectory import clearance_map

FUNC = "deepmapping.experiments.relocalization:relocalize"
# cold start + scan-only L-Net: the default profile with these changes (profiles/relocalization.yaml,
# see the module docstring)
PROFILE = "relocalization"
OVERRIDES = profile_changes(PROFILE)
HEADINGS = ("nearest", "random")
BINS = ((0.0, 16.0), (16.0, 64.0), (64.0, float("inf")))  # distance to the trajectory (px)
SIMILAR_DEG = 30.0  # "similar orientation": within this of the nearest training pose's heading


def jobs(quick: bool) -> list[Job]:
    """quick: one 32-pose trajectory on a 256 px map, 128 beams, 250 epochs, 8 px grid (a smoke
    test, about 20 s on one core). full: three trajectories of 32 poses (500 epochs) and three
    of 64 poses (1000 epochs) on one 512 px map, 256 beams, 4 px grid: six L-Nets (Fig. 7 shows
    two), about 1.5 and 3.5 min each on one core. Not 256 poses: a cold start does not register
    trajectories that long (module docstring)."""
    if quick:
        specs = [dict(map_seed=1, map_size=256, traj_seed=2, num_poses=32, num_beams=128, epochs=250, grid_step=8)]
    else:
        specs = [dict(map_seed=0, map_size=512, traj_seed=t, num_poses=k, num_beams=256, epochs=epochs, grid_step=4)
                 for k, epochs in ((32, 500), (64, 1000)) for t in (1, 2, 3)]
    return [Job(f"map{s['map_seed']}_traj{s['traj_seed']}_K{s['num_poses']}", FUNC, s) for s in specs]


def relocalize(map_seed: int, map_size: int, traj_seed: int, num_poses: int, num_beams: int, epochs: int,
               grid_step: int, headings: tuple | list = HEADINGS, clearance_px: float = 3.0, seed: int = 0,
               overrides: dict | None = None) -> dict:
    """Register one simulated trajectory from a cold start, then re-localize a scan taken at
    every free cell of a ``grid_step`` px grid (cell centres, at least ``clearance_px`` from
    walls) with the trained L-Net. Everything is drawn from the seeds; returns a JSON-able dict
    (grids as row lists, null where a cell is not free; errors in px and degrees)."""
    from scipy.spatial import cKDTree

    t0 = time.perf_counter()
    occ = procedural_indoor_map(map_seed, map_size)
    scans = simulate(occ, num_poses, seed=traj_seed, num_beams=num_beams)
    cfg = load_config(PROFILE, overrides={"optim.epochs": epochs, "seed": seed} | (overrides or {}))
    result = register(scans, cfg)
    t_reg = time.perf_counter() - t0
    gt_px = scans.gt_poses * [PX_SCALE, PX_SCALE, 1.0]
    _, (rot, t) = align_poses_2d(result.poses, scans.gt_poses, return_transform=True)
    to_gt = np.array([t[0], t[1], np.arctan2(rot[1, 0], rot[0, 0])])  # registered frame -> ground truth frame

    def errors(localized: np.ndarray, truth_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        est = se2.compose(to_gt, localized) * [PX_SCALE, PX_SCALE, 1.0]
        return (np.linalg.norm(est[:, :2] - truth_px[:, :2], axis=1),
                np.degrees(np.abs(se2.wrap_angle(est[:, 2] - truth_px[:, 2]))))

    # the training scans themselves: the L-Net must give back the registered poses
    again = result.localize(scans.points, scans.valid)
    train_dev = np.linalg.norm(again[:, :2] - result.poses[:, :2], axis=1) * PX_SCALE

    # grid of free cell centres
    t1 = time.perf_counter()
    cells = np.arange(grid_step / 2.0, map_size, grid_step)
    gx, gy = np.meshgrid(cells, cells)  # rows: y, columns: x
    clear = clearance_map(occ)[gy.astype(int), gx.astype(int)] >= clearance_px
    xy = np.stack([gx[clear], gy[clear]], axis=1)
    dist, nearest = cKDTree(gt_px[:, :2]).query(xy)
    rng = np.random.default_rng([seed, traj_seed, 4242])
    shape = gx.shape
    out_grid: dict = {"shape": list(shape), "step_px": grid_step, "first_px": float(cells[0]),
                      "distance_px": _grid(dist, clear, shape, 1)}
    summary: dict = {}
    for mode in headings:
        if mode == "nearest":
            theta = gt_px[nearest, 2]
        elif mode == "random":
            theta = rng.uniform(-np.pi, np.pi, len(xy))
        else:
            raise ValueError(f"unknown heading mode {mode!r} (nearest, random)")
        truth = np.column_stack([xy, theta])
        localized = np.concatenate([_localize_at(result.localize, occ, truth[i : i + 4096], num_beams)
                                    for i in range(0, len(truth), 4096)])
        te, re = errors(localized, truth)
        dtheta = np.degrees(np.abs(se2.wrap_angle(theta - gt_px[nearest, 2])))
        out_grid[mode] = {"translation_px": _grid(te, clear, shape, 2), "rotation_deg": _grid(re, clear, shape, 2),
                          "heading_offset_deg": _grid(dtheta, clear, shape, 1)}
        summary[mode] = {"median_translation_px": float(np.median(te)), "median_rotation_deg": float(np.median(re)),
                         "n": int(len(te))}
    t_grid = time.perf_counter() - t1
    aligned = se2.compose(to_gt, result.poses) * [PX_SCALE, PX_SCALE, 1.0]
    return {
        "map_seed": map_seed, "map_size": map_size, "traj_seed": traj_seed, "num_poses": num_poses,
        "num_beams": num_beams, "epochs": epochs, "seed": seed, "overrides": OVERRIDES | (overrides or {}),
        "headings": list(headings), "clearance_px": clearance_px,
        "ate_px": float(result.metrics["ate"]), "rotation_rmse_deg": _maybe(result.metrics, "rotation_rmse_deg"),
        "gt_px": np.round(gt_px, 3).tolist(), "registered_px": np.round(aligned, 3).tolist(),
        "training_scans_px": {"median": float(np.median(train_dev)), "max": float(train_dev.max())},
        "grid": out_grid, "summary": summary,
        "register_s": t_reg, "grid_s": t_grid, "cells": int(clear.sum()),
    }


def _localize_at(localize, occ: np.ndarray, poses_px: np.ndarray, num_beams: int) -> np.ndarray:
    """Scan from ``poses_px`` and localize the scans (in chunks: bounded memory on big grids)."""
    pts, valid = simulate_scans(occ, poses_px, num_beams=num_beams)
    return localize(pts / PX_SCALE, valid)


def _maybe(metrics: dict, key: str):
    v = metrics.get(key)
    return float(v) if isinstance(v, (int, float)) else None


def _grid(values: np.ndarray, mask: np.ndarray, shape, digits: int) -> list:
    """Values at the masked cells -> rows of a 2D list, None elsewhere (JSON null)."""
    full = np.full(shape, np.nan)
    full[mask] = np.round(values, digits)
    return [[None if np.isnan(v) else float(v) for v in row] for row in full]


def _array(rows) -> np.ndarray:
    return np.array([[np.nan if v is None else v for v in row] for row in rows], dtype=float)


# ---------------------------------------------------------------------------------------- report


def report(out: Path, results: dict[str, dict], quick: bool) -> Path:
    out = Path(out)
    title = "Re-localization with the trained L-Net"
    sections = [
        "§4.1 \"Generalization of L-Net\" / Fig. 7: after registering a trajectory, a scan is simulated at "
        "every free cell of a grid and the trained L-Net estimates its pose. Registration from a cold start "
        "with a scan-only L-Net (T = f(S), as the paper; profile `relocalization`: the default one with "
        + ", ".join(f"`{k}={v}`" for k, v in OVERRIDES.items())
        + "); new scans are localized with no prior. Errors are against the true pose, after aligning the "
        "registered trajectory rigidly to the ground truth. Grid headings: `nearest` = the heading of the "
        "nearest training pose, `random` = uniform. Colour: black is better (as Fig. 7); cyan: the training "
        f"trajectory. A registration counts as successful when its ATE is under {SUCCESS_PX:g} px (supplementary "
        "B); an L-Net that did not register its own trajectory says little about re-localization, so the "
        "pooled table uses the successful ones only." + (" Quick sizes: a smoke test, not the paper's setting."
                                                         if quick else "")
    ]
    if not results:
        sections.append("No finished runs.")
        return write_report(out, title, sections)
    runs, rows, pictures = [], [], []
    pooled: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]] = {}
    for key, r in sorted(results.items()):
        try:
            picture = _error_map(out / f"{key}_error_map.png", key, r)
            ok = r["ate_px"] < SUCCESS_PX
            dist = _array(r["grid"]["distance_px"])
            for mode in r["headings"]:
                te = _array(r["grid"][mode]["translation_px"])
                re = _array(r["grid"][mode]["rotation_deg"])
                off = _array(r["grid"][mode]["heading_offset_deg"])
                for label, sel in _bins(dist, off, mode):
                    rows.append([key if ok else f"{key} (registration failed)", mode, label, *_stats(te[sel], re[sel])])
                    if ok:
                        pooled.setdefault((mode, label), []).append((te[sel], re[sel]))
        except (KeyError, TypeError, ValueError) as exc:  # a damaged result must not take the report down
            sections.append(f"`{key}`: unreadable result ({type(exc).__name__}: {exc})")
            continue
        runs.append([key, r["num_poses"], r["map_size"], r["epochs"], r["ate_px"], "yes" if ok else "no",
                     r["training_scans_px"]["max"], r["cells"], r["register_s"], r["grid_s"]])
        pictures.append(f"## {key}\n\n" + image(picture.name, f"re-localization errors, {key}"))
    headers = ["heading", "distance to the trajectory", "cells", "median translation error (px)",
               "median rotation error (deg)", f"% under {SUCCESS_PX:g} px"]
    sections.append("## Runs\n\n" + markdown_table(
        ["run", "poses", "map (px)", "epochs", "ATE of the registration (px)", "registered",
         "training scans: localize vs registered, max (px)", "grid cells", "register (s)", "grid (s)"], runs))
    n_ok = sum(row[5] == "yes" for row in runs)
    pooled_rows = [[mode, label, *_stats(np.concatenate([t for t, _ in v]), np.concatenate([q for _, q in v]))]
                   for (mode, label), v in pooled.items()]
    sections.append(f"## Pooled over the {n_ok} successful registration(s) of {len(runs)}\n\n"
                    + (markdown_table(headers, pooled_rows) if pooled_rows else "None succeeded."))
    sections.append("## Per run\n\n" + markdown_table(["run", *headers], rows))
    curve = _error_vs_distance(out / "error_vs_distance.png", results)
    if curve is not None:
        sections.append(image(curve.name, "median error against distance to the trajectory"))
    return write_report(out, title, sections + pictures)


def _stats(te: np.ndarray, re: np.ndarray) -> list:
    n = int(te.size)
    if n == 0:
        return [0, float("nan"), float("nan"), float("nan")]
    return [n, float(np.median(te)), float(np.median(re)), 100.0 * float((te < SUCCESS_PX).mean())]


def _bins(dist: np.ndarray, off: np.ndarray, mode: str):
    free = np.isfinite(dist)
    for lo, hi in BINS:
        label = f"{lo:g}–{hi:g} px" if np.isfinite(hi) else f"≥ {lo:g} px"
        yield label, free & (dist >= lo) & (dist < hi)
    if mode == "random":  # the paper's condition: close to the trajectory with a similar orientation
        lo, hi = BINS[0]
        yield (f"< {hi:g} px, heading within {SIMILAR_DEG:g}°", free & (dist < hi) & (off < SIMILAR_DEG))
    yield "all", free


def _error_map(path: Path, key: str, r: dict) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    occ = procedural_indoor_map(r["map_seed"], r["map_size"])  # deterministic: redrawn, not stored
    size, g = r["map_size"], r["grid"]
    step = g["step_px"]
    half = step / 2.0
    extent = (g["first_px"] - half, g["first_px"] - half + g["shape"][1] * step,
              g["first_px"] - half + g["shape"][0] * step, g["first_px"] - half)
    gt = np.asarray(r["gt_px"])
    modes = r["headings"]
    fig, axes = plt.subplots(len(modes), 2, figsize=(10, 4.6 * len(modes)), squeeze=False)
    for row, mode in zip(axes, modes):
        for ax, name, vmax, unit in ((row[0], "translation_px", size / 2.0, "px"), (row[1], "rotation_deg", 180.0, "deg")):
            err = np.ma.masked_invalid(np.clip(_array(g[mode][name]), 1.0, None))  # log scale from 1 px / 1 deg
            ax.imshow(np.where(occ >= 128, 1.0, 0.55), cmap="gray", vmin=0, vmax=1, extent=(0, size, size, 0))
            im = ax.imshow(err, cmap="inferno", norm=LogNorm(1.0, vmax), extent=extent, interpolation="nearest")
            ax.plot(gt[:, 0], gt[:, 1], ".", color="cyan", ms=2.5)
            ax.set_xlim(0, size)
            ax.set_ylim(size, 0)
            ax.set_xticks([])
            ax.set_yticks([])
            what = "translation" if unit == "px" else "rotation"
            ax.set_title(f"{mode} heading: {what} error ({unit})", fontsize=10)
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, extend="max")
    fig.suptitle(f"{key}: L-Net re-localization (ATE of the registration {r['ate_px']:.1f} px)", fontsize=11)
    fig.tight_layout()
    save_figure(fig, path)
    return path


def _error_vs_distance(path: Path, results: dict[str, dict]) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    drawn = False
    for i, (key, r) in enumerate(sorted(results.items())):
        try:
            dist = _array(r["grid"]["distance_px"])
            edges = np.arange(0.0, np.nanmax(dist) + r["grid"]["step_px"], r["grid"]["step_px"] * 2)
            for mode in r["headings"]:
                te = _array(r["grid"][mode]["translation_px"])
                mids, med = [], []
                for lo, hi in zip(edges[:-1], edges[1:]):
                    sel = np.isfinite(dist) & (dist >= lo) & (dist < hi)
                    if sel.sum() >= 3:
                        mids.append((lo + hi) / 2)
                        med.append(np.median(te[sel]))
                failed = r["ate_px"] >= SUCCESS_PX  # colour: the run; line: the heading; faint: failed
                ax.plot(mids, med, "-" if mode == "nearest" else "--", marker="o", ms=2.5, color=f"C{i % 10}",
                        alpha=0.35 if failed else 1.0, lw=1.0 if failed else 1.5,
                        label=f"{key}, {mode} heading" + (" (registration failed)" if failed else ""))
                drawn = True
        except (KeyError, TypeError, ValueError):
            continue
    if not drawn:
        plt.close(fig)
        return None
    ax.axhline(SUCCESS_PX, color="gray", ls=":", lw=1)
    ax.set_xlabel("distance to the training trajectory (px)")
    ax.set_ylabel("median translation error (px)")
    ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=6, loc="lower right", ncol=2)
    fig.tight_layout()
    save_figure(fig, path)
    return path
