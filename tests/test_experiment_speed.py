"""The speed experiment (``deepmapping experiment speed``): its time-to-accuracy rule and a quick run."""

import json

from deepmapping.experiments import speed
from deepmapping.experiments.runner import run_experiment


def test_time_to_reach_counts_only_from_where_the_ate_stays_below():
    curve = [(1.0, 12.0), (2.0, 4.0), (3.0, 7.0), (4.0, 5.0), (5.0, 2.5), (6.0, 2.9)]
    assert speed.time_to_reach(curve, 20.0) == 1.0
    assert speed.time_to_reach(curve, 5.7) == 4.0  # dipped at 2 s, came back above at 3 s
    assert speed.time_to_reach(curve, 3.0) == 5.0
    assert speed.time_to_reach(curve, 1.0) is None
    assert speed.time_to_reach(curve + [(7.0, 3.5)], 3.0) is None  # not below at the end


def test_summary_reports_median_worst_and_misses():
    runs = [{"ate": a, "point_distance": a, "wall_s": 10.0, "peak_rss_mb": 100.0 + a, "steps": 10, "epochs": 5,
             "train_s": 5.0, "curve": [(1.0, 30.0), (9.0, a)]} for a in (2.0, 4.0, 25.0)]
    s = speed.summarize(runs)
    assert s["ate"] == (4.0, 25.0) and s["peak_rss_mb"] == (104.0, 125.0)
    assert s["t20"][2] == 2 and s["t20"][1] is None  # one trajectory never reached 20 px
    assert s["steps_per_s"] == 2.0 and s["epochs_per_min"] == 60.0
    assert speed.fmt_time(s["t20"], 3) == "9.0 / never (2/3)"


def test_speed_jobs_are_one_per_trajectory_and_method_and_the_scaling_pair():
    keys = [j.key for j in speed.jobs(False)]
    assert len(keys) == 5 * len(speed.METHODS) + 2 and len(set(keys)) == len(keys)
    assert keys[:3] == ["t0-icp-point", "t0-icp-plane", "t0-deepmapping-default"]
    assert keys[-2:] == ["scaling-small", "scaling-big"]
    assert {j.kwargs["paper_budget_s"] for j in speed.jobs(False) if "method" in j.kwargs} == {120.0}
    json.dumps([j.kwargs for j in speed.jobs(True)])


def test_speed_experiment_quick_run_writes_its_table_and_figure(tmp_path):
    """Two runs of trajectory 0 at the quick size, each in a fresh process of its own."""
    run_experiment("speed", tmp_path, quick=True, workers=1, only="t0-icp-plane")
    res = run_experiment("speed", tmp_path, quick=True, workers=1, only="t0-deepmapping-default")
    assert res["errors"] == {}
    dm = res["results"]["t0-deepmapping-default"]
    assert dm["method"] == "deepmapping (default)" and dm["trajectory"] == 0
    assert dm["num_scans"] == 12 and dm["epochs"] == 3 and dm["peak_rss_mb"] > 50 and dm["wall_s"] > 0
    assert len(dm["curve"]) >= 2 and all(t2 >= t1 for (t1, _), (t2, _) in zip(dm["curve"], dm["curve"][1:]))
    assert "poses.npy" in dm["run_files"]  # the run folder was written within the timed part
    assert res["results"]["t0-icp-plane"]["steps"] == 0
    md = (tmp_path / "report.md").read_text()
    assert "| icp-plane |" in md and "| deepmapping (default) |" in md and "| direct (default) |" not in md
    assert "![ATE against wall time](ate_vs_time.png)" in md
    assert (tmp_path / "ate_vs_time.png").stat().st_size > 10_000

