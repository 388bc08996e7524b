"""Tables printed by evaluate and demo."""

from __future__ import annotations

from rich.table import Table


def metrics_table(rows: dict[str, dict], title: str = "Evaluation") -> Table:
    """One row per method; the title names the success criterion when the rows share one."""
    limits = {(m.get("success_threshold"), m.get("unit", "")) for m in rows.values()}
    if len(limits) == 1 and None not in next(iter(limits)):
        value, unit = next(iter(limits))
        title = f"{title} (success: ATE < {value:.3g} {unit})"
    table = Table(title=title)
    for col in ("method", "ATE", "point dist.", "rot. RMSE (deg)", "success", "runtime (s)"):
        table.add_column(col, justify="right" if col != "method" else "left")
    for name, m in rows.items():
        unit = m.get("unit", "")
        table.add_row(name, f"{m['ate']:.2f} {unit}", f"{m['point_distance']:.2f} {unit}",
                      f"{m['rotation_rmse_deg']:.2f}", "yes" if m["success"] else "no",
                      f"{m.get('runtime_s', float('nan')):.1f}")
    return table


def relations_table(rows: dict[str, dict], title: str = "Relations (Kümmerle et al. 2009)") -> Table:
    """Translational (m) and rotational (deg) relation errors: mean ± std / median, all, < 10 s, > 10 s."""
    table = Table(title=title)
    for col in ("method", "relations", "all: m", "all: deg", "< 10 s: m", "> 10 s: m", "unmatched"):
        table.add_column(col, justify="right" if col != "method" else "left")

    def cell(s: dict, key: str) -> str:  # key: "trans_{}_m" or "rot_{}_deg"
        if not s.get("count"):
            return "-"
        return f"{s[key.format('mean')]:.3f} ± {s[key.format('std')]:.3f} / {s[key.format('median')]:.3f}"

    for name, m in rows.items():
        r = m["relations"]
        table.add_row(name, str(r["all"].get("count", 0)), cell(r["all"], "trans_{}_m"), cell(r["all"], "rot_{}_deg"),
                      cell(r["short"], "trans_{}_m"), cell(r["long"], "trans_{}_m"), str(r["unmatched"]))
    return table


def print_metrics(console, rows: dict[str, dict], title: str | None = None) -> None:
    """The ATE table for runs with ground truth, the relations table for scored logs."""
    ate = {k: m for k, m in rows.items() if m and "ate" in m}
    rel = {k: m for k, m in rows.items() if m and "relations" in m}
    if ate:
        console.print(metrics_table(ate, **({"title": title} if title else {})))
    if rel:
        console.print(relations_table(rel, **({"title": title} if title else {})))
