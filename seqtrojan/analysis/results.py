"""What the analysis finds, as typed results: saved with :func:`seqtrojan.serde.save_json` and loaded with
:func:`seqtrojan.serde.load_json`, so that a misspelt or missing key fails at load with its dotted path.

:func:`seqtrojan.analysis.pipeline.run_analysis` writes one file per stage (``responses.json``,
``goal_units.json``, ``interventions.json``, ``unintentional.json``, ``search.json``) and gathers them in
:class:`AnalysisResult` (``analysis.json``), which the report and ``seqtrojan analyze`` read. Every rate is a
:class:`~seqtrojan.stats.Rate` (its counts, rate and Wilson interval). Values derived from others (episodes per
arm, searches' totals, cost per trigger found) are properties, not stored.

The bottom of the analysis package: this module imports only the configs and :mod:`seqtrojan.stats`.
"""

from __future__ import annotations

from dataclasses import dataclass

from seqtrojan.analysis.config import (
    AnalysisConfig,
    LayoutSearchConfig,
    ResponseRule,
    SequenceSearchConfig,
    WalkSearchConfig,
)
from seqtrojan.stats import Rate

ANALYSIS_FILE = "analysis.json"
"""the file in the analysis folder that gathers every stage (an :class:`AnalysisResult`)"""

# --- response types


@dataclass(frozen=True)
class ResponseCounts:
    impulse: int
    none: int
    step: int


@dataclass(frozen=True)
class UnitResponses:
    """One layer's h or c units of one agent, classified (:mod:`seqtrojan.analysis.responses`)."""

    counts: ResponseCounts
    step_units: tuple[int, ...]
    impulse_units: tuple[int, ...]


@dataclass(frozen=True)
class ResponsesResult:
    rule: ResponseRule
    agents: dict[str, dict[str, UnitResponses]]
    """agent ('clean', 'backdoor') -> 'layer<i>.<h|c>' -> its units' responses"""
    step_units_total: dict[str, int]
    """agent -> step-type units over all its layers"""
    finding: str
    """which agents have step responses, in words"""


# --- goal units and editing them


@dataclass(frozen=True)
class GoalUnitsRecord:
    """The goal units a stage chose (:class:`seqtrojan.analysis.unintentional.GoalUnits`) and how it chose them."""

    layer: int
    which: str
    units: tuple[int, ...]
    normal_mean: tuple[float, ...]
    trojan_mean: tuple[float, ...]
    source: str


@dataclass(frozen=True)
class SwitchResult:
    """One arm of :func:`seqtrojan.analysis.interventions.switch_experiment`."""

    direction: str
    """activate (normal env -> adversary's goal) / deactivate (trojan env -> user's goal)"""
    units: str
    """what was edited: step-units / random-units / none"""
    switch: Rate
    """episodes that ended at the other goal"""
    hole: Rate
    timeout: Rate

    @property
    def episodes(self) -> int:
        return self.switch.n


@dataclass(frozen=True)
class InterventionsResult:
    grid: str
    goal_units: GoalUnitsRecord
    results: tuple[SwitchResult, ...]


# --- unintentional triggers and the agent as a trigger detector


@dataclass(frozen=True)
class UnintentionalRow:
    """One grid of the unintentional-trigger sweep (:func:`seqtrojan.analysis.unintentional.sweep_unintentional`)."""

    grid: str
    activation: Rate
    """normal-env episodes (no trigger) that ended at the adversary's goal"""
    deactivation: Rate
    """trojan-env episodes (trigger shown) that ended at the user's goal"""
    normal_outcomes: dict[str, int]
    """normal-env episodes per outcome (user_goal, adversary_goal, hole, timeout)"""
    trojan_outcomes: dict[str, int]

    @property
    def episodes(self) -> int:
        return self.activation.n


@dataclass(frozen=True)
class TriggerDetectionRow:
    """The agent as a trigger detector on one grid, or on all pooled ('all'); see
    :mod:`seqtrojan.analysis.trigger_detection`."""

    grid: str
    recall: Rate
    """triggered episodes that reached the adversary's goal, of the triggered ones that reached a goal"""
    false_positive_rate: Rate
    """untriggered episodes that reached the adversary's goal, of the untriggered ones that reached a goal"""
    precision: float
    """at ``prevalence``"""
    f1: float
    prevalence: float
    undecided: int
    """episodes of either env that fell in a hole or timed out"""

    @property
    def positives(self) -> int:
        return self.recall.n

    @property
    def negatives(self) -> int:
        return self.false_positive_rate.n


