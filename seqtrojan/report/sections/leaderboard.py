"""The detection benchmark's leaderboard (``seqtrojan zoo detect --out S``: ``S/leaderboard.json``): every detector's
scores on the test and holdout splits, then the same by factor, the models left out and why."""

from __future__ import annotations

import html

from seqtrojan.benchmark.leaderboard import Leaderboard
from seqtrojan.benchmark.scoring import Metric, Scores
from seqtrojan.report.markup import CSS


def _metric(m: Metric) -> str:
    """``0.889 [0.59, 0.98]``, the interval as a note; ``n/a`` where the split cannot give it (one label only)."""
    if m.value is None:
        return "n/a"
    if m.low is None or m.high is None:
        return f"{m.value:.3f}"
    return f"{m.value:.3f} <span class='note'>[{m.low:.2f}, {m.high:.2f}]</span>"


def _cells(s: Scores) -> str:
    return (
        f"<td>{s.models} ({s.poisoned})</td><td>{_metric(s.roc_auc_newcombe)}</td><td>{_metric(s.cross_entropy)}</td>"
        f"<td>{_metric(s.brier)}</td>"
    )


def leaderboard_page(board: Leaderboard) -> str:
    """A self-contained page with the section alone (``seqtrojan zoo detect --out S`` writes it as S/report.html)."""
    head = f"<!doctype html><html><head><meta charset='utf-8'><title>seqtrojan leaderboard</title><style>{CSS}</style>"
    return head + "</head><body>" + "".join(leaderboard_section(board)) + "</body></html>"


def leaderboard_section(board: Leaderboard) -> list[str]:
    """The section's HTML parts: per detector and split the models (poisoned), ROC-AUC with Newcombe's interval,
    cross-entropy and Brier score with their bootstrap intervals, milliseconds per model and answers over the
    budget; the same by factor (folded); the models rejected or left out, with their reasons."""
    counts = board.models
    parts = [
        "<h2>Offline detection: the benchmark leaderboard</h2>",
        f"<p class='note'>Zoo <b>{html.escape(board.zoo)}</b>: train {counts.get('train', 0)}, test "
        f"{counts.get('test', 0)}, holdout {counts.get('holdout', 0)} models. Each detector is fitted on the train "
        "split and sees of a model only its network and the clean env (never the trigger or the attack). ROC-AUC "
        "with Newcombe's 95% interval; cross-entropy and Brier score with 95% bootstrap intervals over models (a "
        "constant answer of one half scores 0.693 and 0.250); seconds per model exclude fitting. Holdout holds "
        "factor values (cells, attacks, architectures) the train split never shows.</p>",
        "<table><tr><th class='l'>detector</th><th class='l'>split</th><th>models (poisoned)</th>"
        "<th>ROC-AUC [Newcombe]</th><th>cross-entropy</th><th>Brier</th><th>ms per model</th>"
        "<th>over budget</th></tr>",
    ]
    for d in board.detectors:
        for r in d.splits:
            ms = 1000 * (r.scores.runtime_s.value or 0.0)
            parts.append(
                f"<tr><td class='l' title='{html.escape(d.description)}'>{html.escape(d.detector)}</td>"
                f"<td class='l'>{html.escape(r.split)}</td>{_cells(r.scores)}<td>{ms:.1f}</td>"
                f"<td>{d.over_budget}</td></tr>"
            )
    parts.append("</table>")
    parts += _by_factor(board)
    for title, rows in (("rejected (unreadable or tampered)", board.rejected),
                        ("excluded (backdoor not working or task not learned)", board.excluded)):  # fmt: skip
        if rows:
            items = "".join(f"<li>{html.escape(r.model)}: {html.escape(r.reason)}</li>" for r in rows)
            parts.append(f"<details><summary>{len(rows)} model(s) {title}</summary><ul>{items}</ul></details>")
    return ["".join(parts)]


def _by_factor(board: Leaderboard) -> list[str]:
    """Per detector, split, factor and value: an attack value's poisoned models against every clean model."""
    rows = [
        f"<tr><td class='l'>{html.escape(d.detector)}</td><td class='l'>{html.escape(r.split)}</td>"
        f"<td class='l'>{html.escape(factor)}</td><td class='l'>{html.escape(value)}</td>{_cells(s)}</tr>"
        for d in board.detectors
        for r in d.splits
        for factor, values in sorted(r.by_factor.items())
        for value, s in sorted(values.items())
    ]
    if not rows:
        return []
    return [
        "<details><summary>The same by factor (env, cell, widths, attack)</summary><table><tr>"
        "<th class='l'>detector</th><th class='l'>split</th><th class='l'>factor</th><th class='l'>value</th>"
        "<th>models (poisoned)</th><th>ROC-AUC [Newcombe]</th><th>cross-entropy</th><th>Brier</th></tr>"
        + "".join(rows)
        + "</table></details>"
    ]
