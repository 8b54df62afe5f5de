"""The results of the experiments that train many agents, typed: the learning curves (``curves.json``) and the
adversary's trade-off (``tradeoff.json``). Saved with :func:`seqtrojan.serde.save_json` and read back with
:func:`seqtrojan.serde.load_json`, so that a wrong or missing key fails at load with its dotted path.

This module imports only the result types below it (stats, analysis results).
"""

from __future__ import annotations

from dataclasses import dataclass

from seqtrojan.analysis.results import TriggerDetectionRow, UnintentionalRow
from seqtrojan.stats import OverSeeds, Rate

CURVES_FILE = "curves.json"
TRADEOFF_FILE = "tradeoff.json"

# --- learning curves (seqtrojan.experiments.curves)


@dataclass(frozen=True)
class Curve:
    """One grid's learning curve: the score (normal + trojan success, max 2) on a common step grid, mean and
    standard deviation over the training seeds."""

    grid: str
    seeds: int
    env_steps: tuple[float, ...]
    mean: tuple[float, ...]
    std: tuple[float, ...]
    """population standard deviation over seeds at each step (0 for one seed)"""


@dataclass(frozen=True)
class CurvesResult:
    """``curves.json``: one curve per grid, in the configured order."""

    curves: tuple[Curve, ...]


# --- the adversary's trade-off (seqtrojan.experiments.tradeoff)


@dataclass(frozen=True)
class TradeoffSettings:
    """The trade-off's configuration, as run (:class:`seqtrojan.experiments.tradeoff.TradeoffConfig`)."""

    penalties: tuple[float, ...]
    total_steps: int | None
    configs: str
    episodes: int
    seed: int
    seeds: int


@dataclass(frozen=True)
class TradeoffAgentResult:
    """One agent of the trade-off: its false-activation reward, training seed, attack and stealth."""

    penalty: float
    seed: int
    model: str
    """its model folder, relative to the reproduction's folder"""
    training_grid: str
    normal_success: Rate
    """normal-env episodes on the training grid that reached the user's goal"""
    trojan_success: Rate
    """trojan-env episodes on the training grid that reached the adversary's goal"""
    activation: Rate
    """normal-env episodes over the sweep configs that reached the adversary's goal (unintentional activation)"""
    detection: TriggerDetectionRow
    """the agent as a trigger detector, pooled over the sweep configs"""
    per_config: tuple[UnintentionalRow, ...]


@dataclass(frozen=True)
class PenaltySummary:
    """One false-activation reward over its training seeds."""

    penalty: float
    normal_success: OverSeeds
    trojan_success: OverSeeds
    activation: OverSeeds
    recall: OverSeeds

    @property
    def seeds(self) -> int:
        return self.normal_success.seeds


@dataclass(frozen=True)
class TradeoffResult:
    """``tradeoff.json``: every agent, and each penalty summarised over its seeds."""

    config: TradeoffSettings
    agents: tuple[TradeoffAgentResult, ...]
    penalties: tuple[PenaltySummary, ...]


# --- the attack x defense matrix (seqtrojan.experiments.matrix)

MATRIX_FILE = "matrix.json"


@dataclass(frozen=True)
class AgentMeasurement:
    """One trained agent (an attack's, or a clean one) measured without any defense, then under each online
    defense and mitigation. Saved per agent (``measured/<agent>.json``) so that a stopped matrix resumes."""

    agent: str
    """``<attack>_s<seed>`` or ``clean_s<seed>``"""
    attack: str
    """the attack's name, or ``clean``"""
    seed: int
    grid: str
    clean_success: Rate
    """normal-env episodes that reached the user's goal"""
    attack_success: Rate
    """trojan-env episodes (this attack's trigger) that reached the adversary's goal"""
    unintentional: Rate
    """normal-env episodes that reached the adversary's goal"""
    natural_trigger: Rate | None
    """normal-env episodes whose views showed the whole trigger pattern by chance (None: not measured)"""
    online: dict[str, OnlineArm]
    """online defense name -> its measurement"""
    mitigation: dict[str, MitigationOutcome]
    """mitigation row name (e.g. fine_tuned, fine_pruned) -> the agent after it"""
    offline_scores: dict[str, float]
    """offline detector name -> this model's score (higher: more likely backdoored)"""


@dataclass(frozen=True)
class OnlineArm:
    """An online defense watching this agent: calibrated on its own clean episodes at the false-alarm target."""

    false_alarm: Rate
    """normal-env episodes with an alarm"""
    detection: Rate
    """trojan-env episodes with an alarm at or after the trigger"""
    attack_success_defended: Rate
    """trojan-env episodes that reached the adversary's goal with the defense resetting the state on an alarm"""
    clean_success_defended: Rate
    """normal-env episodes that reached the user's goal with the defense resetting the state on an alarm"""


@dataclass(frozen=True)
class MitigationOutcome:
    clean_success: Rate
    attack_success: Rate


@dataclass(frozen=True)
class MatrixCell:
    """One attack against one defense, over the attack's training seeds: each figure as its per-seed values
    (mean, sd) and pooled over seeds as a Rate (its 95% interval covers the episodes, the sd the training)."""

    attack: str
    defense: str
    kind: str
    """online, mitigation or offline"""
    attack_success: OverSeeds | None
    """with the defense acting (online: reset on alarm; mitigation: after it); None for offline detectors"""
    attack_success_pooled: Rate | None
    clean_success: OverSeeds | None
    """the clean-success cost side: normal-env success with the defense acting"""
    detection: OverSeeds | None
    """online: trojan episodes detected; None for mitigations and offline detectors"""
    detection_pooled: Rate | None
    false_alarm: OverSeeds | None
    false_alarm_pooled: Rate | None
    auc: float | None
    """offline: ROC-AUC of this attack's models against the clean models"""
    auc_interval: tuple[float, float] | None


