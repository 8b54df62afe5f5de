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
