"""Detector scores as the TrojAI program reports them: ROC-AUC, cross-entropy, Brier score and runtime per model,
each with a 95% percentile-bootstrap interval over models (the models of a split resampled with replacement,
stratified by label so that every resample has both classes), and the same broken down by a model factor.

Cross-entropy and Brier score read the probabilities as given, so a detector that ranks well but is badly
calibrated scores a good AUC and a poor cross-entropy, as in TrojAI; probabilities are clipped to [1e-7, 1 - 1e-7]
for the cross-entropy (a detector saying 0 or 1 and being wrong costs 16.1 nats, not infinity). 2,000 resamples.

With few models a percentile bootstrap is too narrow: at a perfect separation every resample separates perfectly
too, and the interval collapses to [1, 1]. The ROC-AUC therefore also carries Newcombe's score interval
(:func:`seqtrojan.stats.auc_interval`, which does not collapse at 0 or 1); read that one on small splits.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence, Set
from dataclasses import dataclass

import numpy as np

from seqtrojan.errors import SeqTrojanError
from seqtrojan.stats import auc_interval

CLIP = 1e-7
BOOTSTRAP_ROUNDS = 2000


@dataclass(frozen=True)
class Metric:
    """A score with its 95% bootstrap interval; ``value`` None where the models cannot give it (one label only)."""

    value: float | None
    low: float | None
    high: float | None

    def text(self, digits: int = 3) -> str:
        if self.value is None:
            return "n/a"
        if self.low is None or self.high is None:
            return f"{self.value:.{digits}f}"
        return f"{self.value:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


@dataclass(frozen=True)
class Scores:
    """One detector on one set of models."""

    models: int
    poisoned: int
    roc_auc: Metric
    roc_auc_newcombe: Metric
    """the same ROC-AUC with Newcombe's score interval (honest on few models, see the module docstring)"""
    cross_entropy: Metric
    brier: Metric
    runtime_s: Metric
    """mean seconds per model (fitting excluded)"""


def roc_auc(labels: np.ndarray, probs: np.ndarray) -> float:
    """The ROC-AUC (the probability that a poisoned model outscores a clean one; ties count half)."""
    positives, negatives = probs[labels == 1], probs[labels == 0]
    if len(positives) == 0 or len(negatives) == 0:
        raise SeqTrojanError("a ROC-AUC needs poisoned and clean models")
    greater = (positives[:, None] > negatives[None, :]).sum()
    ties = (positives[:, None] == negatives[None, :]).sum()
    return float((greater + 0.5 * ties) / (len(positives) * len(negatives)))


def cross_entropy(labels: np.ndarray, probs: np.ndarray) -> float:
    p = np.clip(probs, CLIP, 1 - CLIP)
    return float(-np.mean(labels * np.log(p) + (1 - labels) * np.log(1 - p)))


def brier(labels: np.ndarray, probs: np.ndarray) -> float:
    return float(np.mean((probs - labels) ** 2))


def score(
    labels: Sequence[int], probs: Sequence[float], runtimes: Sequence[float], seed: int = 0,
    rounds: int = BOOTSTRAP_ROUNDS,
) -> Scores:  # fmt: skip
    """Every score of one detector on one set of models, with bootstrap intervals (``rounds`` resamples)."""
    y = np.asarray(labels, dtype=np.int64)
    p = np.asarray(probs, dtype=np.float64)
    t = np.asarray(runtimes, dtype=np.float64)
    if not (len(y) == len(p) == len(t)) or len(y) == 0:
        raise SeqTrojanError(
            f"scores need one label, probability and runtime per model, got {len(y)}, {len(p)}, {len(t)}"
        )
    if not np.all(np.isfinite(p)) or p.min() < 0 or p.max() > 1:
        raise SeqTrojanError("a detector's probabilities must lie in [0, 1]")
    both = 0 < y.sum() < len(y)
    rng = np.random.default_rng(seed)
    samples = _stratified_resamples(y, rng, rounds)
    metrics = {}
    for name, fn in (("roc_auc", roc_auc), ("cross_entropy", cross_entropy), ("brier", brier)):
        if name == "roc_auc" and not both:
            metrics[name] = Metric(None, None, None)
            continue
        values = [fn(y[s], p[s]) for s in samples]
        metrics[name] = Metric(fn(y, p), *_percentiles(values))
    runtime = Metric(float(t.mean()), *_percentiles([float(t[s].mean()) for s in samples]))
    auc = metrics["roc_auc"].value
    newcombe = (
        Metric(None, None, None) if auc is None else Metric(auc, *auc_interval(auc, int(y.sum()), int((1 - y).sum())))
    )
    return Scores(
        len(y), int(y.sum()), metrics["roc_auc"], newcombe, metrics["cross_entropy"], metrics["brier"], runtime
    )


def score_by_factor(
    labels: Sequence[int], probs: Sequence[float], runtimes: Sequence[float], factors: Sequence[Mapping[str, str]],
    attack_factors: Set[str] = frozenset(), seed: int = 0, rounds: int = BOOTSTRAP_ROUNDS,
) -> dict[str, dict[str, Scores]]:  # fmt: skip
    """:func:`score` on the models of each value of each factor (``factors[i]``: model i's factor -> value). For an
    attack factor (in ``attack_factors``; clean models have the value ``none``) a value's group is its poisoned
    models and every clean model: an attack's AUC is how well its models are told from clean ones."""
    out: dict[str, dict[str, Scores]] = {}
    names = sorted({name for row in factors for name in row})
    for name in names:
        values = sorted({row[name] for row in factors if name in row})
        out[name] = {}
        for value in values:
            if name in attack_factors and value == "none":
                continue
            keep = [
                i for i, row in enumerate(factors)
                if row.get(name) == value or (name in attack_factors and labels[i] == 0)
            ]  # fmt: skip
            out[name][value] = score(
                [labels[i] for i in keep], [probs[i] for i in keep], [runtimes[i] for i in keep], seed, rounds
            )
    return out


def _stratified_resamples(labels: np.ndarray, rng: np.random.Generator, rounds: int) -> list[np.ndarray]:
    groups = [np.flatnonzero(labels == k) for k in (0, 1)]
    groups = [g for g in groups if len(g)]
    return [np.concatenate([rng.choice(g, len(g), replace=True) for g in groups]) for _ in range(rounds)]


def _percentiles(values: Sequence[float]) -> tuple[float | None, float | None]:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return None, None
    return float(np.percentile(finite, 2.5)), float(np.percentile(finite, 97.5))