@dataclass(frozen=True)
class AttackSummary:
    """One attack without any defense, over its training seeds."""

    attack: str
    description: str
    seeds: tuple[int, ...]
    attack_success: OverSeeds
    attack_success_pooled: Rate
    clean_success: OverSeeds
    clean_success_pooled: Rate
    unintentional: OverSeeds
    unintentional_pooled: Rate
    natural_trigger: Rate | None
    """pooled over seeds"""


@dataclass(frozen=True)
class MatrixResult:
    """``matrix.json``: every attack alone, then every (attack, defense) cell, then each agent's measurement."""

    scale: str
    grid: str
    attacks: tuple[AttackSummary, ...]
    cells: tuple[MatrixCell, ...]
    agents: tuple[AgentMeasurement, ...]


# --- sequence models compared (seqtrojan.experiments.cells)

CELLS_FILE = "cells.json"


@dataclass(frozen=True)
class PersistenceBin:
    """Trojan-env episodes that reached a goal between ``lo`` and ``hi`` steps (inclusive) after the trigger's
    last step: how many of them reached the adversary's goal. A switch that fades shows as a falling rate."""

    lo: int
    hi: int
    adversary: Rate


@dataclass(frozen=True)
class UnitsToSwitch:
    """The intervention experiment: in normal episodes, from the trigger step on, set the ``k`` most persistent
    goal units (step-type units ranked by their late deviation) to their trojan-episode means; the rate at which
    the agent then reaches the adversary's goal, for each ``k``, beside ``k`` random units of the same layer."""

    layer: int
    which: str
    units: tuple[int, ...]
    """the ranked units (the first ``k`` are edited)"""
    counts: tuple[int, ...]
    activation: tuple[Rate, ...]
    random_activation: tuple[Rate, ...]

    def needed(self, at: float = 0.5) -> int | None:
        """The fewest edited units that switch the goal in at least ``at`` of the episodes (None: none did)."""
        return next((k for k, r in zip(self.counts, self.activation) if r.value >= at), None)


@dataclass(frozen=True)
class Settling:
    """Does the state settle before the trigger? ``change[t]`` is the mean over running normal episodes of
    ``|s_t - s_{t-1}| / |s_{t-1}|`` (s: every layer's recurrent state); beside it, the attack success when the
    trigger comes at each of ``trigger_steps``, on the same grid."""

    grid: str
    steps: tuple[int, ...]
    change: tuple[float, ...]
    trigger_steps: tuple[int, ...]
    attack_success: tuple[Rate, ...]


@dataclass(frozen=True)
class SweepPoint:
    grid: str
    activation: Rate
    """normal-env episodes that reached the adversary's goal (an unintentional activation)"""


@dataclass(frozen=True)
class CellMeasurement:
    """One trained agent of one sequence model. Saved per agent (``measured/<agent>.json``) so a stopped study
    resumes."""

    agent: str
    """``<cell>_<label>_s<seed>``"""
    cell: str
    label: str
    """clean or backdoored"""
    seed: int
    grid: str
    clean_success: Rate
    attack_success: Rate
    """trojan-env episodes (trigger at the evaluation steps) that reached the adversary's goal"""
    persistence: tuple[PersistenceBin, ...]
    trigger_steps: tuple[int, ...]
    by_trigger_step: tuple[Rate, ...]
    """the adversary's-goal rate with the trigger at each of ``trigger_steps``"""
    sweep: tuple[SweepPoint, ...]
    monitor: dict[str, OnlineArm]
    units: UnitsToSwitch | None
    """backdoored agents only"""
    settling: Settling | None
    offline_score: float | None
    """the weight detector's probability 'backdoored' (trained on a zoo of this cell); None without a zoo"""


@dataclass(frozen=True)
class CellSummary:
    """One sequence model over its training seeds (backdoored agents unless named clean)."""

    cell: str
    seeds: tuple[int, ...]
    clean_model_success: OverSeeds
    """the clean agents' normal-env success"""
    clean_success: OverSeeds
    """the backdoored agents' normal-env success"""
    attack_success: OverSeeds
    attack_success_pooled: Rate
    persistence: tuple[tuple[int, int, OverSeeds, Rate], ...]
    """per bin: lo, hi, the per-seed adversary rate (seeds with at least ``min_bin_episodes`` episodes in the bin;
    a bin no seed reaches is left out), pooled over every seed's episodes"""
    by_trigger_step: tuple[tuple[int, OverSeeds], ...]
    unintentional_mean: OverSeeds
    """per seed: the mean activation rate over the sweep's configs"""
    unintentional_pooled: Rate
    monitor_detection: dict[str, OverSeeds]
    monitor_false_alarm: dict[str, OverSeeds]
    units_needed: tuple[int | None, ...]
    """per seed: the fewest edited units that switch the goal in >= half the episodes (None: no count did)"""
    auc: float | None
    auc_interval: tuple[float, float] | None


@dataclass(frozen=True)
class CellsResult:
    """``cells.json``: one summary per sequence model, then each agent's measurement."""

    scale: str
    grid: str
    window: int
    """the Transformer's window"""
    summaries: tuple[CellSummary, ...]
    agents: tuple[CellMeasurement, ...]
