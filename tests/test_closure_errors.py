"""benchmarks/closure_errors.py: the loop-closure front end judged against a simulated ground truth."""

import importlib.util
import re
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "closure_errors.py"


def _module():
    spec = importlib.util.spec_from_file_location("closure_errors", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_similarity_scale_finds_a_shrunk_trajectory():
    import numpy as np

    rng = np.random.default_rng(0)
    gt = np.column_stack([rng.normal(size=(50, 2)), rng.normal(size=50)])
    est = gt.copy()
    est[:, :2] = 0.98 * gt[:, :2] @ np.array([[0.0, -1.0], [1.0, 0.0]]).T + 3.0  # 2 % smaller, turned, moved
    assert abs(_module().similarity_scale(est, gt) - 1 / 0.98) < 1e-9
    assert abs(_module().similarity_scale(gt, gt) - 1.0) < 1e-12


def test_closure_errors_on_a_simulated_trajectory(sim_folder, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["closure_errors.py", str(sim_folder), "--set", "min_gap=10"])
    _module().main()
    out = capsys.readouterr().out
    m = re.search(r"ATE ([\d.]+) px, similarity scale ([\d.]+), (\d+) loop closures, (\d+) over 3 px", out)
    assert m, out
    assert float(m.group(1)) < 2.0 and abs(float(m.group(2)) - 1) < 0.05 and int(m.group(3)) > 0, out
