"""The 2D suite (``deepmapping experiment 2d``) and its pairwise baselines (Go-ICP, PSO)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from deepmapping.geometry import se2


@pytest.fixture(scope="module")
def far_pair():
    """Two consecutive simulated scans, the source turned 120 deg and shifted: (source, target, true pose).

    Incremental ICP from the identity cannot recover this (checked below), a global method must.
    """
    from deepmapping.sim.dataset import simulate
    from deepmapping.sim.maps import procedural_indoor_map

    scans = simulate(procedural_indoor_map(5, size=256), num_poses=2, seed=3, num_beams=128)
    rel = se2.relative(scans.gt_poses[0], scans.gt_poses[1])
    delta = np.array([0.04, -0.03, np.radians(120.0)])
    source = se2.transform_points(se2.inverse(delta), scans.points[1].astype(np.float64))
    return source, scans.points[0].astype(np.float64), se2.compose(rel, delta)


def _pose_error(pose, true) -> tuple[float, float]:
    d = se2.relative(true, pose)
    return float(np.hypot(d[0], d[1])), float(abs(np.degrees(d[2])))


def test_icp_alone_fails_on_the_far_pair(far_pair):
    from deepmapping.methods.icp import icp_2d

    source, target, true = far_pair
    _, angle = _pose_error(icp_2d(source, target)[0], true)
    assert angle > 30.0


def test_goicp_recovers_a_known_transform(far_pair):
    from deepmapping.methods.goicp import goicp_2d

    source, target, true = far_pair
    pose, info = goicp_2d(source, target, trim_fraction=0.1, time_budget_s=30.0)
    dist, angle = _pose_error(pose, true)
    assert dist < 0.004 and angle < 1.0, (pose, true, info)  # 0.004 = 2 px in px/512 units
    assert info["optimal"] and info["icp_runs"] >= 2


def test_pso_recovers_a_known_transform(far_pair):
    from deepmapping.methods.pso import pso_register_2d

    source, target, true = far_pair
    pose, info = pso_register_2d(source, target, trim_fraction=0.1, rounds=3, seed=0)
    dist, angle = _pose_error(pose, true)
    assert dist < 0.004 and angle < 1.0, (pose, true, info)
    assert info["rounds"] == 3


def test_pso_stops_at_its_time_budget(far_pair):
    from deepmapping.methods.pso import pso_register_2d

    source, target, _ = far_pair
    _, info = pso_register_2d(source, target, time_budget_s=0.3, seed=1)
    assert info["rounds"] >= 1 and info["time_s"] < 1.5


def test_paper_trajectory_is_deterministic_and_on_its_map():
    from deepmapping.sim.dataset import PAPER_LENGTHS, paper_trajectory

    assert len(PAPER_LENGTHS) == 75 and PAPER_LENGTHS.count(128) == 50 and PAPER_LENGTHS.count(256) == 25
    a = paper_trajectory(4, num_poses=6, num_beams=32)
    b = paper_trajectory(4, num_poses=6, num_beams=32)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.gt_poses, b.gt_poses)
    assert a.points.shape == (6, 32, 2) and "map 1" in a.source
    with pytest.raises(ValueError):
        paper_trajectory(75)


def test_jobs_cover_every_method_and_trajectory():
    from deepmapping.experiments import exp_2d

    full = exp_2d.jobs(quick=False)
    assert len(full) == 75 * len(exp_2d.METHODS)
    assert len({j.key for j in full}) == len(full)
    budgets = {j.kwargs["method"]: j.kwargs["time_budget_s"] for j in full if j.kwargs["trajectory"] == 0}
    assert budgets["pso"] == budgets["goicp"] == budgets["deepmapping-paper"] == 128 * exp_2d.BUDGET_S_PER_POSE
    assert budgets["deepmapping"] is None
    assert all("cold_overrides" not in j.kwargs for j in full)  # the full size: the cold profile as measured
    for j in exp_2d.jobs(quick=True):  # a smoke run's cold rows search less
        assert j.kwargs.get("cold_overrides") == (exp_2d.QUICK["cold_overrides"] if j.kwargs["method"] in exp_2d.COLD
                                                  else None)
    json.dumps([j.kwargs for j in full])  # plain JSON-able kwargs (cluster workers)


def test_quick_experiment_end_to_end(tmp_path):
    from deepmapping.experiments import exp_2d
    from deepmapping.experiments.runner import run_experiment

    out = tmp_path / "exp"
    outcome = run_experiment("2d", out, quick=True, workers=1)
    assert outcome["errors"] == {}
    n = len(exp_2d.QUICK["trajectories"]) * len(exp_2d.METHODS)
    assert len(outcome["results"]) == n
    for name in ("report.md", "table.md", "ate.png", "point_distance.png", "summary.json", "experiment.json"):
        assert (out / name).stat().st_size > 0, name
    assert len(list((out / "runs").glob("*.json"))) == n

    for key, r in outcome["results"].items():
        for field in ("ate", "point_distance", "runtime_s", "rotation_rmse_deg"):
            assert math.isfinite(r[field]) and r[field] >= 0, (key, field, r[field])
        assert r["success"] == (r["ate"] < 20.0)
        assert r["num_poses"] == exp_2d.QUICK["num_poses"]
    summary = json.loads((out / "summary.json").read_text())
    for method in exp_2d.METHODS:
        assert 0.0 <= summary[method]["success"] <= 1.0
        assert summary[method]["runs"] == len(exp_2d.QUICK["trajectories"])
    # loose sanity bounds for the quick size (the paper's numbers are not expected here)
    assert summary["icp-plane"]["median_ate"] < 20.0
    assert summary["deepmapping"]["median_ate"] < 20.0
    assert summary["icp-point"]["median_ate"] < 100.0
    for method in exp_2d.TIME_MATCHED:  # a budget of a few seconds: no run may take much longer
        assert summary[method]["mean_runtime_s"] < 4 * exp_2d.QUICK_BUDGET_S, method

    text = (out / "report.md").read_text()
    assert "![" in text and "ate.png" in text and "point_distance.png" in text
    assert all(m in text for m in exp_2d.METHODS) and "84.2 %" in text
    hours = sum(r["runtime_s"] for r in outcome["results"].values()) / 3600
    assert f"{hours:.2f} h of run time in all" in text

    # missing results (failed runs) are reported, not fatal
    partial = {k: v for k, v in outcome["results"].items() if not k.startswith("pso")}
    path = exp_2d.report(tmp_path / "partial", partial, quick=True)
    assert "| pso | 0/3 |" in path.read_text()
    path = exp_2d.report(tmp_path / "none", {}, quick=True)
    assert "No finished run" in path.read_text() and not (tmp_path / "none" / "ate.png").exists()
