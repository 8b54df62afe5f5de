"""Sweep results as tables beside the paper's numbers: a rich table for the terminal, rows for reports."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence

from rich.table import Table

from seqtrojan.evaluation.results import SweepRow


def sweep_columns(rows: Sequence[SweepRow]) -> list[tuple[str, str, str]]:
    """(agent name, label, env) in first-seen order."""
    return list(OrderedDict(((r.agent, r.label, r.env), None) for r in rows))


def sweep_grid(rows: Sequence[SweepRow]) -> tuple[list[str], list[tuple[str, str, str]], dict]:
    """Configs (rows), columns, and a lookup (config, column) -> SweepRow."""
    configs = list(OrderedDict((r.config, None) for r in rows))
    columns = sweep_columns(rows)
    cells = {(r.config, (r.agent, r.label, r.env)): r for r in rows}
    return configs, columns, cells


def format_rate(row: SweepRow | None) -> str:
    """Success and the larger half-width of its 95% interval (the exact interval is in the JSON and CSV)."""
    if row is None:
        return ""
    low, high = row.success.interval
    rate = row.success.value
    return f"{rate:.3f} ±{max(rate - low, high - rate):.3f}"


def format_paper(row: SweepRow | None) -> str:
    return "" if row is None or row.paper is None else f"{row.paper:.3f}"


def sweep_table(rows: Sequence[SweepRow], title: str = "Success rate (ours ± 95% CI | paper)") -> Table:
    configs, columns, cells = sweep_grid(rows)
    table = Table(title=title)
    table.add_column("grid", justify="right")
    for name, label, env in columns:
        table.add_column(f"{name} ({label})\n{env} env", justify="right")
        table.add_column("paper", justify="right", style="dim")
    for config in configs:
        values = []
        for column in columns:
            row = cells.get((config, column))
            values += [format_rate(row), format_paper(row)]
        table.add_row(config, *values)
    return table
