"""The sweep runner: results kept per run, failures retried or reported, restarts skip finished runs."""

import json

import pytest

from deepmapping.experiments.base import Job
from deepmapping.experiments.sweep import result_path, run_sweep

ECHO = "deepmapping.experiments.probe:echo"


def _jobs(n, **extra):
    return [Job(f"run-{i}", ECHO, {"value": float(i)} | extra) for i in range(n)]


def test_local_pool_runs_every_job_and_writes_results(tmp_path):
    seen = []
    results, errors = run_sweep(_jobs(4), tmp_path, workers=2, progress=lambda d, t, k: seen.append((d, t)))
    assert errors == {}
    assert {k: r["square"] for k, r in results.items()} == {f"run-{i}": float(i * i) for i in range(4)}
    assert json.loads(result_path(tmp_path, "run-3").read_text())["square"] == 9.0
    assert sorted(seen) == [(i, 4) for i in range(1, 5)]
    assert len({r["pid"] for r in results.values()}) >= 1


def test_failure_is_retried_then_reported_and_others_kept(tmp_path):
    jobs = _jobs(2) + [Job("flaky", ECHO, {"value": 5.0, "fail_times": 1, "marker": str(tmp_path / "m1")}),
                       Job("broken", ECHO, {"value": 6.0, "fail_times": 9, "marker": str(tmp_path / "m2")})]
    results, errors = run_sweep(jobs, tmp_path / "out", workers=2, retries=1)
    assert results["flaky"]["square"] == 25.0  # failed once, retried
    assert set(results) == {"run-0", "run-1", "flaky"}
    assert list(errors) == ["broken"] and "planned failure 2 of 9" in errors["broken"]
    failed = json.loads(result_path(tmp_path / "out", "broken", failed=True).read_text())
    assert "Traceback" in failed["traceback"]
    assert (tmp_path / "m2").read_text() == "2"  # tried exactly 1 + retries times


def test_restart_does_not_redo_finished_runs(tmp_path):
    marker = tmp_path / "calls"
    jobs = [Job("once", ECHO, {"value": 2.0, "fail_times": 0})]
    run_sweep(jobs, tmp_path, workers=1)
    # a finished result is loaded, not recomputed: a job that would now fail is never called
    jobs = [Job("once", ECHO, {"value": 2.0, "fail_times": 5, "marker": str(marker)})]
    results, errors = run_sweep(jobs, tmp_path, workers=1)
    assert results["once"]["square"] == 4.0 and errors == {} and not marker.exists()


def test_failed_runs_are_tried_again_on_restart(tmp_path):
    marker = str(tmp_path / "m")
    jobs = [Job("late", ECHO, {"value": 3.0, "fail_times": 2, "marker": marker})]
    _, errors = run_sweep(jobs, tmp_path / "out", workers=1, retries=0)
    assert "late" in errors and result_path(tmp_path / "out", "late", failed=True).exists()
    _, errors = run_sweep(jobs, tmp_path / "out", workers=1, retries=0)
    assert "late" in errors
    results, errors = run_sweep(jobs, tmp_path / "out", workers=1, retries=0)
    assert results["late"]["square"] == 9.0 and errors == {}
    assert not result_path(tmp_path / "out", "late", failed=True).exists()


def test_bad_keys_are_refused(tmp_path):
    with pytest.raises(ValueError):
        Job("a/b", ECHO)
    with pytest.raises(ValueError):
        run_sweep([Job("x", ECHO, {"value": 1.0})] * 2, tmp_path)


def test_dask_local_cluster(tmp_path):
    pytest.importorskip("distributed", reason="Dask is the optional 'cluster' extra (installed by ./run.sh test)")
    jobs = _jobs(3) + [Job("flaky", ECHO, {"value": 4.0, "fail_times": 1, "marker": str(tmp_path / "m")})]
    results, errors = run_sweep(jobs, tmp_path / "out", cluster="local", workers=2, retries=1)
    assert errors == {} and results["flaky"]["square"] == 16.0
    assert {k: r["square"] for k, r in results.items() if k != "flaky"} == {"run-0": 0.0, "run-1": 1.0, "run-2": 4.0}
    assert result_path(tmp_path / "out", "run-2").exists()


def test_dask_reports_failures_without_losing_others(tmp_path):
    pytest.importorskip("distributed", reason="Dask is the optional 'cluster' extra (installed by ./run.sh test)")
    jobs = _jobs(2) + [Job("broken", ECHO, {"value": 1.0, "fail_times": 9, "marker": str(tmp_path / "m")})]
    results, errors = run_sweep(jobs, tmp_path / "out", cluster="local", workers=1, retries=0)
    assert set(results) == {"run-0", "run-1"} and list(errors) == ["broken"]


def test_results_are_readable_like_any_new_file(tmp_path):
    """Atomic writes go through mkstemp (mode 0600); the result gets the mode open() would give."""
    import os

    from deepmapping.io.atomic import atomic_write

    mask = os.umask(0)
    os.umask(mask)
    atomic_write(tmp_path / "a.txt", lambda f: f.write(b"x"))
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o666 & ~mask


def test_data_folder_of_an_experiment_on_real_recordings(tmp_path, monkeypatch):
    """An experiment with DATA reads --data, or ../shared/data/<DATA> from where it is run; one
    that simulates its data refuses --data; a missing folder is a one-line error naming it."""
    from types import SimpleNamespace

    from deepmapping.errors import ConfigError
    from deepmapping.experiments import data_folder, experiment_module

    real = SimpleNamespace(DATA="carmen")
    (tmp_path / "logs").mkdir()
    assert data_folder("x", real, tmp_path / "logs") == (tmp_path / "logs").resolve()
    with pytest.raises(ConfigError, match="nowhere: folder not found$"):
        data_folder("x", real, tmp_path / "nowhere")
    monkeypatch.chdir(tmp_path / "logs")
    with pytest.raises(ConfigError, match=r"shared/data/carmen: folder not found \(give the folder with --data\)"):
        data_folder("x", real, None)
    (tmp_path / "shared" / "data" / "carmen").mkdir(parents=True)
    assert data_folder("x", real, None) == (tmp_path / "shared" / "data" / "carmen").resolve()
    assert data_folder("1d", experiment_module("1d"), None) is None
    with pytest.raises(ConfigError, match="experiment '1d' reads no data folder"):
        data_folder("1d", experiment_module("1d"), tmp_path)
