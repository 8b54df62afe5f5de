"""The learning curves of backdoor training."""

from __future__ import annotations

from pathlib import Path

from seqtrojan.experiment_results import CurvesResult
from seqtrojan.report.markup import img


def curves_section(result: CurvesResult | None, figure: Path) -> list[str]:
    """The figure, and a table of each grid's final score (no table before the curves stage has run)."""
    parts = ["<h2>Learning curves (backdoor training)</h2>", img(figure)]
    if result is not None and result.curves:
        items = "".join(
            f"<tr><td class='l'>{c.grid}</td><td>{c.mean[-1]:.3f} &plusmn; {c.std[-1]:.3f}</td>"
            f"<td>{c.seeds}</td><td>{c.env_steps[-1]:,.0f}</td></tr>"
            for c in result.curves
        )
        parts.append(
            "<table><tr><th class='l'>grid</th><th>final score (mean &plusmn; sd)</th><th>seeds</th>"
            f"<th>env steps</th></tr>{items}</table>"
            "<p class='note'>Score = success in the normal env + success in the trojan env (max 2) over the "
            "episodes that ended in each update, each run trained on that grid alone. The paper shows these curves "
            "(10 seeds) without numbers to compare.</p>"
        )
    return parts
