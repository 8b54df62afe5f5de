"""The adversary's trade-off: a penalty on unintentional activation."""

from __future__ import annotations

import html

from seqtrojan.experiment_results import TradeoffResult
from seqtrojan.report.markup import rate
from seqtrojan.stats import OverSeeds


def _spread(x: OverSeeds, digits: int = 3) -> str:
    return html.escape(x.text(digits)).replace("±", "&plusmn;")


def tradeoff_section(t: TradeoffResult) -> list[str]:
    cfg = t.config
    parts = [
        "<h2>The adversary's trade-off: a penalty on unintentional activation</h2>",
        "<p class='note'>Backdoored agents that differ only in the reward for reaching the adversary's goal while "
        "the user's goal is correct (<code>env.rewards.false_activation</code>; -1 is the ordinary wrong-goal "
        f"reward), {cfg.seeds} training seed(s) each. Success on the training grid; activation = "
        f"normal-env episodes (no trigger) over {html.escape(cfg.configs)} configs ({cfg.episodes} per "
        "config) that ended at the adversary's goal; recall of the agent as a trigger detector over the same "
        "configs.</p>",
    ]
    if t.penalties:
        parts.append(
            "<table><tr><th>false-activation reward</th><th>seeds</th><th>normal success</th><th>trojan success</th>"
            "<th>unintentional activation</th><th>recall</th></tr>"
        )
        for p in t.penalties:
            parts.append(
                f"<tr><td>{p.penalty:g}</td><td>{p.seeds}</td><td>{_spread(p.normal_success)}</td>"
                f"<td>{_spread(p.trojan_success)}</td><td>{_spread(p.activation, 4)}</td>"
                f"<td>{_spread(p.recall)}</td></tr>"
            )
        parts.append("</table><details><summary>every agent, with 95% intervals</summary>")
    parts.append(
        "<table><tr><th>false-activation reward</th><th>seed</th><th>normal success [95% CI]</th>"
        "<th>trojan success [95% CI]</th><th>unintentional activation [95% CI]</th><th>recall</th>"
        "<th>precision</th><th class='l'>agent</th></tr>"
    )
    for a in t.agents:
        d = a.detection
        parts.append(
            f"<tr><td>{a.penalty:g}</td><td>{a.seed}</td><td>{rate(a.normal_success)}</td>"
            f"<td>{rate(a.trojan_success)}</td><td>{rate(a.activation, 4)}</td><td>{d.recall.value:.3f}</td>"
            f"<td>{d.precision:.3f}</td><td class='l'>{html.escape(a.model)}</td></tr>"
        )
    parts.append("</table>" + ("</details>" if t.penalties else ""))
    return ["".join(parts)]
