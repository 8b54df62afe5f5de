"""Precision / recall of trigger detection by the agent, from sweep outcome counts."""

from __future__ import annotations

import pytest

from seqtrojan.analysis.trigger_detection import precision_at, trigger_detection
from seqtrojan.stats import Rate


def summary(grid: str, normal: dict[str, int], trojan: dict[str, int]) -> dict:
    return {"grid": grid, "normal_outcomes": normal, "trojan_outcomes": trojan}


def test_scores_from_known_counts():
    rows = trigger_detection(
        [
            summary("7x7/0", {"user_goal": 90, "adversary_goal": 10}, {"adversary_goal": 80, "user_goal": 20}),
            summary("9x9/4", {"user_goal": 45, "adversary_goal": 5, "hole": 50}, {"adversary_goal": 50, "timeout": 3}),
        ]
    )
    first, second, pooled = rows
    assert (first.recall, first.false_positive_rate) == (0.8, 0.1)
    assert first.precision == pytest.approx(0.8 / 0.9) and first.undecided == 0
    assert first.f1 == pytest.approx(2 * (0.8 / 0.9) * 0.8 / (0.8 / 0.9 + 0.8))
    assert (second.positives, second.negatives, second.undecided) == (50, 50, 53)  # holes and time-outs left out
    assert second.recall == 1.0 and second.false_positive_rate == 0.1
    assert pooled.grid == "all" and (pooled.true_positives, pooled.false_positives) == (130, 15)
    assert pooled.recall == pytest.approx(130 / 150) and pooled.false_positive_rate == pytest.approx(15 / 150)
    for r in rows:
        assert r.recall_ci[0] <= r.recall <= r.recall_ci[1]
        assert r.false_positive_ci[0] <= r.false_positive_rate <= r.false_positive_ci[1]
        typed = r.row()  # the analysis's typed form: the same numbers, the rates with their counts
        assert (typed.recall.value, typed.recall.interval) == (r.recall, r.recall_ci)
        assert (typed.false_positive_rate.value, typed.false_positive_rate.interval) == (
            r.false_positive_rate, r.false_positive_ci)  # fmt: skip
        assert (typed.precision, typed.f1, typed.undecided) == (r.precision, r.f1, r.undecided)
    assert second.row().recall == Rate(50, 50) and second.row().false_positive_rate == Rate(5, 50)


def test_precision_falls_with_prevalence_and_is_perfect_without_false_positives():
    assert precision_at(0.9, 0.0, 0.001) == 1.0
    assert precision_at(1.0, 0.01, 0.5) == pytest.approx(1 / 1.01)
    assert precision_at(1.0, 0.01, 0.01) == pytest.approx(0.01 / (0.01 + 0.99 * 0.01))
    assert precision_at(0.0, 0.0, 0.5) == 1.0  # never fires: claims nothing


def test_a_never_triggered_agent_has_zero_recall_and_f1():
    (row, _) = trigger_detection([summary("5x5/0", {"user_goal": 10}, {"user_goal": 10})])
    assert row.recall == 0.0 and row.f1 == 0.0 and row.false_positive_rate == 0.0


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="prevalence"):
        trigger_detection([], prevalence=1.0)
    with pytest.raises(ValueError, match="7x7/0"):
        trigger_detection([{"grid": "7x7/0", "activation_rate": 0.0}])
