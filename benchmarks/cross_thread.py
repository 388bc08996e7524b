"""Reproducibility across thread counts (docs/results.md): the final ATE of the default 2D
command on one of the paper's trajectories with 1 and with 2 torch threads, seeds 0-4.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/cross_thread.py 2d 0

Same seed and thread count give bit-identical poses (tests/test_solver.py, tests/test_cli.py);
different thread counts sum floats in a different order, so runs part and end in nearby minima.
"""
import json
import sys
import time

from deepmapping.api import evaluate_poses, register
from deepmapping.config import load_config
from deepmapping.sim.dataset import paper_trajectory

kind = sys.argv[1]
out = {}
if kind == "2d":
    s = paper_trajectory(int(sys.argv[2]) if len(sys.argv) > 2 else 0)
    for seed in range(5):
        for th in (1, 2):
            t = time.time()
            r = register(s, load_config("default", overrides={"seed": seed, "threads": th}))
            ate = evaluate_poses(s, r.poses)["ate"]
            out[f"{seed}-{th}"] = ate
            print(seed, th, f"{ate:.4f}", f"{time.time()-t:.0f}s", flush=True)
print(json.dumps(out))
