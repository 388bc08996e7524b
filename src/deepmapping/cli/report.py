"""Tables printed by evaluate and demo."""

from __future__ import annotations

from rich.table import Table


def metrics_table(rows: dict[str, dict], title: str = "Evaluation") -> Table:
    table = Table(title=title)
    for col in ("method", "ATE", "point dist.", "rot. RMSE (deg)", "success", "runtime (s)"):
        table.add_column(col, justify="right" if col != "method" else "left")
    for name, m in rows.items():
        unit = m.get("unit", "")
        table.add_row(name, f"{m['ate']:.2f} {unit}", f"{m['point_distance']:.2f} {unit}",
                      f"{m['rotation_rmse_deg']:.2f}", "yes" if m["success"] else "no",
                      f"{m.get('runtime_s', float('nan')):.1f}")
    return table
