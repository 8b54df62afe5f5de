"""The arms race's answer: every defense judged by the worst attack tried on it, every attack by the best defense.

A defense claim holds only against the attacker who knows the defense, so a defense is summarised by its worst case
over every attack tried on it (the adaptive ones built against it among them), never by the attack it was built
for. Only attacks whose backdoor works count (mean undefended attack success over seeds at least
:data:`WORKS_AT`): a recipe that destroys its own backdoor evades nothing. The worst case of a defense that acts
(an online monitor, with its alarm-driven reset, or a mitigation) is the working attack with the highest mean
attack success with the defense acting; of an offline detector, the working attack whose models it ranks worst
against the clean models (lowest ROC-AUC). The best defense against an attack is the acting defense that leaves it
the lowest mean attack success; its clean-success cost is shown beside it.

Both read :class:`~seqtrojan.experiment_results.MatrixCell` objects: the matrix's own (``seqtrojan matrix``), or
cells built from a benchmark's sweep (``scripts/arms_race.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from seqtrojan.experiment_results import MatrixCell, MatrixResult
from seqtrojan.stats import OverSeeds, Rate

WORKS_AT = 0.5
"""mean undefended attack success over seeds from which an attack's backdoor counts as working"""


@dataclass(frozen=True)
class WorstCase:
    """One defense against the worst working attack tried on it."""

    defense: str
    kind: str
    """online, mitigation or offline"""
    tried: int
    """attacks measured against it"""
    working: int
    """of them, attacks whose backdoor works undefended"""
    worst: MatrixCell | None
    """that attack's cell (None: no working attack was tried)"""


@dataclass(frozen=True)
class BestDefense:
    """One working attack against the acting defense that stops it best."""

    attack: str
    undefended: OverSeeds
    undefended_pooled: Rate | None
    best: MatrixCell | None
    """the defense's cell (None: no acting defense was tried on it)"""


def _mean(x: OverSeeds | None, default: float) -> float:
    return x.mean if x is not None else default


def worst_cases(cells: Sequence[MatrixCell], undefended: Mapping[str, OverSeeds]) -> list[WorstCase]:
    """Per defense (in the order the cells first name them), its worst case (see the module docstring)."""
    out = []
    for defense in dict.fromkeys(c.defense for c in cells):
        mine = [c for c in cells if c.defense == defense]
        working = [c for c in mine if c.attack in undefended and undefended[c.attack].mean >= WORKS_AT]
        worst: MatrixCell | None = None
        if working and mine[0].kind == "offline":
            scored = [c for c in working if c.auc is not None]
            worst = min(scored, key=lambda c: c.auc if c.auc is not None else 1.0) if scored else None
        elif working:
            worst = max(working, key=lambda c: _mean(c.attack_success, 0.0))
        out.append(WorstCase(defense, mine[0].kind, len(mine), len(working), worst))
    return out


def best_defenses(
    cells: Sequence[MatrixCell], undefended: Mapping[str, tuple[OverSeeds, Rate | None]]
) -> list[BestDefense]:
    """Per working attack (in the order of ``undefended``), the acting defense that leaves it the lowest mean
    attack success."""
    out = []
    for attack, (success, pooled) in undefended.items():
        if success.mean < WORKS_AT:
            continue
        acting = [c for c in cells if c.attack == attack and c.kind != "offline" and c.attack_success is not None]
        best = min(acting, key=lambda c: _mean(c.attack_success, 1.0)) if acting else None
        out.append(BestDefense(attack, success, pooled, best))
    return out


def matrix_answer(result: MatrixResult) -> tuple[list[WorstCase], list[BestDefense]]:
    """:func:`worst_cases` and :func:`best_defenses` of a matrix."""
    alone = {a.attack: (a.attack_success, a.attack_success_pooled) for a in result.attacks}
    return worst_cases(result.cells, {k: v[0] for k, v in alone.items()}), best_defenses(result.cells, alone)
