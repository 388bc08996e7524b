"""Warm-start experiment (Fig. 1): the quick sweep end to end, and its pieces."""

import json
import math

import numpy as np
import pytest

from deepmapping.experiments import warm_start


def test_jobs_one_run_per_trajectory_and_start():
    for quick in (True, False):
        s = warm_start.sizes(quick)
        jobs = warm_start.jobs(quick)
        assert len(jobs) == len(s["trajectories"]) * len(warm_start.STARTS)
        assert len({j.key for j in jobs}) == len(jobs)
        assert {j.kwargs["start"] for j in jobs} == {"none", "icp-plane", "icp-point"}
        json.dumps([j.kwargs for j in jobs])
    assert warm_start.sizes(False)["poses"] == 256 and len(warm_start.sizes(False)["trajectories"]) == 3


def test_trajectory_is_deterministic_and_moves():
    a, b = warm_start.trajectory_2d(1, 32, 64), warm_start.trajectory_2d(1, 32, 64)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.gt_poses, b.gt_poses)
    assert a.points.shape == (32, 64, 2) and a.unit == "px"
    travel = np.linalg.norm(np.diff(a.gt_poses[:, :2], axis=0), axis=1).sum() * a.unit_scale
    assert travel > 50  # px: the quick trajectory goes somewhere (trajectory 0 turns on the spot)
    assert not np.array_equal(warm_start.trajectory_2d(2, 32, 64).gt_poses, a.gt_poses)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    from deepmapping.experiments.runner import run_experiment

    out = tmp_path_factory.mktemp("warm_start")
    return out, run_experiment("warm-start", out, quick=True, workers=1)


def test_quick_run_end_to_end(quick_run):
    out, res = quick_run
    s = warm_start.sizes(True)
    assert res["errors"] == {}
    for name in ("report.md", "experiment.json", "ate_vs_iterations.png"):
        assert (out / name).stat().st_size > 0, name
    assert len(list((out / "runs").glob("*.json"))) == len(warm_start.jobs(True))
    final = {}
    for r in res["results"].values():
        logs = 1 + math.ceil(s["epochs"] / s["eval_every"])  # the cold start's curriculum logs more
        assert len(r["ate"]) == len(r["iteration"]) and (len(r["ate"]) > logs if r["start"] == "none"
                                                        else len(r["ate"]) == logs)
        assert r["iteration"][0] == 0 and np.all(np.diff(r["iteration"]) > 0)
        ate = np.array(r["ate"], float)
        assert np.isfinite(ate).all() and (ate >= 0).all() and (ate < 500).all()  # px
        assert r["final_ate"] == pytest.approx(ate[-1])
        final[r["start"]] = r["final_ate"]
    cold = next(r for r in res["results"].values() if r["start"] == "none")
    assert cold["init_ate"] > 10  # px: every pose at the origin
    # the cold start converges (the curriculum): measured 39 -> 1.18 px; warm 1.35 -> 2.9, 2.0 -> 3.6 px
    assert final["none"] < 0.2 * cold["init_ate"] and final["none"] < 3 * max(final["icp-plane"], 1.0)
    text = (out / "report.md").read_text()
    assert "(ate_vs_iterations.png)" in text and "## Final ATE" in text
    for label in warm_start.STARTS:
        assert f"| {label} | 1/1 |" in text


def test_report_copes_with_missing_runs(quick_run, tmp_path):
    _, res = quick_run
    some = {k: v for k, v in res["results"].items() if not k.endswith("cold")}
    text = warm_start.report(tmp_path, some, quick=True).read_text()
    assert "| cold | 0/1 |" in text and (tmp_path / "ate_vs_iterations.png").exists()
    assert warm_start.report(tmp_path / "none", {}, quick=True).exists()
