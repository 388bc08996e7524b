"""`deepmapping experiment`: a sweep with a progress bar, then where the report is."""

from __future__ import annotations

from pathlib import Path

import typer

from deepmapping.experiments import data_folder, experiment_module
from deepmapping.experiments.runner import run_experiment


def run_experiment_cli(name: str, out: Path, quick: bool, jobs: int | None, threads: int, cluster: str | None,
                       retries: int, only: str | None = None, data: Path | None = None) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from deepmapping.cli.progress import console

    data_folder(name, experiment_module(name), data)  # an unknown name or a missing folder fails before anything is written
    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[info]}"), TimeElapsedColumn()]
    with Progress(*columns, console=console) as bar:
        task = bar.add_task(f"experiment {name}", total=None, info="")

        def progress(done: int, total: int, key: str) -> None:
            bar.update(task, completed=done, total=total, info=key)

        outcome = run_experiment(name, out, quick=quick, workers=jobs, threads=threads, cluster=cluster,
                                 retries=retries, progress=progress, only=only, data=data)
    n_err = len(outcome["errors"])
    if n_err:
        console.print(f"[yellow]{n_err} run(s) failed[/] (listed in the report); rerun the same command to retry them")
    typer.echo(f"report: {outcome['report']} ({outcome['wall_s']:.0f} s)")
    if n_err:
        raise typer.Exit(1)
