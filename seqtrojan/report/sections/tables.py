"""Tables 1 and 2: success over the grid configs, each cell over the training seeds, beside the paper."""

from __future__ import annotations

import html
from collections.abc import Sequence

from seqtrojan.evaluation.results import SweepRow
from seqtrojan.evaluation.seeds import SeedSummary, find_summary
from seqtrojan.report.markup import ci

Column = tuple[str, str, str]
"""(agent role, env, title)"""


def seed_cell(cell: SeedSummary | None) -> str:
    """One seed: the rate and its Wilson interval. Several: mean +- sd over seeds, then each seed's rate."""
    if cell is None:
        return "<td></td>"
    cls = " class='differs'" if cell.differs else ""
    if len(cell.rows) == 1:
        return f"<td{cls}>{cell.mean:.3f} {ci(cell.interval)}</td>"
    each = ", ".join(f"{s:.3f}" for s in cell.successes)
    return f"<td{cls}>{cell.mean:.3f} &plusmn; {cell.sd:.3f} <span class='note'>({each})</span></td>"


def paper_cell(cell: SeedSummary | None) -> str:
    if cell is None or cell.paper is None:
        return "<td class='paper'></td>"
    return f"<td class='paper'>{cell.paper:.3f}</td>"


def evaluation_table(cells: Sequence[SeedSummary], columns: list[Column], configs: list[str]) -> str:
    head = "".join(f"<th>{html.escape(title)}</th><th>paper</th>" for _, _, title in columns)
    body = []
    for config in configs:
        row = "".join(
            seed_cell(find_summary(cells, r, e, config)) + paper_cell(find_summary(cells, r, e, config))
            for r, e, _ in columns
        )
        body.append(f"<tr><td class='l'>{config}</td>{row}</tr>")
    return f"<table><tr><th class='l'>grid</th>{head}</tr>{''.join(body)}</table>"


def seeds_note(cells: Sequence[SeedSummary]) -> str:
    seeds = max((len(c.rows) for c in cells), default=1)
    if seeds == 1:
        return (
            "<p class='note'>One training seed: each cell is that agent's success with its 95% Wilson interval "
            "over the trials. A retrained agent (another seed) can differ by more than this interval.</p>"
        )
    return (
        f"<p class='note'>Over {seeds} training seeds: mean &plusmn; standard deviation of the per-seed success "
        "rates, then each seed's rate. A cell is shaded when the paper's value lies outside every seed's 95% "
        "Wilson interval (the paper reports one training run, so it is compared with what one run gives). "
        "evaluation/summary.json also holds a 95% t-interval for the mean.</p>"
    )


def details_table(rows: Sequence[SweepRow]) -> str:
    head = "<tr><th class='l'>agent</th><th>seed</th><th>env</th><th class='l'>grid</th><th>success</th>"
    head += "<th>95% interval</th><th>hole</th><th>time-out</th><th>wrong goal</th><th>mean length</th>"
    head += "<th>trials</th></tr>"
    body = "".join(
        f"<tr><td class='l'>{r.agent}</td><td>{r.seed}</td><td>{r.env}</td><td class='l'>{r.config}</td>"
        f"<td>{r.success.value:.3f}</td><td>[{r.success.interval[0]:.3f}, {r.success.interval[1]:.3f}]</td>"
        f"<td>{r.hole.value:.3f}</td><td>{r.timeout.value:.3f}</td><td>{r.wrong_goal.value:.3f}</td>"
        f"<td>{r.mean_length:.1f}</td><td>{r.episodes}</td></tr>"
        for r in rows
    )
    return f"<table>{head}{body}</table>"


def tables_section(cells: Sequence[SeedSummary], rows: Sequence[SweepRow]) -> list[str]:
    configs = list(dict.fromkeys(r.config for r in rows))
    both: list[Column] = [("clean", "normal", "clean agent"), ("backdoor", "normal", "backdoored agent")]
    return [
        "<h2>Table 1: success in the normal environment (no trigger)</h2>",
        "<p class='note'>Success = reached the user's goal. The backdoored agent should behave like the "
        "clean one here.</p>",
        evaluation_table(cells, both, configs),
        "<h2>Table 2: success of the backdoored agent in the trojan environment</h2>",
        "<p class='note'>Success = reached the adversary's goal after the trigger was shown (once, for "
        "one step, at a step drawn so that it always comes before a goal can be reached).</p>",
        evaluation_table(cells, [("backdoor", "trojan", "backdoored agent")], configs),
        "<details><summary>Every seed's cell: success, hole-fall, time-out and wrong-goal rates</summary>",
        details_table(rows) + "</details>",
    ]
