"""Rich progress bars with loss and ETA for the long steps."""

from __future__ import annotations

import contextlib
import math

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

console = Console(stderr=True)


@contextlib.contextmanager
def progress_bar(enabled: bool = True):
    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
    with Progress(*columns, console=console, disable=not enabled, transient=False) as bar:
        cb = Callbacks(bar)
        try:
            yield cb
        finally:
            cb.stop()


class Callbacks:
    """Callbacks for register(): ICP progress, per-epoch loss, periodic ATE.

    One bar per stage (warm start, cold-start placing, training). A stage ends when the next
    one begins: its bar is then shown complete and its clock stops (else the warm start's clock
    would keep counting through the training).
    """

    def __init__(self, bar: Progress):
        self.bar = bar
        self.tasks: dict[str, int] = {}
        self.ate: float | None = None

    def _task(self, name: str, total: int) -> int:
        if name not in self.tasks:
            self.stop(complete=True)  # a new stage: the earlier ones are over
            self.tasks[name] = self.bar.add_task(name, total=total, info="")
        return self.tasks[name]

    def stop(self, complete: bool = False) -> None:
        """Stop the clock of every running stage; ``complete`` also fills its bar (2D ICP reports
        scans 1 ... K-1 of K, so its last report is one short)."""
        for task in self.bar.tasks:
            if task.stop_time is None:
                if complete and task.total is not None:
                    self.bar.update(task.id, completed=task.total)
                self.bar.stop_task(task.id)

    def icp(self, i: int, total: int) -> None:
        self.bar.update(self._task("warm start / ICP", total), completed=i)

    def place(self, placed: int, total: int) -> None:
        self.bar.update(self._task("cold start / placing scans", total), completed=placed)

    def epoch(self, epoch: int, total: int, loss: float) -> None:
        info = f"loss {loss:.4f}" + (f"  ATE {self.ate:.2f}" if self.ate is not None else "")
        self.bar.update(self._task("training", total), completed=epoch, info=info)

    def log(self, row: dict) -> None:
        ate = row.get("ate")
        if ate is not None and not math.isnan(ate):
            self.ate = ate
