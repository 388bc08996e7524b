"""AVD-like experiment (Table 2, Fig. 9): the in-memory trajectories, and the quick sweep end to end."""

import json
import math

import numpy as np
import pytest

from deepmapping.experiments import exp_avd


def test_in_memory_trajectory_is_the_one_simulate_writes(tmp_path):
    from deepmapping.io.rgbd import load_rgbd
    from deepmapping.sim.rgbd import write_rgbd_dataset

    folders = write_rgbd_dataset(tmp_path, num_trajectories=3, frames=3, seed=1)
    for t in (0, 2):  # trajectory 2 is in the second scene
        disk = load_rgbd(folders[t])
        mem = exp_avd.avd_trajectory(t, frames=3, seed=1)
        np.testing.assert_array_equal(mem.valid, disk.valid)
        np.testing.assert_allclose(mem.points, disk.points, atol=1e-6)
        np.testing.assert_allclose(mem.gt_poses, disk.gt_poses, atol=1e-9)
        assert (mem.grid_shape, mem.pose_dof, mem.unit, mem.unit_scale) == ((60, 80), 3, "mm", 1000.0)


def test_smaller_images_see_the_same_trajectory():
    full, small = exp_avd.avd_trajectory(1, 4), exp_avd.avd_trajectory(1, 4, width=32, height=24)
    np.testing.assert_array_equal(full.gt_poses, small.gt_poses)
    assert small.points.shape == (4, 32 * 24, 3) and small.grid_shape == (24, 32)


def test_methods_and_jobs():
    labels = [label for label, _ in exp_avd.METHODS.values()]
    assert len(set(labels)) == len(labels)
    assert len(exp_avd.TRAINED) == 8  # {DeepMapping, direct} x {+ Ch, BCE only} x {cold, warm}
    cold = [m for m in exp_avd.TRAINED if m.endswith("-cold")]
    assert all(exp_avd.METHODS[m][1]["warm_start.method"] == "none" for m in cold)
    assert {exp_avd.METHODS[m][1]["loss.chamfer_weight"] for m in exp_avd.TRAINED} == {0.0, 0.1}
    for quick, (n, frames) in ((True, (2, 8)), (False, (10, 16))):
        jobs = exp_avd.jobs(quick)
        assert len(jobs) == n * len(exp_avd.METHODS) and len({j.key for j in jobs}) == len(jobs)
        assert {j.kwargs["frames"] for j in jobs} == {frames}
        json.dumps([j.kwargs for j in jobs])


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    from deepmapping.experiments.runner import run_experiment

    out = tmp_path_factory.mktemp("avd")
    return out, run_experiment("avd", out, quick=True, workers=1)


def test_quick_run_end_to_end(quick_run):
    out, res = quick_run
    s = exp_avd.sizes(True)
    assert res["errors"] == {}
    assert len(res["results"]) == len(exp_avd.jobs(True))
    for name in ("report.md", "experiment.json", "ate_box.png", "point_distance_box.png", "ate_vs_iterations.png"):
        assert (out / name).stat().st_size > 0, name
    for r in res["results"].values():
        for key in ("ate", "point_distance", "rotation_rmse_deg"):
            assert math.isfinite(r[key]) and 0 <= r[key] < 1e4, (r["method"], key)
        assert r["success"] == (r["ate"] < 450.0)
        if r["method"] in exp_avd.TRAINED:
            evals = 1 + math.ceil(s["epochs"] / s["eval_every"])
            assert len(r["ate_curve"]) == len(r["iteration"])
            assert np.all(np.diff(r["iteration"]) > 0)
            if r["method"].endswith("-cold"):  # the curriculum's stages are logged too
                assert len(r["iteration"]) > evals
            else:
                assert len(r["iteration"]) == evals
            assert r["ate_curve"][-1] == pytest.approx(r["ate"])
    text = (out / "report.md").read_text()
    for paper in ("80.0 %", "77.1 %", "58.1 %"):
        assert paper in text
    for label, _ in exp_avd.METHODS.values():
        assert f"| {label} | 2/2 |" in text
    assert "(ate_box.png)" in text and "(point_distance_box.png)" in text


def test_report_copes_with_missing_runs(quick_run, tmp_path):
    _, res = quick_run
    some = {k: v for k, v in res["results"].items() if "multiway" not in k and "cold" not in k}
    text = exp_avd.report(tmp_path, some, quick=True).read_text()
    assert "| multiway | 0/2 | - |" in text and (tmp_path / "ate_box.png").exists()
    assert exp_avd.report(tmp_path / "none", {}, quick=True).exists()
