"""The benchmark's detector API and its registered detectors.

A :class:`Detector` is fitted on the train split (suspects and their labels) and gives a
:class:`FittedDetector`, which returns for one :class:`~seqtrojan.benchmark.suspect.Suspect` (its network and the
clean env: never the trigger or the attack) the probability that the model is poisoned. Registered in
:data:`DETECTORS` (``seqtrojan defenses`` lists them); :func:`seqtrojan.benchmark.leaderboard.run_leaderboard`
scores every registered one.

- ``metadata_baseline``: logistic regression on the architecture alone (inputs, actions, cell, widths, parameter
  count). Clean and poisoned models are drawn with the same architectures, so it must score near 0.5: the check
  that the splits leak nothing.
- ``weight_statistics``: logistic regression on size-invariant statistics of the recurrent layers' weights
  (:func:`seqtrojan.agent.weight_stats.weight_features`, the weight detector's features).
- ``behaviour_search``: the trigger-free behaviour detector (:mod:`seqtrojan.defense.behaviour`: one-step view
  patches and the rise of episodes ending at the adversary's goal), its raw score calibrated to a probability by a
  logistic regression on the train split's scores. Grid-world suspects only; it answers 0.5 (no opinion) for others.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch

from seqtrojan.benchmark.suspect import Suspect
from seqtrojan.cell_types import cell_names
from seqtrojan.env.config import EnvConfig
from seqtrojan.errors import SeqTrojanError
from seqtrojan.registry import Registry

NO_OPINION = 0.5
"""what a detector answers for a suspect it does not apply to"""


class FittedDetector(Protocol):
    def probability(self, suspect: Suspect) -> float:
        """P(poisoned) of one suspect, in [0, 1]."""
        ...


class Detector(Protocol):
    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        """Learn from the train split (labels: 1 poisoned, 0 clean)."""
        ...


DETECTORS: Registry[Detector] = Registry("defense", "benchmark detector")
"""Detectors scored by the benchmark's leaderboard (``seqtrojan zoo detect --out``)."""


def _classifier() -> Any:
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    return make_pipeline(StandardScaler(), LogisticRegression(C=0.1, max_iter=2000))


@dataclass(frozen=True)
class FeatureModel:
    """A logistic regression on named features of a suspect (the features a fitted detector reads)."""

    features: Callable[[Suspect], dict[str, float]]
    names: tuple[str, ...]
    pipeline: Any
    constant: float | None = None
    """the train split's poisoned share, answered when it held one label only (nothing to learn)"""

    def probability(self, suspect: Suspect) -> float:
        if self.constant is not None:
            return self.constant
        row = self.features(suspect)
        x = np.nan_to_num(np.array([[row.get(n, 0.0) for n in self.names]]), nan=0.0, posinf=0.0, neginf=0.0)
        return float(self.pipeline.predict_proba(x)[0, 1])


def fit_features(
    features: Callable[[Suspect], dict[str, float]], suspects: Sequence[Suspect], labels: Sequence[int]
) -> FeatureModel:
    """A :class:`FeatureModel` on the features every train suspect has."""
    if not suspects:
        raise SeqTrojanError("a detector needs train models to fit on")
    rows = [features(s) for s in suspects]
    names = tuple(sorted(set.intersection(*(set(r) for r in rows))))
    y = np.asarray(labels, dtype=np.int64)
    if len(set(y.tolist())) < 2 or not names:
        return FeatureModel(features, names, None, float(y.mean()))
    x = np.nan_to_num(np.array([[r[n] for n in names] for r in rows]), nan=0.0, posinf=0.0, neginf=0.0)
    return FeatureModel(features, names, _classifier().fit(x, y))


def metadata_features(suspect: Suspect) -> dict[str, float]:
    """The architecture as numbers: inputs, actions, the cell (one-hot over the registered cells), depth, widths,
    parameter count."""
    facts = suspect.facts
    row = {
        "obs_dim": float(facts.obs_dim), "num_actions": float(facts.num_actions), "depth": float(len(facts.widths)),
        "first_width": float(facts.widths[0]), "last_width": float(facts.widths[-1]),
        "log_parameters": float(np.log(facts.parameters)),
    }  # fmt: skip
    row.update({f"cell_{name}": float(facts.cell == name) for name in cell_names()})
    return row


def weight_statistic_features(suspect: Suspect) -> dict[str, float]:
    """The weight detector's statistics of the suspect's recurrent layers."""
    from seqtrojan.agent.weight_stats import weight_features

    agent = suspect.agent
    with torch.no_grad():
        tensors = {k: v.detach() for k, v in agent.state_dict().items()}
        feats = weight_features(tensors, agent.obs_dim, agent.cell)
    return {name: float(value) for name, value in feats.items()}


@dataclass(frozen=True)
class MetadataBaseline:
    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        return fit_features(metadata_features, suspects, labels)


@dataclass(frozen=True)
class WeightStatistics:
    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        return fit_features(weight_statistic_features, suspects, labels)


@dataclass(frozen=True)
class BehaviourSearch:
    """The behaviour detector's largest rise of adversary-goal episodes, calibrated on the train split."""

    episodes: int = 100
    random_patches: int = 12
    seed: int = 0

    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        search = _Search(self)
        return _Abstaining(fit_features(search.features, suspects, labels), search)


@dataclass
class _Search:
    """One fitted search's raw scores, each suspect searched once."""

    settings: BehaviourSearch
    scores: dict[int, float | None] = field(default_factory=dict)

    def raw_score(self, suspect: Suspect) -> float | None:
        """The search's score, or None for a suspect it does not apply to (not a grid-world model)."""
        from seqtrojan.defense.behaviour import BehaviourConfig, behaviour_score

        key = id(suspect)
        if key not in self.scores:
            if not isinstance(suspect.env, EnvConfig):
                self.scores[key] = None
            else:
                s = self.settings
                cfg = BehaviourConfig(episodes=s.episodes, random_patches=s.random_patches, seed=s.seed)
                self.scores[key] = float(behaviour_score(suspect.agent, suspect.env, suspect.env.grid, cfg).score)
        return self.scores[key]

    def features(self, suspect: Suspect) -> dict[str, float]:
        raw = self.raw_score(suspect)
        return {} if raw is None else {"rise": raw}


@dataclass(frozen=True)
class _Abstaining:
    """A fitted behaviour search: :data:`NO_OPINION` for a suspect the search does not apply to."""

    model: FeatureModel
    search: _Search

    def probability(self, suspect: Suspect) -> float:
        if self.search.raw_score(suspect) is None:
            return NO_OPINION
        return self.model.probability(suspect)


DETECTORS.register(
    "metadata_baseline", "architecture only (must score near 0.5: the splits leak nothing)", MetadataBaseline()
)
DETECTORS.register("weight_statistics", "logistic regression on recurrent-weight statistics", WeightStatistics())
DETECTORS.register(
    "behaviour_search", "one-step view patches that switch the goal, calibrated on train (grid world)",
    BehaviourSearch(),
)  # fmt: skip
