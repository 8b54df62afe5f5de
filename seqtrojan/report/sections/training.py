"""Training: every headline run's grid, budget and speed, and the configs it was trained with."""

from __future__ import annotations

import html
from pathlib import Path

from seqtrojan.artifacts import RunSummary


def training_section(runs: dict[str, RunSummary | None], configs: dict[str, Path]) -> list[str]:
    """``runs``: run name -> its summary (None: not trained yet); ``configs``: title -> a YAML file to show (those
    that exist are shown, folded)."""
    parts = [
        "<h2>Training</h2><table><tr><th class='l'>agent</th><th class='l'>final grid</th>"
        "<th>env steps</th><th>minutes</th><th>mean steps/s</th><th>final stage</th></tr>"
    ]
    for role, summary in runs.items():
        if summary:
            parts.append(
                f"<tr><td class='l'>{role}</td><td class='l'>{summary.grid}</td><td>{summary.env_steps:,}</td>"
                f"<td>{summary.minutes:.1f}</td><td>{summary.sps:,.0f}</td><td>{summary.stage}</td></tr>"
            )
    parts.append("</table>")
    for title, path in configs.items():
        if path.exists():
            parts.append(f"<details><summary>{title}</summary><pre>{html.escape(path.read_text())}</pre></details>")
    return parts
