"""The analysis's configuration: what ``seqtrojan analyze`` (and the reproduction's ``analysis:`` section) runs.

Plain frozen dataclasses at the bottom of the analysis package, so that the analysis's results
(:mod:`seqtrojan.analysis.results`) can carry the configuration they were made with. Each is documented where it
is used: :class:`ResponseRule` in :mod:`seqtrojan.analysis.responses`, the searches in
:mod:`seqtrojan.analysis.search` and :mod:`seqtrojan.analysis.walks`; they are importable from there too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from seqtrojan.env.config import GridSpec
from seqtrojan.errors import ConfigError


@dataclass(frozen=True)
class ResponseRule:
    threshold: float = 1.0
    """deviation (in normal-env standard deviations) that counts as a response"""
    response_window: int = 3
    """steps from the trigger within which a response must start"""
    late_start: int = 6
    """the late window starts this many steps after the trigger ..."""
    late_end: int = 20
    """... and ends here (exclusive), cut to the steps with enough running episodes"""
    persist_fraction: float = 0.5
    """a step response keeps at least this fraction of the threshold on average over the late window"""
    min_episodes: int = 30
    """steps with fewer running episodes in either env are ignored"""
    eps: float = 1e-3
    """added to the standard deviation (units that never vary)"""

    def __post_init__(self) -> None:
        if not 0 < self.response_window <= self.late_start < self.late_end:
            raise ConfigError(
                f"need 0 < response_window <= late_start < late_end, got {self.response_window}, {self.late_start}, "
                f"{self.late_end}"
            )


@dataclass(frozen=True)
class LayoutSearchConfig:
    size: int = 17
    holes: int = 30
    population: int = 32
    rollouts: int = 16
    """sampled episodes per layout per generation"""
    generations: int = 25
    elite: int = 8
    moves: int = 2
    """holes moved per mutation"""
    restarts: int = 4
    success_at: float = 0.5
    """a layout is a trigger when at least this fraction of its episodes end at the adversary's goal"""
    seed: int = 0


@dataclass(frozen=True)
class SequenceSearchConfig:
    length: int = 24
    """observations per sequence"""
    restarts: int = 32
    """sequences optimised in parallel"""
    steps: int = 300
    lr: float = 0.1
    success_at: float = 0.5
    """found when the rounded sequence drives the goal activation at its last step at least this high"""
    seed: int = 0


@dataclass(frozen=True)
class WalkSearchConfig:
    size: int = 17
    """grid side (the training grid by default)"""
    length: int = 24
    """views per walk"""
    restarts: int = 32
    steps: int = 300
    lr: float = 0.1
    density: float | None = None
    """target hole density of the revealed cells; None: ``holes / (size^2 - 3)`` (the training density)"""
    holes: int = 30
    """with ``density`` None, the hole count that gives the target density"""
    density_weight: float = 2.0
    """penalty per unit of revealed-cell hole density above the target"""
    success_at: float = 0.5
    """found when the rounded walk drives the goal activation at its last step at least this high"""
    seed: int = 0

    @property
    def target_density(self) -> float:
        return self.density if self.density is not None else self.holes / (self.size * self.size - 3)


@dataclass(frozen=True)
class AnalysisConfig:
    size: int = 27
    """grid of the recorded episodes (the paper: 27x27)"""
    holes: tuple[int, int] = (90, 100)
    """inclusive range of hole counts, one drawn per episode (the paper: roughly 90-100)"""
    episodes: int = 350
    """trials per agent and env (the paper: 350)"""
    trigger_step: int = 12
    """the trigger's step in the trojan env (the paper: 12)"""
    seed: int = 0
    rule: ResponseRule = field(default_factory=ResponseRule)
    intervention_episodes: int = 1000
    unintentional_configs: str = "paper"
    """'paper' (includes 23x23/0, the paper's example) or a list like '23x23/0,27x27/27'"""
    unintentional_episodes: int = 1000
    goal_units: int = 8
    """how many units the goal-unit edits and plots use (see select_goal_units)"""
    findings_to_plot: int = 2
    """per kind (activation, deactivation)"""
    layout_search: LayoutSearchConfig = field(default_factory=LayoutSearchConfig)
    sequence_search: SequenceSearchConfig = field(default_factory=SequenceSearchConfig)
    walk_search: WalkSearchConfig = field(default_factory=WalkSearchConfig)
    walk_density_weights: tuple[float, ...] = (2.0, 0.0)
    """one walk search per weight of the hole-density penalty (2: ordinary density; 0: any density)"""

    @property
    def grids(self) -> list[GridSpec]:
        lo, hi = self.holes
        return [GridSpec(self.size, h) for h in range(lo, hi + 1)]
