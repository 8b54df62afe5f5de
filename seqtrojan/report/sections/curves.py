"""The learning curves of backdoor training (read as plain JSON: curves.json is not typed yet)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from seqtrojan.report.markup import img


def curves_section(curves: dict[str, Any], figure: Path) -> list[str]:
    """``curves``: grid -> its curve over seeds (seqtrojan.experiments.curves.aggregate_curves), may be empty."""
    parts = ["<h2>Learning curves (backdoor training)</h2>", img(figure)]
    if curves:
        items = "".join(
            f"<tr><td class='l'>{c}</td><td>{d['mean'][-1]:.3f} &plusmn; {d['std'][-1]:.3f}</td>"
            f"<td>{int(d['seeds'][0])}</td><td>{d['env_steps'][-1]:,.0f}</td></tr>"
            for c, d in curves.items()
        )
        parts.append(
            "<table><tr><th class='l'>grid</th><th>final score (mean &plusmn; sd)</th><th>seeds</th>"
            f"<th>env steps</th></tr>{items}</table>"
            "<p class='note'>Score = success in the normal env + success in the trojan env (max 2) over the "
            "episodes that ended in each update, each run trained on that grid alone. The paper shows these curves "
            "(10 seeds) without numbers to compare.</p>"
        )
    return parts
