"""The reproduction report: one self-contained HTML file (figures embedded), our numbers beside the paper's.

:func:`build_report` reads what :mod:`seqtrojan.experiments.reproduce` wrote under its output folder, typed,
through :class:`seqtrojan.artifacts.RunLayout` (one loader per stage), and lays out the sections of
:mod:`seqtrojan.report.sections`, each of which takes typed results. Every section is optional, so a partial
reproduction still gives a report of what exists.
"""

from __future__ import annotations

import datetime as _dt
import html
from pathlib import Path
from typing import Any

from seqtrojan.artifacts import RunLayout
from seqtrojan.evaluation.seeds import summarise_over_seeds
from seqtrojan.paper import paper_results
from seqtrojan.report.markup import CSS
from seqtrojan.report.sections.analysis import analysis_section
from seqtrojan.report.sections.cells import cells_section
from seqtrojan.report.sections.curves import curves_section
from seqtrojan.report.sections.defense import defense_section
from seqtrojan.report.sections.headline import headline_section
from seqtrojan.report.sections.leaderboard import leaderboard_section
from seqtrojan.report.sections.machine import machine_section
from seqtrojan.report.sections.tables import tables_section
from seqtrojan.report.sections.tradeoff import tradeoff_section
from seqtrojan.report.sections.training import training_section
from seqtrojan.report.sections.trajectory import trajectory_section


def build_report(out: Path, scale: str, machine: dict[str, Any]) -> Path:
    layout = RunLayout(out)
    rows = layout.evaluation()
    cells = summarise_over_seeds(rows)
    paper = paper_results()
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>seqtrojan reproduction</title>",
        f"<style>{CSS}</style></head><body>",
        "<h1>Persistent backdoors in recurrent agents: reproduction</h1>",
        f"<p class='note'>{html.escape(paper['source'])}. Scale <b>{html.escape(scale)}</b>, generated "
        f"{_dt.datetime.now():%Y-%m-%d %H:%M} by seqtrojan {html.escape(str(machine.get('seqtrojan')))}. Every rate "
        "is over independent batched episodes with a 95% Wilson interval; cells whose paper value lies outside "
        "our interval are shaded.</p>",
    ]
    backdoor = layout.run_summary("backdoor")
    parts += headline_section(cells, backdoor.grid if backdoor else None, paper)
    parts += tables_section(cells, rows)
    parts += curves_section(layout.curves(), layout.curves_figure)
    parts += trajectory_section(layout.trajectory(), layout.trajectory_figure)
    analysis = layout.analysis()
    if analysis:
        parts += analysis_section(analysis, layout.analysis_figures)
    tradeoff = layout.tradeoff()
    if tradeoff:
        parts += tradeoff_section(tradeoff)
    defense, detection = layout.defense(), layout.detection()
    if defense or detection:
        parts += defense_section(defense, detection)
    leaderboard = layout.leaderboard()
    if leaderboard:
        parts += leaderboard_section(leaderboard)
    cells_result = layout.cells()
    if cells_result:
        parts += cells_section(cells_result, layout.cells_figure)
    configs = {f"{role} agent config": layout.run(role) / "config.yaml" for role in ("clean", "backdoor")}
    parts += training_section(layout.headline_runs(), {**configs, "reproduction config": layout.config})
    parts += machine_section(machine, layout.stage_seconds())
    parts.append("</body></html>")
    layout.report.write_text("\n".join(parts))
    return layout.report
