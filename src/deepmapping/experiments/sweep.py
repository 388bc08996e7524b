"""Run a sweep's jobs in parallel: a local process pool by default, a Dask cluster on request.

Every finished run's result is written atomically to ``<out>/runs/<key>.json`` as soon as it
arrives; a restarted sweep loads those and runs only the rest. A run that raises is retried
``retries`` times, then recorded in ``<out>/runs/<key>.failed.json`` (with its traceback) and
reported; the other runs go on. Failed runs are tried again when the sweep is restarted.
"""

from __future__ import annotations

import json
import os
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path
from typing import Callable

from deepmapping.experiments.base import Job, call_job
from deepmapping.io.atomic import atomic_write

Progress = Callable[[int, int, str], None]  # (done, total, key of the run just finished)


def result_path(out: Path, key: str, failed: bool = False) -> Path:
    return Path(out) / "runs" / (f"{key}.failed.json" if failed else f"{key}.json")


def load_finished(out: Path, jobs: list[Job]) -> dict[str, dict]:
    done = {}
    for job in jobs:
        path = result_path(out, job.key)
        if path.exists():
            try:
                done[job.key] = json.loads(path.read_text())
            except (OSError, ValueError):  # a damaged result is redone
                pass
    return done


def run_sweep(jobs: list[Job], out: str | Path, *, workers: int | None = None, threads: int = 1,
              cluster: str | None = None, retries: int = 1, progress: Progress | None = None) -> tuple[dict, dict]:
    """Run ``jobs``; return (results by key, error messages by key) over all jobs of the sweep."""
    keys = [j.key for j in jobs]
    if len(set(keys)) != len(keys):
        raise ValueError("job keys must be unique")
    out = Path(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    results = load_finished(out, jobs)
    todo = [j for j in jobs if j.key not in results]
    errors: dict[str, str] = {}

    def record(job: Job, value: dict | None, error: str | None) -> None:
        if error is None:
            results[job.key] = value
            _write_json(result_path(out, job.key), value)
            result_path(out, job.key, failed=True).unlink(missing_ok=True)
        else:
            errors[job.key] = error.strip().splitlines()[-1]
            _write_json(result_path(out, job.key, failed=True), {"key": job.key, "traceback": error})
        if progress is not None:
            progress(len(results) + len(errors), len(jobs), job.key)

    if todo:
        runner = _run_dask if cluster else _run_local
        runner(todo, record, workers=workers, threads=threads, cluster=cluster, retries=retries)
    return results, errors


def _write_json(path: Path, value: dict) -> None:
    text = json.dumps(value, indent=1, default=_jsonable).encode()
    atomic_write(path, lambda f: f.write(text))


def _jsonable(x):
    import numpy as np

    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"not JSON-serializable: {type(x).__name__}")


def _guarded(func: str, kwargs: dict, threads: int) -> tuple[dict | None, str | None]:
    try:
        return call_job(func, kwargs, threads), None
    except Exception:  # reported per run; the sweep goes on
        return None, traceback.format_exc()


def _run_local(todo, record, *, workers, threads, cluster, retries):
    workers = workers or max(1, (os.cpu_count() or 1) // threads)
    if workers == 1:  # in this process: simplest to debug, no pickling
        for job in todo:
            for _ in range(retries + 1):
                value, error = _guarded(job.func, job.kwargs, threads)
                if error is None:
                    break
            record(job, value, error)
        return
    tries = {j.key: 0 for j in todo}
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        pending = {pool.submit(_guarded, j.func, j.kwargs, threads): j for j in todo}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                job = pending.pop(fut)
                try:
                    value, error = fut.result()
                except Exception:  # the worker process died (e.g. killed for memory)
                    value, error = None, traceback.format_exc()
                if error is not None and tries[job.key] < retries:
                    tries[job.key] += 1
                    pending[pool.submit(_guarded, job.func, job.kwargs, threads)] = job
                    continue
                record(job, value, error)


def _run_dask(todo, record, *, workers, threads, cluster, retries):
    """On a Dask cluster (``pip install 'deepmapping[cluster]'``): ``cluster`` is the scheduler's
    address (tcp://host:8786), or "local" for a LocalCluster of ``workers`` processes."""
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        from deepmapping.errors import ConfigError

        raise ConfigError("--cluster needs Dask: pip install 'deepmapping[cluster]'") from None
    local = None
    if cluster == "local":
        local = LocalCluster(n_workers=workers or max(1, (os.cpu_count() or 1) // threads),
                             threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(local or cluster)
    try:
        futures = {client.submit(call_job, j.func, j.kwargs, threads, key=f"deepmapping-{j.key}",
                                 retries=retries, pure=False): j for j in todo}
        for fut in as_completed(futures):
            job = futures[fut]
            if fut.status == "finished":
                record(job, fut.result(), None)
            else:
                exc, tb = fut.exception(), fut.traceback()
                record(job, None, "".join(traceback.format_exception(type(exc), exc, tb)))
    finally:
        client.close()
        if local is not None:
            local.close()
