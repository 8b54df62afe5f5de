"""The adversary's trade-off: a penalty on unintentional activation (read as plain JSON: tradeoff.json is not typed
yet)."""

from __future__ import annotations

import html
from typing import Any

from seqtrojan.report.markup import ci


def tradeoff_section(t: dict[str, Any]) -> list[str]:
    """``t``: tradeoff.json as plain JSON (not typed yet: seqtrojan.experiments.tradeoff writes it)."""
    cfg = t["config"]
    parts = [
        "<h2>The adversary's trade-off: a penalty on unintentional activation</h2>",
        "<p class='note'>Backdoored agents that differ only in the reward for reaching the adversary's goal while "
        "the user's goal is correct (<code>env.rewards.false_activation</code>; -1 is the ordinary wrong-goal "
        f"reward), {cfg.get('seeds', 1)} training seed(s) each. Success on the training grid; activation = "
        f"normal-env episodes (no trigger) over {html.escape(str(cfg['configs']))} configs ({cfg['episodes']} per "
        "config) that ended at the adversary's goal; recall of the agent as a trigger detector over the same "
        "configs.</p>",
    ]
    if t.get("penalties"):

        def ms(d: dict[str, float], seeds: int, digits: int = 3) -> str:  # no spread to show from a single seed
            spread = f" &plusmn; {d['std']:.{digits}f}" if seeds > 1 else ""
            return f"{d['mean']:.{digits}f}{spread}"

        parts.append(
            "<table><tr><th>false-activation reward</th><th>seeds</th><th>normal success</th><th>trojan success</th>"
            "<th>unintentional activation</th><th>recall</th></tr>"
        )
        for p in t["penalties"]:
            parts.append(
                f"<tr><td>{p['penalty']:g}</td><td>{p['seeds']}</td><td>{ms(p['normal_success'], p['seeds'])}</td>"
                f"<td>{ms(p['trojan_success'], p['seeds'])}</td><td>{ms(p['activation_rate'], p['seeds'], 4)}</td>"
                f"<td>{ms(p['recall'], p['seeds'])}</td>"
                "</tr>"
            )
        parts.append("</table><details><summary>every agent, with 95% intervals</summary>")
    parts.append(
        "<table><tr><th>false-activation reward</th><th>seed</th><th>normal success [95% CI]</th>"
        "<th>trojan success [95% CI]</th><th>unintentional activation [95% CI]</th><th>recall</th>"
        "<th>precision</th><th class='l'>agent</th></tr>"
    )
    for a in t["agents"]:
        d = a["detection"]
        parts.append(
            f"<tr><td>{a['penalty']:g}</td><td>{a.get('seed', '')}</td>"
            f"<td>{a['normal_success']:.3f} {ci(a['normal_ci'])}</td>"
            f"<td>{a['trojan_success']:.3f} {ci(a['trojan_ci'])}</td>"
            f"<td>{a['activation_rate']:.4f} {ci(a['activation_ci'])}</td><td>{d['recall']:.3f}</td>"
            f"<td>{d['precision']:.3f}</td><td class='l'>{html.escape(a['model'])}</td></tr>"
        )
    parts.append("</table>" + ("</details>" if t.get("penalties") else ""))
    return ["".join(parts)]
