"""``run_experiment``: the jobs of an experiment through the sweep, then its report."""

from __future__ import annotations

import fnmatch
import json
import time
from pathlib import Path

from deepmapping.errors import ConfigError
from deepmapping.experiments import data_folder, experiment_module
from deepmapping.experiments.sweep import load_finished, run_sweep
from deepmapping.io.atomic import atomic_write, make_folder
from deepmapping.io.lock import folder_lock


def run_experiment(name: str, out: str | Path, *, quick: bool = False, workers: int | None = None,
                   threads: int = 1, cluster: str | None = None, retries: int = 1, progress=None,
                   only: str | None = None, data: str | Path | None = None) -> dict:
    """Run experiment ``name`` into ``out``; return {"report", "results", "errors", "wall_s"}.

    Finished runs in ``out/runs`` are kept and not redone; the report is rewritten from all
    results each time (runs that failed are listed in it). ``only``: a shell pattern; only the
    runs whose key matches it are run (the report uses every finished run all the same).
    ``data``: the folder of real recordings an experiment on them reads (default
    ``../shared/data/<its DATA>``; see :func:`deepmapping.experiments.data_folder`).
    """
    module = experiment_module(name)
    folder = data_folder(name, module, data)
    jobs = module.jobs(quick) if folder is None else module.jobs(quick, str(folder))
    chosen = [j for j in jobs if only is None or fnmatch.fnmatchcase(j.key, only)]
    if not chosen:
        raise ConfigError(f"--only {only!r} matches none of the {len(jobs)} runs of experiment {name}")
    out = make_folder(out)
    with folder_lock(out):  # a second command on this folder refuses (FolderBusy)
        t0 = time.perf_counter()
        _, errors = run_sweep(chosen, out, workers=workers, threads=threads, cluster=cluster, retries=retries,
                              progress=progress)
        results = load_finished(out, jobs)
        wall = time.perf_counter() - t0
        settings = {"experiment": name, "quick": quick, "jobs": len(jobs), "only": only, "workers": workers,
                    "threads": threads, "cluster": cluster, "sweep_wall_s": wall, "failed": sorted(errors)}
        if folder is not None:
            settings["data"] = str(folder)
        atomic_write(out / "experiment.json", lambda f: f.write(json.dumps(settings, indent=1).encode()))
        report = module.report(out, results, quick)
        if errors:
            lines = "\n".join(f"- `{k}`: {msg} (runs/{k}.failed.json)" for k, msg in sorted(errors.items()))
            text = Path(report).read_text() + f"\n## Failed runs ({len(errors)} of {len(jobs)})\n\n{lines}\n"
            atomic_write(report, lambda f: f.write(text.encode()))
    return {"report": report, "results": results, "errors": errors, "wall_s": wall}
