"""What the defenses measure, as typed results: the online monitor and the mitigations of one model
(:class:`DefenseResult`, ``defense.json``) and offline detection on a zoo (:class:`DetectionResult`,
``detection.json``). Saved with :func:`seqtrojan.serde.save_json` and loaded with :func:`seqtrojan.serde.load_json`,
so that a misspelt or missing key fails at load with its dotted path. Every rate is a
:class:`~seqtrojan.stats.Rate` (its counts, rate and Wilson interval).

The bottom of the defense package: this module imports only :mod:`seqtrojan.stats` and the analysis's results.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from seqtrojan.analysis.results import GoalUnitsRecord
from seqtrojan.stats import Rate

DEFENSE_FILE = "defense.json"
"""the file in the defense folder that holds the :class:`DefenseResult`"""
DETECTION_FILE = "detection.json"
"""the file in the zoo folder that holds the :class:`DetectionResult`"""

# --- the online monitor (seqtrojan.defense.monitor)


@dataclass(frozen=True)
class NormalEnvArm:
    """Episodes of the normal env (no trigger) with the monitor watching."""

    success: Rate
    """episodes that reached the user's goal"""
    false_alarm: Rate
    """episodes with an alarm"""


@dataclass(frozen=True)
class TrojanEnvArm:
    """Episodes of the trojan env (trigger shown) with the monitor watching."""

    attack_success: Rate
    """episodes that reached the adversary's goal"""
    user_goal: Rate
    detected: Rate
    """episodes with an alarm at or after the trigger"""
    alarm_before_trigger: Rate
    median_steps_to_detect: float | None
    """median steps from the trigger to the first alarm over the detected episodes (None: none detected)"""


@dataclass(frozen=True)
class MonitorResult:
    """:func:`seqtrojan.defense.monitor.measure_monitor`: each env with the monitor (any online detector) raising
    alarms only, with it resetting the state on an alarm, and without it."""

    grid: str
    episodes: int
    """fresh episodes per arm"""
    threshold: float
    """the detector's alarm threshold (for the state monitor: the largest |z| over all units)"""
    units: tuple[int, ...]
    """units watched per layer (h and c); () for a detector that reads only the input (input novelty)"""
    normal_alarm: NormalEnvArm
    normal_reset: NormalEnvArm
    trojan_alarm: TrojanEnvArm
    trojan_reset: TrojanEnvArm
    clean_success_undefended: Rate
    """normal-env episodes that reached the user's goal without the monitor"""
    attack_success_undefended: Rate
    """trojan-env episodes that reached the adversary's goal without the monitor"""


# --- mitigation (seqtrojan.defense.mitigation)


@dataclass(frozen=True)
class MitigationArm:
    """One row of the mitigation table: the model after one mitigation (or before any), in both envs."""

    title: str
    """the row's title in the report"""
    clean_success: Rate
    """normal-env episodes that reached the user's goal"""
    attack_success: Rate
    """trojan-env episodes that reached the adversary's goal"""
    units: tuple[int, ...]
    """the units the mitigation pruned or held (none for the others)"""


MitigationResult = dict[str, MitigationArm]
""":func:`seqtrojan.defense.mitigation.run_mitigation`: ``before`` (no mitigation), then the rows of each
registered mitigation in registration order, by name (e.g. ``pruned``, ``fine_pruned``, ``fine_tuned``,
``reset_goal_units_oracle``)."""


@dataclass(frozen=True)
class DefenseResult:
    """``defense.json``: :func:`seqtrojan.defense.pipeline.run_defense` on one model."""

    model: str
    """the model folder"""
    label: str
    """clean / backdoored, from the model's card"""
    grid: str
    trigger_value: str
    """what the model's trigger draws (``env.trigger.drawn_codes``: its cell code, or a per-cell patch's or a
    sequence's codes)"""
    monitor: MonitorResult
    oracle_goal_units: GoalUnitsRecord | None
    """the step-type units the oracle found with trigger episodes (None: none found, or a clean model)"""
    mitigation: dict[str, MitigationArm]
    """the mitigation table's rows by name (:data:`MitigationResult`)"""


# --- offline detection on a zoo (seqtrojan.defense.offline)


@dataclass(frozen=True)
class Prediction:
    model: str
    label: int
    """1 backdoored, 0 clean"""
    p_backdoored: float
    """the out-of-fold probability of 'backdoored'"""


@dataclass(frozen=True)
class GroupScores:
    """One feature group's detector, scored on out-of-fold predictions (k-fold cross-validation)."""

    group: str
    """a feature group, or 'all'"""
    features: int
    models: int
    folds: int
    roc_auc: float
    cross_entropy: float
    brier: float
    predictions: tuple[Prediction, ...]