@dataclass(frozen=True)
class UnintentionalResult:
    summaries: tuple[UnintentionalRow, ...]
    trigger_detection: tuple[TriggerDetectionRow, ...]
    findings: int
    """episodes kept in findings.json (each replays exactly)"""
    goal_units_flipped: dict[str, Rate]
    """kind of finding (activation, deactivation) -> findings in which the goal units switched, of that kind's"""
    plotted: tuple[str, ...]
    """figure files of the plotted findings"""


# --- searches


@dataclass(frozen=True)
class LayoutSearchResult:
    """One restart of :func:`seqtrojan.analysis.search.evolve_layouts`."""

    found: bool
    generations: int
    best_rate: Rate
    """the best layout's episodes that ended at the adversary's goal, of its rollouts"""
    best_layout: list[list[int]]
    episodes: int
    seconds: float


@dataclass(frozen=True)
class LayoutSearch:
    config: LayoutSearchConfig
    runs: tuple[LayoutSearchResult, ...]

    @property
    def restarts(self) -> int:
        return len(self.runs)

    @property
    def found(self) -> int:
        return sum(r.found for r in self.runs)

    @property
    def episodes(self) -> int:
        return sum(r.episodes for r in self.runs)

    @property
    def seconds(self) -> float:
        return sum(r.seconds for r in self.runs)

    @property
    def seconds_per_found(self) -> float | None:
        return self.seconds / self.found if self.found else None


@dataclass(frozen=True)
class SequenceSearchResult:
    """:func:`seqtrojan.analysis.search.search_sequences`, with what the pipeline measured after it."""

    config: SequenceSearchConfig
    found: int
    relaxed_activation: list[float]
    rounded_activation: list[float]
    seconds: float
    forward_steps: int
    flip_rate: Rate | None = None
    """normal-env episodes, started from the state the found sequences leave behind, that end at the adversary's
    goal (None: nothing found or not measured)"""
    baseline_rate: Rate | None = None
    """the same from the usual zero state"""
    walkable: int | None = None
    """found sequences a walk through a grid could produce (None: not checked)"""

    @property
    def restarts(self) -> int:
        return self.config.restarts

    @property
    def seconds_per_found(self) -> float | None:
        return self.seconds / self.found if self.found else None


@dataclass(frozen=True)
class WalkSearchResult:
    """:func:`seqtrojan.analysis.walks.search_walks`, with the flip rates the pipeline measured after it."""

    config: WalkSearchConfig
    found: int
    rounded_activation: list[float]
    walkable: int
    """rounded walks that pass :func:`seqtrojan.analysis.walks.is_walkable` (all of them, by construction)"""
    solvable: int
    """found walks whose rounded grid still lets the agent reach both goals"""
    revealed_density: list[float]
    """hole density of the cells each rounded walk reveals"""
    seconds: float
    flip_rate: Rate | None = None
    baseline_rate: Rate | None = None

    @property
    def restarts(self) -> int:
        return self.config.restarts

    @property
    def target_density(self) -> float:
        return self.config.target_density

    @property
    def seconds_per_found(self) -> float | None:
        return self.seconds / self.found if self.found else None


@dataclass(frozen=True)
class SearchResult:
    layouts: LayoutSearch
    sequences: SequenceSearchResult
    walks: tuple[WalkSearchResult, ...]
    """one per walk density weight"""


# --- the whole analysis


@dataclass(frozen=True)
class AnalysisResult:
    """``analysis.json``: every stage of :func:`seqtrojan.analysis.pipeline.run_analysis`."""

    config: AnalysisConfig
    responses: ResponsesResult
    goal_units: GoalUnitsRecord
    interventions: InterventionsResult
    unintentional: UnintentionalResult
    search: SearchResult
    timings: dict[str, float]
    """seconds per stage"""
