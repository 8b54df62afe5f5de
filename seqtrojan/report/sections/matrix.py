"""The attack x defense matrix: each attack alone, then against each defense."""

from __future__ import annotations

import html
from pathlib import Path

from seqtrojan.arms_race import WORKS_AT, BestDefense, WorstCase, matrix_answer
from seqtrojan.experiment_results import MatrixCell, MatrixResult
from seqtrojan.report.markup import CSS, ci, img, rate
from seqtrojan.stats import OverSeeds, Rate


def _seeds(x: OverSeeds | None, pooled: Rate | None = None) -> str:
    if x is None:
        return ""
    text = html.escape(x.text()).replace("±", "&plusmn;")
    return text + (f" {ci(pooled.interval)}" if pooled is not None else "")


def _cell_row(c: MatrixCell) -> str:
    auc = _auc(c)
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
    parts += _answer(result)
    return ["".join(parts)]


def _auc(c: MatrixCell) -> str:
    if c.auc is None or c.auc_interval is None:
        return ""
    return f"{c.auc:.3f} <span class='note'>[{c.auc_interval[0]:.3f}, {c.auc_interval[1]:.3f}]</span>"


def _worst_row(w: WorstCase) -> str:
    head = f"<tr><td class='l'>{html.escape(w.defense)}</td><td class='l'>{w.kind}</td><td>{w.tried} ({w.working})</td>"
    c = w.worst
    if c is None:
        return head + "<td class='l' colspan='6'>no working backdoor tried</td></tr>"
    return (
        head + f"<td class='l'>{html.escape(c.attack)}</td><td>{_seeds(c.attack_success, c.attack_success_pooled)}</td>"
        f"<td>{_seeds(c.clean_success)}</td><td>{_seeds(c.false_alarm, c.false_alarm_pooled)}</td>"
        f"<td>{_seeds(c.detection, c.detection_pooled)}</td><td>{_auc(c)}</td></tr>"
    )


def _best_row(b: BestDefense) -> str:
    head = f"<tr><td class='l'>{html.escape(b.attack)}</td><td>{_seeds(b.undefended, b.undefended_pooled)}</td>"
    c = b.best
    if c is None:
        return head + "<td class='l' colspan='3'>no acting defense tried</td></tr>"
    return (
        head + f"<td class='l'>{html.escape(c.defense)}</td>"
        f"<td>{_seeds(c.attack_success, c.attack_success_pooled)}</td><td>{_seeds(c.clean_success)}</td></tr>"
    )


def _answer(result: MatrixResult) -> list[str]:
    """The answer tables (:mod:`seqtrojan.arms_race`): each defense by its worst case, each attack by
    its best defense."""
    worst, best = matrix_answer(result)
    return [
        "<h3>Every defense against the worst attack tried on it</h3>",
        f"<p class='note'>A defense is judged by the worst of the attacks tried on it whose backdoor works "
        f"(undefended attack success &ge; {WORKS_AT} on average over seeds), the adaptive ones built against it "
        "among them: an acting defense (a monitor with its reset, a mitigation) by the highest attack success it "
        "leaves, an offline detector by its lowest ROC-AUC. Brackets after the defense's count: the working "
        "attacks.</p>",
        "<table><tr><th class='l'>defense</th><th class='l'>kind</th><th>attacks tried (working)</th>"
        "<th class='l'>worst case</th><th>attack success (defended)</th><th>clean success (defended)</th>"
        "<th>false alarms</th><th>detection</th><th>ROC-AUC</th></tr>" + "".join(map(_worst_row, worst)) + "</table>",
        "<h3>Every working attack against the defense that stops it best</h3>",
        "<table><tr><th class='l'>attack</th><th>undefended attack success</th><th class='l'>best acting defense</th>"
        "<th>attack success (defended)</th><th>clean success (defended)</th></tr>"
        + "".join(map(_best_row, best))
        + "</table>",
    ]
