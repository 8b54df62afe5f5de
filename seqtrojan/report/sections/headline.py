"""The headline: the three agent/env cells of the training configuration, beside the paper."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from seqtrojan.evaluation.seeds import SeedSummary
from seqtrojan.report.sections.tables import evaluation_table, seeds_note


def headline_section(cells: Sequence[SeedSummary], train_grid: str | None, paper: dict[str, Any]) -> list[str]:
    """``train_grid``: the backdoored agent's training grid (None before it has trained); ``paper``: the paper's
    results (seqtrojan.paper.paper_results)."""
    parts = ["<h2>Headline: the training configuration</h2>"]
    if not (train_grid and cells):
        return [*parts, "<p class='note'>(no evaluation yet)</p>"]
    columns = [
        ("clean", "normal", "clean agent, normal env"),
        ("backdoor", "normal", "backdoored agent, normal env"),
        ("backdoor", "trojan", "backdoored agent, trojan env"),
    ]
    parts.append(evaluation_table(cells, columns, [train_grid]))
    parts.append(seeds_note(cells))
    ptc = paper["agents"]["training_config"]
    if train_grid != f"{ptc['size']}x{ptc['size']}/{ptc['holes']}":
        parts.append(
            f"<p class='note'>This scale trains on {train_grid}, not the paper's "
            f"{ptc['size']}x{ptc['size']}/{ptc['holes']}: the paper column is empty where it reports nothing "
            "for this grid. Run <code>seqtrojan reproduce --scale paper</code> for the paper's setting.</p>"
        )
    return parts
