"""Markdown reports with embedded pictures, and the plots the paper's figures use."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from deepmapping.io.atomic import atomic_write


def markdown_table(headers: list[str], rows: list[list]) -> str:
    def cell(v):
        if isinstance(v, float):
            return "-" if math.isnan(v) else f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def write_report(out: Path, title: str, sections: list[str]) -> Path:
    """``out/report.md``: the title, then each section (markdown) separated by blank lines."""
    text = "\n\n".join([f"# {title}", *sections]) + "\n"
    path = Path(out) / "report.md"
    atomic_write(path, lambda f: f.write(text.encode()))
    return path


def image(name: str, caption: str = "") -> str:
    """Markdown that embeds the picture ``name`` (relative to report.md)."""
    return f"![{caption or name}]({name})"


def box_plot(path: Path, data: dict[str, list[float]], ylabel: str, title: str = "", log: bool = True,
             threshold: float | None = None) -> Path:
    """A box plot per method (the paper's Figs. 6 and 9), on a log axis by default."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(data)
    values = [np.clip(np.asarray(data[n], float), 1e-6, None) for n in names]
    fig, ax = plt.subplots(figsize=(1.4 * len(names) + 2.5, 4.0))
    ax.boxplot(values, showfliers=True)
    ax.set_xticks(range(1, len(names) + 1), names, rotation=20, ha="right")
    if log:
        ax.set_yscale("log")
    if threshold is not None:
        ax.axhline(threshold, color="tab:red", ls="--", lw=1, label=f"success threshold ({threshold:g})")
        ax.legend(loc="upper left", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
    return Path(path)


def save_figure(fig, path: Path) -> None:
    """Save a matplotlib figure atomically as PNG and close it."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    atomic_write(path, lambda f: f.write(buf.getvalue()))


def runs_by(results: dict[str, dict], field: str, names) -> dict[str, list[dict]]:
    """The run records grouped by ``field`` (a method, a variant), each group sorted by trajectory."""
    return {n: sorted((r for r in results.values() if r.get(field) == n), key=lambda r: r["trajectory"])
            for n in names}


def summary(values: list[float]) -> dict:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], float)
    if v.size == 0:
        return {"median": float("nan"), "mean": float("nan"), "n": 0}
    return {"median": float(np.median(v)), "mean": float(v.mean()), "n": int(v.size)}
