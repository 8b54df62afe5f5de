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
- ``query_response``: a meta-classifier (logistic regression) on the suspect's answers to a fixed probe set of
  clean-env episodes, the same for every suspect: policy entropy, hidden-state magnitude and saturation, outcomes
  (:func:`query_response_features`). Any env.
- ``state_probe``: one-step candidate inputs (in the observation's own encoding) replayed over recorded clean
  episodes, and how far and how persistently they move the recurrent state once gone from view
  (:mod:`seqtrojan.benchmark.state_probe`); grid world and MiniGrid views.
- ``state_probe_deviation``: the state probe's features read on both sides (:func:`fit_deviations`): how far they
  lie from the train split's clean models', above or below; the answer to an attacker who trains the state to
  remember less than a clean agent's (``probe_camouflage``).
- ``trigger_reconstruction``: a relaxed one-step trigger (mask and pattern over the view) optimised by gradient to
  change the policy most over the steps after it has left the view, with an L1 size penalty: the recurrent
  Neural Cleanse (:mod:`seqtrojan.benchmark.reconstruction`); grid world and MiniGrid views.
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

from seqtrojan.agent.state import SUMMARY_NAMES, state_summaries
from seqtrojan.benchmark.reconstruction import ReconstructionSettings, reconstruction_features
from seqtrojan.benchmark.state_probe import ProbeSettings, probe_features
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


DETECTORS: Registry[Detector] = Registry("defense", "benchmark_detector")
"""Detectors scored by the benchmark's leaderboard (``seqtrojan zoo detect --out``)."""


def _classifier() -> Any:
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    return make_pipeline(StandardScaler(), LogisticRegression(C=0.1, max_iter=2000))


def _finite(x: np.ndarray) -> np.ndarray:
    return np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def _train_rows(
    features: Callable[[Suspect], dict[str, float]], suspects: Sequence[Suspect], labels: Sequence[int]
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """The train split as a matrix: the names of the features every suspect has, their values (non-finite read as
    0) and the labels."""
    if not suspects:
        raise SeqTrojanError("a detector needs train models to fit on")
    rows = [features(s) for s in suspects]
    names = tuple(sorted(set.intersection(*(set(r) for r in rows))))
    x = _finite(np.array([[r[n] for n in names] for r in rows]).reshape(len(rows), len(names)))
    return names, x, np.asarray(labels, dtype=np.int64)


@dataclass(frozen=True)
class FeatureModel:
    """A logistic regression on named features of a suspect (the features a fitted detector reads)."""

    features: Callable[[Suspect], dict[str, float]]
    names: tuple[str, ...]
    pipeline: Any
    constant: float | None = None
    """the train split's poisoned share, answered when it held one label only (nothing to learn)"""
    transform: Callable[[np.ndarray], np.ndarray] | None = None
    """what the features become before the regression reads them (:class:`Deviation`); None: read as they are"""

    def probability(self, suspect: Suspect) -> float:
        if self.constant is not None:
            return self.constant
        row = self.features(suspect)
        x = _finite(np.array([[row.get(n, 0.0) for n in self.names]]))
        return float(self.pipeline.predict_proba(x if self.transform is None else self.transform(x))[0, 1])


def fit_features(
    features: Callable[[Suspect], dict[str, float]], suspects: Sequence[Suspect], labels: Sequence[int]
) -> FeatureModel:
    """A :class:`FeatureModel` on the features every train suspect has."""
    names, x, y = _train_rows(features, suspects, labels)
    if len(set(y.tolist())) < 2 or not names:
        return FeatureModel(features, names, None, float(y.mean()))
    return FeatureModel(features, names, _classifier().fit(x, y))


MIN_CLEAN_FOR_DEVIATION = 3
"""clean train models :func:`fit_deviations` needs (each one's own deviation is measured against the others)"""


@dataclass(frozen=True)
class Deviation:
    """How far features lie from the train split's clean models', on either side: per feature ``log(1 + z^2)``, z
    the distance from the clean models' ``mean`` in units of their spread ``sd``. A feature pushed below every clean
    model's value is as suspect as one above."""

    mean: np.ndarray
    sd: np.ndarray

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return np.log1p(((x - self.mean) / self.sd) ** 2)

    @staticmethod
    def of(clean: np.ndarray) -> Deviation:
        """From the clean models' feature rows: their mean and sample standard deviation, the latter floored at 1%
        of the mean's size (plus 1e-6) so that a feature on which they agree exactly does not make every other
        value infinitely far."""
        mean = clean.mean(0)
        return Deviation(mean, np.maximum(clean.std(0, ddof=1), 0.01 * np.abs(mean) + 1e-6))


def fit_deviations(
    features: Callable[[Suspect], dict[str, float]], suspects: Sequence[Suspect], labels: Sequence[int]
) -> FeatureModel:
    """A :class:`FeatureModel` on the :class:`Deviation` of the features every train suspect has (the state probe
    read on both sides). Each clean train model's deviation is measured against the other clean models (leave one
    out), as a clean model the detector has never seen would be; fewer than :data:`MIN_CLEAN_FOR_DEVIATION` clean
    train models, or one label only: it answers the train split's poisoned share."""
    names, x, y = _train_rows(features, suspects, labels)
    clean = np.flatnonzero(y == 0)
    if len(set(y.tolist())) < 2 or not names or len(clean) < MIN_CLEAN_FOR_DEVIATION:
        return FeatureModel(features, names, None, float(y.mean()))
    deviation = Deviation.of(x[clean])
    z = deviation(x)
    for i in clean:
        z[i] = Deviation.of(x[clean[clean != i]])(x[i : i + 1])[0]
    return FeatureModel(features, names, _classifier().fit(z, y), transform=deviation)


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
        return _Abstaining(fit_features(search.features, suspects, labels), lambda s: search.raw_score(s) is not None)


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
    """A fitted detector that answers :data:`NO_OPINION` for a suspect it does not apply to."""

    model: FittedDetector
    applies: Callable[[Suspect], bool]

    def probability(self, suspect: Suspect) -> float:
        if not self.applies(suspect):
            return NO_OPINION
        return self.model.probability(suspect)


def _fit_abstaining(
    compute: Callable[[Suspect], dict[str, float]], suspects: Sequence[Suspect], labels: Sequence[int],
    fit: Callable[..., FittedDetector] = fit_features,
) -> FittedDetector:  # fmt: skip
    """A logistic regression (``fit``: :func:`fit_features` or :func:`fit_deviations`) on features that are costly
    (each suspect's computed once, then kept) and empty where they do not apply to a suspect (it then answers
    :data:`NO_OPINION`)."""
    cache: dict[int, dict[str, float]] = {}

    def features(suspect: Suspect) -> dict[str, float]:
        if id(suspect) not in cache:
            cache[id(suspect)] = compute(suspect)
        return cache[id(suspect)]

    return _Abstaining(fit(features, suspects, labels), lambda s: bool(features(s)))


@dataclass(frozen=True)
class StateProbe:
    """The recurrent-state probe (:mod:`seqtrojan.benchmark.state_probe`): how far and how persistently one-step
    candidate inputs move the state, the trigger gone from view; a logistic regression on the train split."""

    settings: ProbeSettings = field(default_factory=ProbeSettings)

    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        return _fit_abstaining(lambda suspect: probe_features(suspect, self.settings), suspects, labels)


@dataclass(frozen=True)
class StateProbeDeviation:
    """The state probe's features read on both sides (:func:`fit_deviations`): how far they lie from the train
    split's clean models', so that a state trained to remember less than a clean one (the ``probe_camouflage``
    attacker) is as suspect as one that remembers a trigger."""

    settings: ProbeSettings = field(default_factory=ProbeSettings)

    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        return _fit_abstaining(
            lambda suspect: probe_features(suspect, self.settings), suspects, labels, fit=fit_deviations
        )


@dataclass(frozen=True)
class TriggerReconstruction:
    """Trigger reconstruction by optimisation (:mod:`seqtrojan.benchmark.reconstruction`): the largest persistent
    change of the policy a small relaxed one-step trigger can make, and what it takes; a logistic regression on the
    train split."""

    settings: ReconstructionSettings = field(default_factory=ReconstructionSettings)

    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        return _fit_abstaining(lambda suspect: reconstruction_features(suspect, self.settings), suspects, labels)


class _ProbeRecorder:
    """Sums, over the running steps of a probe's episodes, what :func:`query_response_features` summarises."""

    def __init__(self) -> None:
        self.steps = 0
        self.sums: dict[str, float] = {}

    def add(self, name: str, values: torch.Tensor) -> None:
        self.sums[name] = self.sums.get(name, 0.0) + float(values.sum())

    def on_step(self, step: Any) -> None:
        running = step.running
        if step.logits is None or step.state is None or not bool(running.any()):
            return
        self.steps += int(running.sum())
        probs = torch.softmax(step.logits[running], -1)
        self.add("entropy", -(probs * torch.log(probs.clamp_min(1e-12))).sum(-1))
        self.add("top_probability", probs.max(-1).values)
        summaries = state_summaries([layer.h[running] for layer in step.state.layers])
        names = [f"layer{i}_{name}" for i in range(len(step.state.layers)) for name in SUMMARY_NAMES]
        for j, name in enumerate(names):
            self.add(name, summaries[:, j].contiguous())

    def on_end(self, batch: Any) -> None:
        self.batch = batch


def query_response_features(suspect: Suspect, episodes: int = 64, seed: int = 0) -> dict[str, float]:
    """The suspect's answers to a fixed probe: ``episodes`` clean-env episodes seeded alike for every suspect,
    summarised as per-step means over its running steps (policy entropy and top probability; per layer the mean
    |h|, the share of units with |h| > 0.9 and the spread of h across units; the layer index counted from the first,
    so suspects of other depths share the first layers' features) and per-episode outcome shares and length."""
    from seqtrojan.agent.policy import AgentPolicy
    from seqtrojan.env.codes import OUTCOME_NAMES
    from seqtrojan.env.rollout import run_episodes
    from seqtrojan.world.episodes import episode_env

    env = episode_env(suspect.env, None, episodes, trojan=False, seed=seed)
    recorder = _ProbeRecorder()
    try:
        batch = run_episodes(env, AgentPolicy(suspect.agent, seed=seed), seed=seed, recorders=[recorder])
    finally:
        close = getattr(env, "close", None)
        if close is not None:
            close()
    row = {name: total / max(recorder.steps, 1) for name, total in recorder.sums.items()}
    row["length"] = float(batch.length.float().mean())
    for code, name in enumerate(OUTCOME_NAMES[1:], start=1):
        row[f"outcome_{name}"] = float((batch.outcome == code).float().mean())
    return row


@dataclass(frozen=True)
class QueryResponse:
    """A meta-classifier on the suspect's answers to a fixed probe set of clean episodes
    (:func:`query_response_features`), TrojAI performers' common approach."""

    episodes: int = 64
    seed: int = 0

    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        def features(suspect: Suspect) -> dict[str, float]:
            return query_response_features(suspect, self.episodes, self.seed)

        return fit_features(features, suspects, labels)


@dataclass(frozen=True)
class AllFeatures:
    """One logistic regression on the features of four detectors together (weight statistics, the query response,
    the state probe and trigger reconstruction, each name prefixed by its source): an attacker who evades one
    reading must evade the others in the same model, and the regression weighs them on the train split. The state
    probe's and trigger reconstruction's features are absent where they do not apply (the regression then reads the
    features every train model has)."""

    probe: ProbeSettings = field(default_factory=ProbeSettings)
    reconstruction: ReconstructionSettings = field(default_factory=ReconstructionSettings)
    episodes: int = 64
    seed: int = 0

    def parts(self) -> dict[str, Callable[[Suspect], dict[str, float]]]:
        return {
            "weights": weight_statistic_features,
            "query": lambda suspect: query_response_features(suspect, self.episodes, self.seed),
            "probe": lambda suspect: probe_features(suspect, self.probe),
            "reconstruction": lambda suspect: reconstruction_features(suspect, self.reconstruction),
        }

    def features(self, suspect: Suspect) -> dict[str, float]:
        return {f"{source}/{name}": value for source, compute in self.parts().items()
                for name, value in compute(suspect).items()}  # fmt: skip

    def fit(self, suspects: Sequence[Suspect], labels: Sequence[int]) -> FittedDetector:
        return _fit_abstaining(self.features, suspects, labels)  # never abstains: weight statistics always apply


DETECTORS.register(
    "metadata_baseline", "architecture only (must score near 0.5: the splits leak nothing)", MetadataBaseline()
)
DETECTORS.register("weight_statistics", "logistic regression on recurrent-weight statistics", WeightStatistics())
DETECTORS.register(
    "behaviour_search", "one-step view patches that switch the goal, calibrated on train (grid world)",
    BehaviourSearch(),
)  # fmt: skip
DETECTORS.register(
    "state_probe", "one-step candidate inputs whose mark on the recurrent state persists after they are gone",
    StateProbe(),
)  # fmt: skip
DETECTORS.register(
    "state_probe_deviation",
    "the state probe's features read on both sides: their distance from the train split's clean models', so a "
    "state that remembers less than a clean one is suspect too",
    StateProbeDeviation(),
)  # fmt: skip
DETECTORS.register(
    "query_response", "meta-classifier on the policy's and state's answers to fixed clean probe episodes",
    QueryResponse(),
)  # fmt: skip
DETECTORS.register(
    "trigger_reconstruction",
    "a small one-step view perturbation optimised to change the policy after it is gone (recurrent Neural Cleanse)",
    TriggerReconstruction(),
)  # fmt: skip
DETECTORS.register(
    "all_features",
    "one logistic regression on the weight statistics', query response's, state probe's and trigger "
    "reconstruction's features together",
    AllFeatures(),
)  # fmt: skip
