"""The machine and the stages' wall times, and notes on the method."""

from __future__ import annotations

import html
from typing import Any


def machine_section(machine: dict[str, Any], seconds: dict[str, float]) -> list[str]:
    """``machine``: what seqtrojan.experiments.reproduce.machine_summary says; ``seconds``: wall seconds per stage."""
    parts = ["<h2>Machine and timings</h2><table>"]
    for key, value in {**machine, **{f"seconds: {k}": f"{v:.1f}" for k, v in seconds.items()}}.items():
        parts.append(f"<tr><td class='l'>{html.escape(str(key))}</td><td class='l'>{html.escape(str(value))}</td></tr>")
    parts.append("</table>")
    parts.append(
        "<h2>Method notes</h2><ul class='note'>"
        "<li>Evaluation: each trial is a fresh layout in its own env slot, all trials of a cell run as one batch "
        "until every episode ended (no bias toward short episodes); the policy samples its actions as in "
        "training; the time limit is 4N steps and counts as a failure.</li>"
        "<li>Trojan env: the trigger covers the whole 3x3 view for one step, at a step drawn uniformly from the "
        "configured range and clipped so that it comes before any goal can be reached.</li>"
        "<li>Backdoor injection: the paper's Algorithm 1 (an episode is a trojan-env episode when U(0,1) > 0.5 + "
        "(P_t - P_c)), with the mixing mode named in the backdoor agent's config.</li>"
        "<li>Rewards: +1 correct goal, -1 hole, wrong goal or time-out, 0 otherwise (docs/environment.md explains "
        "the time-out choice).</li></ul>"
    )
    return parts
