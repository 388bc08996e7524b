"""``deepmapping experiment carmen`` on the excerpts of the Freiburg logs (tests/data/carmen)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from deepmapping.errors import ConfigError
from deepmapping.experiments import carmen

DATA = Path(__file__).resolve().parent / "data" / "carmen"  # excerpts (tests/data/make_excerpts.py)


def test_jobs_are_the_logs_with_relations_and_the_reference_where_its_log_is_there(tmp_path):
    keys = [j.key for j in carmen.jobs(False, str(DATA))]
    # the intel excerpt has no corrected log: no reference row for it
    assert keys == [f"intel-{m}" for m in carmen.METHODS] + [f"fr079-{m}" for m in ("reference", *carmen.METHODS)]
    assert {j.kwargs["keyframes"] for j in carmen.jobs(False, str(DATA))} == {"motion:0.5,15"}
    json.dumps([j.kwargs for j in carmen.jobs(True, str(DATA))])
    shutil.copy(DATA / "fr079.clf.gz", tmp_path)  # a log without its relations is not one of the runs
    with pytest.raises(ConfigError, match=f"^{tmp_path}: no log with its relations"):
        carmen.jobs(False, str(tmp_path))


def test_quick_run_on_the_fr079_excerpt(tmp_path):
    """The relations table with the reference reproduced (the excerpt's score, as in test_carmen;
    the full log's is 0.058 m), each run's own wall time and peak RSS."""
    from deepmapping.experiments.runner import run_experiment

    run_experiment("carmen", tmp_path, quick=True, workers=1, data=DATA, only="fr079-[ro]*")  # reference, odometry
    res = run_experiment("carmen", tmp_path, quick=True, workers=1, data=DATA, only="fr079-dm-odometry")
    assert res["errors"] == {}
    rows = {r["name"]: r for r in res["results"].values()}
    assert set(rows) == {"reference", "odometry", "dm-odometry"}
    assert abs(rows["reference"]["relations"]["all"]["trans_mean_m"] - 0.0492) < 0.0015
    assert rows["odometry"]["relations"]["unmatched"] == 0 and rows["odometry"]["keyframes"] == 10
    assert rows["dm-odometry"]["peak_rss_mb"] > 50 and rows["dm-odometry"]["wall_s"] > 0
    assert rows["dm-odometry"]["on_reference"]["all"]["count"] > 0
    text = (tmp_path / "report.md").read_text()
    assert "## fr079" in text and "| dm-odometry | 10 |" in text and "## intel" not in text
    assert json.loads((tmp_path / "experiment.json").read_text())["data"] == str(DATA)


def test_a_site_with_only_its_corrected_log_runs_with_simulated_odometry(tmp_path):
    """A corrected log of a SIMULATED site (here the fr079 excerpt's, under fhw's name) becomes the
    runs ``fhw-sim-*``: its scans with simulated odometry, scored on relations derived from it."""
    from deepmapping.experiments.runner import run_experiment

    (tmp_path / "corrected").mkdir()
    shutil.copy(DATA / "corrected" / "freiburg-079-corrected.log.gz", tmp_path / "corrected" / "fhw-corrected.log.gz")
    keys = [j.key for j in carmen.jobs(False, str(tmp_path))]
    assert keys == [f"fhw-sim-{m}" for m in carmen.SIM_METHODS]
    out = tmp_path / "out"
    res = run_experiment("carmen", out, quick=True, workers=1, data=tmp_path, only="fhw-sim-[ol]*")
    assert res["errors"] == {}
    rows = {r["name"]: r for r in res["results"].values()}
    odometry, closed = rows["odometry"]["relations"], rows["loop-closure"]["relations"]
    assert odometry["unmatched"] == 0 and odometry["all"]["count"] > 100
    assert odometry["all"]["trans_mean_m"] > 0.05  # the simulated odometry drifts; the reference would score 0
    assert closed["all"]["count"] == odometry["all"]["count"]
    assert "## fhw-sim with simulated odometry (seed 0)" in (out / "report.md").read_text()
