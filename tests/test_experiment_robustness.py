"""``deepmapping experiment robustness``: jobs, one run of each kind, the report, ``--only``."""

from __future__ import annotations

import json
import math

import pytest

from deepmapping.errors import ConfigError
from deepmapping.experiments import robustness


def test_jobs_cover_methods_trajectories_and_strides():
    full = robustness.jobs(quick=False)
    s = robustness.sizes(False)
    assert len(full) == len(s["trajectories"]) * len(s["strides"]) * len(robustness.METHODS)
    assert len({j.key for j in full}) == len(full)
    for j in full:
        budget = j.kwargs["time_budget_s"]
        if j.kwargs["method"] in robustness.TIME_MATCHED:
            assert budget == pytest.approx(0.5 * math.ceil(256 / j.kwargs["stride"]))
        else:
            assert budget is None
    json.dumps([j.kwargs for j in full])
    for j in robustness.jobs(quick=True):  # a smoke run's cold rows search less; the full size as measured
        cold = j.kwargs["method"] in ("deepmapping-cold", "direct-cold")
        assert j.kwargs.get("cold_overrides") == (robustness.QUICK_CURRICULUM if cold else None)
    assert all("cold_overrides" not in j.kwargs for j in full)


@pytest.fixture(scope="module")
def icp_only(tmp_path_factory):
    from deepmapping.experiments.runner import run_experiment

    out = tmp_path_factory.mktemp("robustness")
    return out, run_experiment("robustness", out, quick=True, workers=1, only="icp-*")


def test_only_runs_the_matching_runs_and_reports_them(icp_only):
    out, res = icp_only
    s = robustness.sizes(True)
    assert res["errors"] == {}
    assert sorted(r["method"] for r in res["results"].values()) == ["icp-plane"] * 2 + ["icp-point"] * 2
    assert len(list((out / "runs").glob("*.json"))) == 2 * len(s["strides"])
    rows = sorted(res["results"].values(), key=lambda r: (r["method"], r["stride"]))
    small, large = rows[0], rows[1]  # icp-plane at stride 4 and 16: larger motions at the larger stride
    assert small["stride"] < large["stride"] and small["median_step_px"] < large["median_step_px"]
    assert small["num_poses"] == math.ceil(256 / small["stride"])
    text = (out / "report.md").read_text()
    assert "(success.png)" in text and (out / "success.png").stat().st_size > 0
    assert f"of {len(robustness.jobs(True))} runs finished" in text
    assert json.loads((out / "experiment.json").read_text())["only"] == "icp-*"


def test_only_that_matches_nothing_is_refused_before_anything_is_written(tmp_path):
    from deepmapping.experiments.runner import run_experiment

    with pytest.raises(ConfigError, match="matches none"):
        run_experiment("robustness", tmp_path / "x", quick=True, only="nothing-*")
    assert not (tmp_path / "x").exists()


def test_a_cold_run_on_a_thinned_trajectory():
    row = robustness.run(50, "deepmapping-cold", stride=16, num_beams=64, epochs=5,
                         cold_overrides=robustness.QUICK_CURRICULUM)
    assert row["num_poses"] == 16 and row["profile"] == "cold" and math.isfinite(row["ate"])
    assert row["placed_ate"] is not None and row["median_turn_deg"] > 10  # 16 steps of up to 10 deg each


def test_report_without_runs(tmp_path):
    text = robustness.report(tmp_path, {}, quick=True).read_text()
    assert "No finished run" in text and not (tmp_path / "success.png").exists()
