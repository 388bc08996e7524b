"""``deepmapping experiment threads``: jobs and a quick run of one seed with 1 and 2 threads."""

from __future__ import annotations

import json

import numpy as np

from deepmapping.experiments import threads


def test_jobs_are_seeds_by_thread_counts():
    full = threads.jobs(False)
    assert [j.key for j in full] == [f"s{s}-t{t}" for s in range(5) for t in (1, 2)]
    assert {j.kwargs["trajectory"] for j in full} == {0} and {j.kwargs["num_poses"] for j in full} == {None}
    json.dumps([j.kwargs for j in threads.jobs(True)])


def test_quick_run_reports_the_difference_between_thread_counts(tmp_path):
    from deepmapping.experiments.runner import run_experiment

    res = run_experiment("threads", tmp_path, quick=True, workers=1, only="s0-*")
    assert res["errors"] == {}
    rows = {r["threads"]: r for r in res["results"].values()}
    assert set(rows) == {1, 2} and all(np.isfinite(r["ate"]) and r["num_poses"] == 16 for r in rows.values())
    text = (tmp_path / "report.md").read_text()
    assert "| ATE, 1 thread (px) |" in text and "| ATE, 2 threads (px) |" in text and "| difference (px) |" in text
    assert "Largest difference between thread counts" in text
