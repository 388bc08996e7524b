"""Run a sweep's jobs in parallel: a local process pool by default, a Dask cluster on request.

Every finished run's result is written atomically to ``<out>/runs/<key>.json`` as soon as it
arrives; a restarted sweep loads those and runs only the rest. A run that raises is retried
``retries`` times, then recorded in ``<out>/runs/<key>.failed.json`` (with its traceback) and
reported; the other runs go on. Failed runs are tried again when the sweep is restarted.

Local runs go to worker processes of our own (``_Pool``), not a ProcessPoolExecutor: a worker
that dies (kill -9, the out-of-memory killer) fails only the run it had, as "worker died
(signal 9)", and is replaced; an executor would break and fail every run in flight. The sweep
holds the lock of ``out`` (``io.lock``): a second sweep on the same folder refuses at once.
"""

from __future__ import annotations

import json
import os
import traceback
from collections import deque
from multiprocessing import get_context
from multiprocessing.connection import wait
from pathlib import Path
from typing import Callable

from deepmapping.experiments.base import Job, call_job
from deepmapping.io.atomic import atomic_write, make_folder
from deepmapping.io.lock import folder_lock

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
    out = make_folder(out)
    with folder_lock(out):
        return _sweep(jobs, out, workers, threads, cluster, retries, progress)


def _sweep(jobs, out: Path, workers, threads, cluster, retries, progress) -> tuple[dict, dict]:
    make_folder(out / "runs")
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
    _Pool(workers, threads).run(todo, record, retries)


class _Worker:
    """A spawned process that runs the jobs sent to it, one at a time (imports stay loaded)."""

    def __init__(self, ctx, threads: int):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child, threads), name="deepmapping-sweep-worker")
        self.proc.start()
        child.close()  # the worker's end lives in the worker only: its death is EOF here
        self.job: Job | None = None

    def death(self) -> str:
        """The error of the run this worker had when it died."""
        self.proc.join()
        code = self.proc.exitcode
        how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        return f"RuntimeError: worker died ({how}) while running {self.job.key}\n"

    def stop(self, now: bool = False) -> None:
        try:
            if not now:
                self.conn.send(None)
                self.proc.join(timeout=10)
        except OSError:
            pass
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join()
        self.conn.close()


def _serve(conn, threads: int) -> None:
    """A worker's loop: (func, kwargs) in, (value, traceback) out, until None or the pipe closes."""
    while True:
        try:
            task = conn.recv()
        except EOFError:
            return
        if task is None:
            return
        reply = _guarded(*task, threads)
        try:
            conn.send(reply)
        except Exception:  # the result cannot be pickled: reported as that run's error
            conn.send((None, traceback.format_exc()))


class _Pool:
    """``workers`` processes; each job goes to an idle one; a dead worker is replaced."""

    def __init__(self, workers: int, threads: int):
        self.size, self.threads, self.ctx = workers, threads, get_context("spawn")
        self.idle: list[_Worker] = []
        self.busy: list[_Worker] = []

    def run(self, todo: list[Job], record, retries: int) -> None:
        queue, tries = deque(todo), {j.key: 0 for j in todo}
        try:
            while queue or self.busy:
                while queue and len(self.busy) < self.size:
                    self._start(queue.popleft())
                for job, value, error in self._finished():
                    if error is not None and tries[job.key] < retries:
                        tries[job.key] += 1
                        queue.append(job)
                    else:
                        record(job, value, error)
        finally:
            for w in self.busy:
                w.stop(now=True)
            for w in self.idle:
                w.stop()

    def _start(self, job: Job) -> None:
        while True:
            w = self.idle.pop() if self.idle else _Worker(self.ctx, self.threads)
            try:
                w.conn.send((job.func, job.kwargs))
                break
            except OSError:  # died while idle: take another
                w.stop(now=True)
        w.job = job
        self.busy.append(w)

    def _finished(self) -> list[tuple[Job, dict | None, str | None]]:
        """Wait for one or more busy workers to answer or die: (job, value, error) each."""
        ready = wait([w.conn for w in self.busy])
        done = []
        for w in [w for w in self.busy if w.conn in ready]:
            self.busy.remove(w)
            try:
                value, error = w.conn.recv()
                self.idle.append(w)
            except (EOFError, OSError):  # the process died (kill -9, out of memory, a crash in C code)
                value, error = None, w.death()
                w.stop(now=True)
            done.append((w.job, value, error))
            w.job = None
        return done


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
