"""Probe the cold-start curriculum's placements (docs/method.md, "Larger motions" and "Cold start
on depth images"): the measurements that decide its settings, a few minutes each.

    .venv/bin/python benchmarks/cold_placements.py robustness --trajectories 50,51,52,53,54 --stride 8 --why
    .venv/bin/python benchmarks/cold_placements.py robustness --stride 8 \\
        --set curriculum.refine_top=8 --set curriculum.max_turn_deg=60 --set curriculum.hypotheses=64
    .venv/bin/python benchmarks/cold_placements.py avd --trajectories 0,1,2 --set curriculum.select_truncate=0.05
    .venv/bin/python benchmarks/cold_placements.py avd --trajectories 20,21,22,23 --depth-noise

``robustness``: every ``stride``-th scan of the paper's 256-pose trajectories, profile ``cold``,
one epoch after the curriculum: the ATE of the placements alone (what the 250 epochs start from;
a failure there is a failure at the end). ``avd``: AVD-like depth images (``experiment avd``'s
trajectories), profile ``default-3d`` from the identity with the curriculum on and the
experiment's Chamfer weight, all epochs: ATE and rotation RMSE of the result and of the
placements. One torch thread; prints one line per trajectory.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import yaml


def _overrides(sets: list[str]) -> dict:
    out = {}
    for s in sets:
        key, _, value = s.partition("=")
        out[key] = yaml.safe_load(value)
    return out


def explain_placements(gt: np.ndarray, unit: float, log: list, first_scan: np.ndarray) -> None:
    """Wrap curriculum.place_new_scan: after each placement, append (scan, error px, error deg,
    loss of the chosen placement, loss of the true one relative to the placed predecessor, then
    eq. 4 alone, the Chamfer distance alone and the weighted free-space check (0 when off), each for
    the chosen and the true placement; then how far the truth lies from the nearer of the search's
    two centres, in the new scan's median ranges, and how far it turned, in degrees).
    Placements live in the model's normalized frame (points / frame scale); ``first_scan`` (the
    valid points of scan 0 in the data's units) gives that scale, so the true motion is taken to
    the same units before it is compared."""
    from deepmapping.geometry import se2
    from deepmapping.solver import curriculum as cur

    plain = getattr(cur.place_new_scan, "plain", cur.place_new_scan)
    scale = {}  # data units per model unit, found at the first placement

    def place(trainer, j):
        plain(trainer, j)
        if j == 0:
            return
        model, cfg = trainer.model, trainer.cfg.curriculum
        prev, chosen = cur.placement(model, j - 1), cur.placement(model, j)
        if not scale:
            scale["s"] = float(np.linalg.norm(first_scan) / float(model.scans[0][trainer.valid[0]].double().norm()))
        motion = se2.relative(gt[j - 1], gt[j])
        motion[:2] /= scale["s"]
        truth = se2.compose(prev, motion)
        err = se2.relative(truth, chosen)
        err[:2] *= scale["s"]
        pts = cur.selection_points(model, trainer.valid, j, cfg.select_points)
        pp, pv = cur.selection_points(model, trainer.valid, j - 1, cfg.select_points)
        prev_glob = (cur.transform(cur.candidate_poses(model, prev[None]), pp[None])[0], pv)
        both = cur.candidate_poses(model, np.stack([chosen, truth]))
        with torch.no_grad():
            loss = cur.candidate_losses(model, pts, j, both, prev_glob, trainer.cfg.loss.chamfer_weight,
                                        cfg.select_bce_weight)
            eq4 = cur.candidate_losses(model, pts, j, both, prev_glob, 0.0)  # eq. 4 alone, weight 1
            ch = cur.candidate_losses(model, pts, j, both, prev_glob, 1.0, 0.0)  # Chamfer alone, weight 1
            mr = float(pts[0][pts[1]].norm(dim=1).median())
            ranked = cur.triggered(model, j, cfg, mr)[1]  # the check as the ranking used it
            check = cur.free_space_check(trainer, j, prev, prev_glob, mr) if ranked else None
            fs = check(both, pts) if check is not None else torch.zeros(2)  # weighted, as ranked
            loss = loss + fs
        ahead = se2.compose(prev, cur.last_motion(model, j))  # the search's second centre
        reach = min(np.hypot(*motion[:2]), np.hypot(*se2.relative(ahead, truth)[:2])) / mr
        log.append((j, unit * float(np.hypot(err[0], err[1])), float(np.degrees(abs(err[2]))),
                    float(loss[0]), float(loss[1]), float(eq4[0]), float(eq4[1]), float(ch[0]), float(ch[1]),
                    float(fs[0]), float(fs[1]), reach, float(np.degrees(abs(motion[2])))))

    place.plain = plain
    cur.place_new_scan = place


def robustness(trajectories: list[int], stride: int, extra: dict, why: bool = False) -> None:
    from deepmapping.api import evaluate_poses, register
    from deepmapping.config import load_config
    from deepmapping.sim.dataset import paper_trajectory

    placed = []
    for t in trajectories:
        s = paper_trajectory(t)
        s.points, s.valid, s.gt_poses, s.names = s.points[::stride], s.valid[::stride], s.gt_poses[::stride], \
            s.names[::stride]
        log: list = []
        if why:
            explain_placements(s.gt_poses, s.unit_scale, log, s.points[0][s.valid[0]].astype(np.float64))
        t0 = time.perf_counter()
        r = register(s, load_config("cold", overrides={"optim.epochs": 1, "threads": 1} | extra))
        placed.append(float(evaluate_poses(s, r.placements)["ate"]))
        print(f"trajectory {t} stride {stride}: placed ATE {placed[-1]:.1f} px ({time.perf_counter() - t0:.0f} s)",
              flush=True)
        off = [e for e in log if e[1] > 20 or e[2] > 10][:3]
        for j, px, deg, chosen, true, b0, b1, c0, c1, f0, f1, reach, turn in off:
            cause = "search (the truth is lower)" if true < chosen else "criterion (the truth is higher)"
            print(f"  scan {j}: {px:.1f} px / {deg:.1f} deg off, loss {chosen:.3f} vs truth {true:.3f}: {cause}; "
                  f"eq. 4 {b0:.3f} vs {b1:.3f}, Chamfer {c0:.4f} vs {c1:.4f}, free space {f0:.3f} vs {f1:.3f}; "
                  f"the truth {reach:.2f} median ranges from the nearer centre, turned {turn:.0f} deg")
    print(f"below 20 px: {sum(a < 20 for a in placed)} of {len(placed)}")


def kinect_noise(scans, seed: int):
    """Depth noise as a Kinect's (sigma = 1.2 mm + 1.9 mm x (z - 0.4 m)^2 along the ray, Nguyen et
    al. 2012), 3 % of the pixels dropped, depth rounded to mm (scans in metres)."""
    rng = np.random.default_rng([7, seed])
    z = scans.points[..., 2].astype(np.float64)
    zn = np.round((z + rng.normal(0, 1, z.shape) * (0.0012 + 0.0019 * (z - 0.4) ** 2)) * 1000) / 1000
    keep = scans.valid & (rng.uniform(size=z.shape) > 0.03) & (zn > 0)
    scale = zn / np.where(z > 0, z, 1)
    scans.points = np.where(keep[..., None], scans.points * scale[..., None], 0).astype(np.float32)
    scans.valid = keep
    return scans


def avd(trajectories: list[int], extra: dict, noise: bool = False) -> None:
    from deepmapping.api import evaluate_poses, register
    from deepmapping.config import load_config
    from deepmapping.experiments.exp_avd import THRESHOLD_MM, avd_trajectory

    for t in trajectories:
        scans = avd_trajectory(t, 16, 0, 80, 60)
        if noise:
            scans = kinect_noise(scans, t)
        over = {"warm_start.method": "none", "curriculum.enabled": "on", "loss.chamfer_weight": 0.1,
                "eval.success_threshold": THRESHOLD_MM, "threads": 1} | extra
        t0 = time.perf_counter()
        r = register(scans, load_config("default-3d", overrides=over))
        p = evaluate_poses(scans, r.placements)
        print(f"trajectory {t}: ATE {r.metrics['ate']:.0f} mm, rotation {r.metrics['rotation_rmse_deg']:.1f} deg "
              f"(placed: {p['ate']:.0f} mm, {p['rotation_rmse_deg']:.1f} deg), {time.perf_counter() - t0:.0f} s",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind", choices=["robustness", "avd"])
    ap.add_argument("--trajectories", default=None, help="comma-separated (robustness: 50-54, avd: 0-2)")
    ap.add_argument("--stride", type=int, default=8)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--why", action="store_true", help="robustness: for the first scans placed > 20 px or "
                    "10 deg off, the loss of the chosen and of the true placement (search or criterion failure)")
    ap.add_argument("--depth-noise", action="store_true", help="avd: Kinect-like depth noise and dropped pixels")
    a = ap.parse_args()
    torch.set_num_threads(1)
    default = "50,51,52,53,54" if a.kind == "robustness" else "0,1,2"
    ts = [int(x) for x in (a.trajectories or default).split(",")]
    np.set_printoptions(precision=3)
    if a.kind == "robustness":
        robustness(ts, a.stride, _overrides(a.sets), a.why)
    else:
        avd(ts, _overrides(a.sets), a.depth_noise)


if __name__ == "__main__":
    main()
