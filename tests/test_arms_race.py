"""The answer tables' rule: a defense is judged by its worst working attack, an attack by its best acting defense."""

from __future__ import annotations

from seqtrojan.arms_race import best_defenses, worst_cases
from seqtrojan.experiment_results import MatrixCell
from seqtrojan.stats import OverSeeds, Rate


def cell(attack: str, defense: str, kind: str = "online", success: float | None = None,
         auc: float | None = None) -> MatrixCell:  # fmt: skip
    s = OverSeeds((success,)) if success is not None else None
    pooled = Rate(round(1000 * success), 1000) if success is not None else None
    return MatrixCell(attack, defense, kind, s, pooled, OverSeeds((0.97,)), None, None, None, None, auc,
                      (0.4, 1.0) if auc is not None else None)  # fmt: skip


UNDEFENDED = {"plain": OverSeeds((0.95, 0.93)), "adaptive": OverSeeds((0.9, 0.8)), "broken": OverSeeds((0.1, 0.2))}


def test_a_monitor_is_judged_by_the_working_attack_it_stops_least():
    cells = [cell("plain", "monitor", success=0.05), cell("adaptive", "monitor", success=0.7),
             cell("broken", "monitor", success=0.95)]  # fmt: skip
    (w,) = worst_cases(cells, UNDEFENDED)
    assert (w.defense, w.tried, w.working) == ("monitor", 3, 2)
    assert w.worst is not None and w.worst.attack == "adaptive"  # not "broken": its backdoor does not work


def test_an_offline_detector_is_judged_by_its_lowest_auc_and_no_working_attack_is_said():
    cells = [cell("plain", "detector", "offline", auc=1.0), cell("adaptive", "detector", "offline", auc=0.55),
             cell("broken", "detector", "offline", auc=0.1), cell("broken", "reset", success=0.0)]  # fmt: skip
    detector, reset = worst_cases(cells, UNDEFENDED)
    assert detector.worst is not None and detector.worst.attack == "adaptive"
    assert reset.working == 0 and reset.worst is None


def test_each_working_attack_gets_the_acting_defense_that_stops_it_best():
    cells = [
        cell("plain", "monitor", success=0.3),
        cell("plain", "fine_tuning", "mitigation", success=0.1),
        cell("plain", "detector", "offline", auc=1.0),
        cell("adaptive", "detector", "offline", auc=0.5),
    ]
    alone = {name: (x, None) for name, x in UNDEFENDED.items()}
    plain, adaptive = best_defenses(cells, alone)  # "broken" is left out: nothing to stop
    assert plain.best is not None and plain.best.defense == "fine_tuning"
    assert adaptive.attack == "adaptive" and adaptive.best is None  # an offline detector does not act