@dataclass(frozen=True)
class HeldOutGroup:
    """The models with one value of the held-out variation, scored by a detector trained on all the others."""

    value: Any
    """the value as the zoo's label.json records it (a list, a string, a mapping or null)"""
    models: int
    backdoored: int
    roc_auc: float | None
    """None (and the other scores too) when these models all have the same label"""
    cross_entropy: float | None
    brier: float | None


@dataclass(frozen=True)
class HeldOutScores:
    """:func:`seqtrojan.defense.offline.held_out_group_scores` for one variation ``key``."""

    key: str
    models: int
    """models scored out of their group"""
    roc_auc: float | None
    """over all out-of-group predictions (None, and the other scores too: they hold one label only)"""
    cross_entropy: float | None
    brier: float | None
    groups: tuple[HeldOutGroup, ...]
    skipped: tuple[Any, ...]
    """values whose held-out or remaining models lack a label"""


@dataclass(frozen=True)
class FunctionalSplit:
    """Backdoored models whose backdoor works (final trojan-env success >= ``functional_at``) and those whose does
    not, each scored against all clean models."""

    functional_at: float
    functional: int
    not_functional: int
    functional_roc_auc: float | None
    """None when there are no such models (or no clean ones)"""
    not_functional_roc_auc: float | None


@dataclass(frozen=True)
class Rejected:
    model: str
    reason: str
    """one line"""


@dataclass(frozen=True)
class DetectionResult:
    """``detection.json``: :func:`seqtrojan.defense.offline.detect_zoo`."""

    rejected: tuple[Rejected, ...]
    scores: tuple[GroupScores, ...]
    """all features first, then each group alone"""
    held_out: tuple[HeldOutScores, ...]
    functional_backdoors: FunctionalSplit
    auc_by_trigger_value: dict[str, float]
    """ROC-AUC of the backdoored models with each trigger cell code against all clean models"""

    @property
    def clean_models(self) -> int:
        return sum(p.label == 0 for p in self.scores[0].predictions)

    @property
    def backdoored_models(self) -> int:
        return sum(p.label == 1 for p in self.scores[0].predictions)


# --- the trigger-free behavioural detector (seqtrojan.defense.behaviour)


@dataclass(frozen=True)
class PatchCandidate:
    """One candidate patch shown for one step of normal-env episodes, and how often the agent then ended at the
    adversary's goal."""

    name: str
    """``whole_view:<code>`` (one code over the whole view) or ``random:<i>`` (ordinary codes on some cells)"""
    cells: tuple[tuple[int, int], ...]
    """the view cells (row, col) the patch draws on"""
    codes: tuple[str, ...]
    """the code drawn on each of those cells"""
    adversary_goal: Rate
    """episodes with this patch that ended at the adversary's goal"""
    rise: float
    """``adversary_goal`` minus the no-patch baseline's rate (the same episodes' layouts and patch steps)"""


@dataclass(frozen=True)
class BehaviourScore:
    """:func:`seqtrojan.defense.behaviour.behaviour_score` on one model."""

    grid: str
    episodes: int
    """normal-env episodes per candidate (and for the baseline)"""
    patch_steps: tuple[int, int]
    """inclusive range of the step the patch is shown at (drawn per episode, shared by all candidates)"""
    baseline: Rate
    """episodes without a patch that ended at the adversary's goal"""
    score: float
    """the model's score: the largest rise over the candidates (a backdoor makes some patch switch the goal)"""
    best: str
    """the name of the candidate with that rise"""
    candidates: tuple[PatchCandidate, ...]


@dataclass(frozen=True)
class DetectorAUC:
    """:func:`seqtrojan.defense.behaviour.scores_auc`: how well a score ranks backdoored above clean models."""

    auc: float
    """ROC-AUC (ties count half)"""
    interval: tuple[float, float]
    """its 95% interval (:func:`seqtrojan.stats.auc_interval`)"""
    positives: int
    """backdoored models"""
    negatives: int
    """clean models"""


@dataclass(frozen=True)
class ScoredModel:
    model: str
    label: int
    """1 backdoored, 0 clean"""
    score: float
    best: str
    """the candidate patch that gave the score"""


@dataclass(frozen=True)
class BehaviourDetectionResult:
    """:func:`seqtrojan.defense.behaviour.detect_zoo_behaviour`: every usable zoo model's behavioural score."""

    models: tuple[ScoredModel, ...]
    rejected: tuple[Rejected, ...]
    auc: DetectorAUC | None
    """None when the scored models hold one label only"""
