"""Sequence models compared: one row per cell, then what each conjecture's measurement shows."""

from __future__ import annotations

import html
from pathlib import Path

from seqtrojan.experiment_results import CellsResult, CellSummary
from seqtrojan.report.markup import CSS, ci, img
from seqtrojan.stats import OverSeeds, Rate


def _seeds(x: OverSeeds, pooled: Rate | None = None) -> str:
    text = html.escape(x.text()).replace("±", "&plusmn;")
    return text + (f" {ci(pooled.interval)}" if pooled is not None else "")


def _units(s: CellSummary) -> str:
    return ", ".join("none" if k is None else str(k) for k in s.units_needed)


def _auc(s: CellSummary) -> str:
    if s.auc is None or s.auc_interval is None:
        return "not measured"
    return f"{s.auc:.3f} <span class='note'>[{s.auc_interval[0]:.3f}, {s.auc_interval[1]:.3f}]</span>"


def cells_page(result: CellsResult, figure: Path) -> str:
    """A self-contained page with the section alone (``seqtrojan cells`` writes it as report.html)."""
    head = f"<!doctype html><html><head><meta charset='utf-8'><title>seqtrojan cells</title><style>{CSS}</style>"
    return head + "</head><body>" + "".join(cells_section(result, figure)) + "</body></html>"


def cells_section(result: CellsResult, figure: Path) -> list[str]:
    monitors = sorted({m for s in result.summaries for m in s.monitor_detection})
    parts = [
        "<h2>Sequence models: LSTM, peephole LSTM, GRU, Transformer</h2>",
        f"<p class='note'>Scale <b>{html.escape(result.scale)}</b>, measured on {html.escape(result.grid)}; the "
        f"Transformer attends over a window of {result.window} steps. Each figure is the mean &plusmn; sd over the "
        "backdoored agents' training seeds, then the 95% Wilson interval of the episodes pooled over seeds. "
        "Unintentional activation: the mean over the sweep's grid configs. Units to switch: per seed, the fewest "
        "goal units that, set to their trojan level, send the agent to the adversary's goal in at least half the "
        "normal episodes ('none': no tried count did).</p>",
        img(figure),
        "<table><tr><th class='l'>cell</th><th>clean model success</th><th>backdoored: clean success</th>"
        "<th>attack success</th><th>unintentional activation</th>"
        + "".join(f"<th>{html.escape(m)} detection</th>" for m in monitors)
        + "<th>units to switch</th><th>weight detector ROC-AUC</th></tr>",
    ]
    for s in result.summaries:
        parts.append(
            f"<tr><td class='l'>{html.escape(s.cell)}</td><td>{_seeds(s.clean_model_success)}</td>"
            f"<td>{_seeds(s.clean_success)}</td><td>{_seeds(s.attack_success, s.attack_success_pooled)}</td>"
            f"<td>{_seeds(s.unintentional_mean, s.unintentional_pooled)}</td>"
            + "".join(f"<td>{_seeds(s.monitor_detection[m])}</td>" for m in monitors)
            + f"<td>{_units(s)}</td><td>{_auc(s)}</td></tr>"
        )
    parts.append("</table>")
    bins = sorted({(lo, hi) for s in result.summaries for lo, hi, _, _ in s.persistence})
    parts.append(
        "<h3>Persistence: the adversary's share of goals reached k steps after the trigger</h3><table><tr>"
        "<th class='l'>cell</th>" + "".join(f"<th>k = {lo}-{hi}</th>" for lo, hi in bins) + "</tr>"
    )
    for s in result.summaries:
        cells = {(lo, hi): _seeds(x, pooled) for lo, hi, x, pooled in s.persistence}
        parts.append(
            f"<tr><td class='l'>{html.escape(s.cell)}</td>"
            + "".join(f"<td>{cells.get(b, '')}</td>" for b in bins)
            + "</tr>"
        )
    parts.append("</table>")
    return ["".join(parts)]
