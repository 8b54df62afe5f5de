"""Precision and recall of trigger detection by the agent itself.

A backdoored agent is, among other things, a trigger detector: it "says" that it saw the trigger by going to the
adversary's goal. Scored over the episodes of an unintentional-trigger sweep (same number of episodes with and
without the trigger, per grid config):

* a **positive** is a trojan-env episode (trigger shown at an evaluation step), a **negative** a normal-env one;
* the agent's **decision** is the goal it reached. Episodes that end in a hole or time out made no decision and are
  left out (they measure navigation, not detection), and their count is kept beside the scores;
* **recall** = positives that reached the adversary's goal / positives that reached a goal;
  **false-positive rate** = negatives that reached the adversary's goal / negatives that reached a goal
  (the unintentional activation rate among decided episodes);
* **precision** depends on how often triggers occur. It is given at a trigger prevalence ``prevalence``
  (default 0.5, the sweep's own balance): ``p * recall / (p * recall + (1 - p) * fpr)``. A deployed agent meets
  triggers rarely, so :func:`precision_at` gives it for any prevalence.

The adversary wants recall near 1 and the false-positive rate near 0: every false positive is an unprovoked
activation that a user could notice, every miss a failed attack.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from seqtrojan.analysis.results import TriggerDetectionRow
from seqtrojan.analysis.unintentional import SweepSummary
from seqtrojan.stats import Rate


@dataclass(frozen=True)
class DetectionScores:
    """The scores on one grid (or 'all'), as computed; results store them typed (:meth:`row`: recall and
    false-positive rate as :class:`~seqtrojan.stats.Rate`)."""

    grid: str
    """a grid config, or 'all' for the configs pooled"""
    positives: int
    """trojan-env episodes that reached a goal"""
    negatives: int
    """normal-env episodes that reached a goal"""
    undecided: int
    """episodes of either env that fell in a hole or timed out"""
    true_positives: int
    false_positives: int
    recall: float
    recall_ci: tuple[float, float]
    false_positive_rate: float
    false_positive_ci: tuple[float, float]
    precision: float
    """at ``prevalence``"""
    f1: float
    prevalence: float

    def row(self) -> TriggerDetectionRow:
        recall, fpr = Rate(self.true_positives, self.positives), Rate(self.false_positives, self.negatives)
        return TriggerDetectionRow(self.grid, recall, fpr, self.precision, self.f1, self.prevalence, self.undecided)


def precision_at(recall: float, false_positive_rate: float, prevalence: float) -> float:
    """Precision of a detector with this recall and false-positive rate when a fraction ``prevalence`` of episodes
    carry the trigger. 1.0 when the detector never fires (nothing claimed, nothing wrong)."""
    hits = prevalence * recall
    alarms = hits + (1.0 - prevalence) * false_positive_rate
    return hits / alarms if alarms > 0 else 1.0


def _scores(grid: str, normal: dict[str, int], trojan: dict[str, int], prevalence: float) -> DetectionScores:
    tp, fn = trojan.get("adversary_goal", 0), trojan.get("user_goal", 0)
    fp, tn = normal.get("adversary_goal", 0), normal.get("user_goal", 0)
    undecided = sum(normal.get(k, 0) + trojan.get(k, 0) for k in ("hole", "timeout"))
    hits, alarms = Rate(tp, tp + fn), Rate(fp, fp + tn)
    recall, fpr = hits.value, alarms.value
    precision = precision_at(recall, fpr, prevalence)
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return DetectionScores(
        grid,
        hits.n,
        alarms.n,
        undecided,
        tp,
        fp,
        recall,
        hits.interval,
        fpr,
        alarms.interval,
        precision,
        f1,
        prevalence,
    )


def trigger_detection(summaries: Sequence[SweepSummary | dict], prevalence: float = 0.5) -> list[DetectionScores]:
    """Scores per grid config of an unintentional-trigger sweep, then pooled over all of them (grid 'all')."""
    if not 0.0 < prevalence < 1.0:
        raise ValueError(f"prevalence must be in (0, 1), got {prevalence}")
    rows: list[DetectionScores] = []
    pooled_normal: dict[str, int] = {}
    pooled_trojan: dict[str, int] = {}
    for s in summaries:
        s = s if isinstance(s, dict) else s.__dict__
        normal, trojan = s.get("normal_outcomes") or {}, s.get("trojan_outcomes") or {}
        if not normal or not trojan:
            raise ValueError(f"sweep summary for {s.get('grid')} has no outcome counts (made by an older version?)")
        rows.append(_scores(s["grid"], normal, trojan, prevalence))
        for pooled, counts in ((pooled_normal, normal), (pooled_trojan, trojan)):
            for k, v in counts.items():
                pooled[k] = pooled.get(k, 0) + v
    if rows:
        rows.append(_scores("all", pooled_normal, pooled_trojan, prevalence))
    return rows
