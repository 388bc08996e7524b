"""How right the loop closures are on a simulated 2D trajectory (its ground truth judges each edge).

    .venv/bin/python benchmarks/closure_errors.py DIR                      # the default settings
    .venv/bin/python benchmarks/closure_errors.py DIR --set refine_closures=false --set max_drift=0.3

DIR is a `deepmapping simulate` folder (the authors' layout, gt_pose.mat). Runs
``methods.loop_closure.close_loops`` as the default warm start does (no odometry: every match from
the identity, no prior, or with ``--set constant_velocity=true`` from the previous keyframe's motion;
``scale`` from the scans' ranges) and prints the trajectory's ATE, the scale a similarity alignment
would add (a trajectory that shrank or grew), how many loop closures there are, how many are more
than --bad px from the truth, and the mean error of the closures in bands of distance between their
keyframes (too short = negative). --set takes the config's `loop` settings and close_loops' other
keyword arguments.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from deepmapping.config import LoopClosureConfig
from deepmapping.errors import InputError
from deepmapping.evaluation.metrics import ate
from deepmapping.geometry import se2
from deepmapping.io.loaders import load_authors
from deepmapping.methods.loop_closure import close_loops, data_scale
from deepmapping.methods.registry import loop_closure_settings


def similarity_scale(est, gt) -> float:
    """The scale s of the best similarity gt ~ s R est + t (Umeyama), positions only."""
    a, b = est[:, :2] - est[:, :2].mean(0), gt[:, :2] - gt[:, :2].mean(0)
    u, sv, vt = np.linalg.svd(b.T @ a / len(a))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    return float(np.trace(np.diag(sv) @ d) / (a ** 2).sum(1).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--bad", type=float, default=3.0, help="a closure further than this (px) is wrong")
    args = ap.parse_args()
    try:
        scans = load_authors(args.data)
    except InputError as e:
        sys.exit(f"closure_errors: {e}")
    given = dict((item.split("=", 1)[0], json.loads(item.split("=", 1)[1])) for item in args.set)
    loop = LoopClosureConfig(**{k: v for k, v in given.items() if k in LoopClosureConfig.model_fields})
    settings = loop_closure_settings(loop, data_scale(scans.points, scans.valid), odometry=False)
    settings |= {k: v for k, v in given.items() if k not in LoopClosureConfig.model_fields}
    start = time.perf_counter()
    poses, edges = close_loops(scans.points, scans.valid, np.zeros((scans.num_scans, 3)), **settings)
    seconds = time.perf_counter() - start
    gt, px = scans.gt_poses, scans.unit_scale
    loops = [e for e in edges if e.j - e.i > 1]
    true = np.array([se2.relative(gt[e.i], gt[e.j]) for e in loops]).reshape(-1, 3)
    z = np.array([e.z for e in loops]).reshape(-1, 3)
    apart = np.hypot(true[:, 0], true[:, 1]) * px
    error = np.hypot(*(z[:, :2] - true[:, :2]).T) * px
    longer = (np.hypot(z[:, 0], z[:, 1]) * px) - apart
    print(f"ATE {ate(poses, gt) * px:.3f} px, similarity scale {similarity_scale(poses, gt):.4f}, "
          f"{len(loops)} loop closures, {int((error > args.bad).sum())} over {args.bad:g} px, {seconds:.0f} s")
    for lo, hi in ((0, 20), (20, 50), (50, 100), (100, np.inf)):
        band = (apart >= lo) & (apart < hi)
        if band.any():
            print(f"  keyframes {lo:g}-{hi:g} px apart: {int(band.sum())} closures, mean error {error[band].mean():.2f} px, "
                  f"length {longer[band].mean():+.2f} px")


if __name__ == "__main__":
    main()
