"""The attack x defense matrix: each attack alone, then against each defense."""

from __future__ import annotations

import html
from pathlib import Path

from seqtrojan.experiment_results import MatrixCell, MatrixResult
from seqtrojan.report.markup import CSS, ci, img, rate
from seqtrojan.stats import OverSeeds, Rate


def _seeds(x: OverSeeds | None, pooled: Rate | None = None) -> str:
    if x is None:
        return ""
    text = html.escape(x.text()).replace("±", "&plusmn;")
    return text + (f" {ci(pooled.interval)}" if pooled is not None else "")


def _cell_row(c: MatrixCell) -> str:
    auc = ""
    if c.auc is not None and c.auc_interval is not None:
        auc = f"{c.auc:.3f} <span class='note'>[{c.auc_interval[0]:.3f}, {c.auc_interval[1]:.3f}]</span>"
    return (
        f"<tr><td class='l'>{html.escape(c.attack)}</td><td class='l'>{html.escape(c.defense)}</td>"
        f"<td class='l'>{c.kind}</td><td>{_seeds(c.attack_success, c.attack_success_pooled)}</td>"
        f"<td>{_seeds(c.clean_success)}</td><td>{_seeds(c.detection, c.detection_pooled)}</td>"
        f"<td>{_seeds(c.false_alarm, c.false_alarm_pooled)}</td><td>{auc}</td></tr>"
    )


def matrix_page(result: MatrixResult, figure: Path) -> str:
    """A self-contained page with the matrix section alone (``seqtrojan matrix`` writes it as report.html)."""
    head = f"<!doctype html><html><head><meta charset='utf-8'><title>seqtrojan matrix</title><style>{CSS}</style>"
    return head + "</head><body>" + "".join(matrix_section(result, figure)) + "</body></html>"


def matrix_section(result: MatrixResult, figure: Path) -> list[str]:
    parts = [
        "<h2>Attacks against defenses: the matrix</h2>",
        f"<p class='note'>Scale <b>{html.escape(result.scale)}</b>, measured on {html.escape(result.grid)}. Each "
        "figure is the mean &plusmn; sd over the attack's training seeds, then in brackets the 95% Wilson interval "
        "of the episodes pooled over seeds. Online defenses are calibrated on each agent's own clean episodes at "
        "their false-alarm target; their attack success is with the state reset on an alarm. Offline detectors "
        "rank the attack's models against the clean models (ROC-AUC with its interval; few models give wide "
        "intervals).</p>",
        img(figure),
        "<table><tr><th class='l'>attack</th><th>seeds</th><th>attack success</th><th>clean success</th>"
        "<th>unintentional activation</th><th>trigger seen by chance</th></tr>",
    ]
    for a in result.attacks:
        natural = rate(a.natural_trigger, 4) if a.natural_trigger is not None else "not measured"
        parts.append(
            f"<tr><td class='l' title='{html.escape(a.description)}'>{html.escape(a.attack)}</td>"
            f"<td>{len(a.seeds)}</td><td>{_seeds(a.attack_success, a.attack_success_pooled)}</td>"
            f"<td>{_seeds(a.clean_success, a.clean_success_pooled)}</td>"
            f"<td>{_seeds(a.unintentional, a.unintentional_pooled)}</td><td>{natural}</td></tr>"
        )
    parts.append("</table>")
    parts.append(
        "<table><tr><th class='l'>attack</th><th class='l'>defense</th><th class='l'>kind</th>"
        "<th>attack success (defended)</th><th>clean success (defended)</th><th>detection</th>"
        "<th>false alarms</th><th>ROC-AUC</th></tr>" + "".join(_cell_row(c) for c in result.cells) + "</table>"
    )
    return ["".join(parts)]
