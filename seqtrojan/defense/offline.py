"""Offline detection from the weights alone (the paper's second proposal and its open problem 1), scored the way
the TrojAI program scores detectors: ROC-AUC, cross-entropy and Brier score of predicted probabilities on
held-out models.

Features are size-invariant statistics of the LSTM parameters, so that a zoo of varied architectures shares one
feature space: per gate (input, forget, cell, output) of the first and the last LSTM layer, statistics of the
input weights, the recurrent weights and the biases (mean, std, max |w|, skewness, kurtosis, RMS), spectra of the
weight blocks (largest singular value over RMS, effective rank), and, for the first layer, the relative norm of
the input weights reading each of the six cell codes (a defender knows the input encoding). The detector is a
standardised logistic regression; predictions for every model come from stratified k-fold cross-validation, so
each model is scored by a detector that never saw it. Feature groups are also scored alone, to tell what works,
and :func:`held_out_group_scores` asks whether the detector carries over to a kind of model (an architecture, a
trigger code, a curriculum) absent from its training models. :func:`detect_zoo` gathers it all in a
:class:`~seqtrojan.defense.results.DetectionResult`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from seqtrojan.agent.checkpoint import WEIGHTS, load_agent
from seqtrojan.agent.weight_stats import weight_features as torch_weight_features
from seqtrojan.defense.behaviour import BehaviourDetector
from seqtrojan.defense.results import (
    DetectionResult,
    FunctionalSplit,
    GroupScores,
    HeldOutGroup,
    HeldOutScores,
    Prediction,
    Rejected,
)
from seqtrojan.errors import CheckpointError, SeqTrojanError
from seqtrojan.registry import Registry
from seqtrojan.stats import reaches


class OfflineDetector(Protocol):
    """What a registered offline detector offers a study (the matrix): a score per model folder (higher: more
    likely backdoored), after fitting on a zoo where ``needs_zoo``. ``grid_only``: it reads the grid world's
    views, so it scores grid-world models only."""

    @property
    def needs_zoo(self) -> bool: ...

    @property
    def grid_only(self) -> bool: ...

    def score_models(self, models: Sequence[Path], zoo: Path | None, device: str | torch.device = "cpu") -> list[float]:
        """One score per model folder in ``models`` (``zoo``: the fitted zoo's folder, where ``needs_zoo``)."""
        ...


@dataclass(frozen=True)
class WeightDetector:
    """The weight detector as registered: logistic regression on weight statistics, fitted on a zoo's models
    (:func:`fit_weight_detector`); :func:`detect_zoo` scores it on the zoo itself, held out by folds."""

    needs_zoo: bool = True
    grid_only: bool = False

    def score_models(self, models: Sequence[Path], zoo: Path | None, device: str | torch.device = "cpu") -> list[float]:
        if zoo is None:
            raise SeqTrojanError("the weight detector is fitted on a zoo: give the zoo's folder")
        detector = fit_weight_detector(zoo)
        return [float(detector.probability(path)) for path in models]


DETECTORS: Registry[OfflineDetector] = Registry("defense", "detector")
"""Offline detectors (:class:`OfflineDetector`): the weight detector (:class:`WeightDetector`; scored on a zoo by
:func:`detect_zoo`) and the behavioural one (:class:`~seqtrojan.defense.behaviour.BehaviourDetector`)."""

GROUPS = ("gate_stats", "spectral", "input_codes")


def weight_features(tensors: dict[str, np.ndarray], obs_dim: int, cell: str) -> dict[str, float]:
    """Named features of one model's parameters (``cells.<i>.weight_ih`` etc., layers of ``cell``); see the module
    docstring. Computed by :func:`seqtrojan.agent.weight_stats.weight_features`, the same function a
    weight-camouflage attacker differentiates (tests/train/test_penalties.py checks it against an independent numpy
    reference)."""
    with torch.no_grad():
        feats = torch_weight_features({k: torch.from_numpy(np.asarray(v)) for k, v in tensors.items()}, obs_dim, cell)
    return {name: float(value) for name, value in feats.items()}


@dataclass(frozen=True)
class ZooModel:
    model_id: str
    label: int  # 1 backdoored, 0 clean
    features: dict[str, float]
    truth: dict[str, Any]
    attack_success: float | None = None
    """a backdoored model's final trojan-env success, from its card (None for clean models)"""


def load_zoo_model(path: Path) -> ZooModel:
    """One zoo model's features and ground truth. Anything wrong with the folder (a pickled, corrupt or malformed
    model or card, a ``label.json`` that is not a valid label, non-finite weights) is a one-line
    :class:`~seqtrojan.errors.SeqTrojanError` naming the problem."""
    from seqtrojan.zoo.build import load_zoo_agent, read_label

    agent, _, card = load_zoo_agent(path)
    truth = read_label(path)
    tensors = {k: v.detach().numpy() for k, v in agent.state_dict().items()}
    bad = sorted(k for k, v in tensors.items() if not np.isfinite(v).all())
    if bad:
        raise CheckpointError(f"{WEIGHTS} in {str(path)!r} holds NaN or infinite values (in {', '.join(bad)})")
    label = 1 if truth["label"] == "backdoored" else 0
    attack = card.get("metrics", {}).get("trojan_success") if label else None
    if attack is not None and not (isinstance(attack, (int, float)) and not isinstance(attack, bool)):
        raise CheckpointError(f"card.json in {str(path)!r}: metrics.trojan_success must be a number, got {attack!r}")
    return ZooModel(path.name, label, weight_features(tensors, agent.obs_dim, agent.cell), truth, attack)


def load_zoo_features(zoo: Path) -> tuple[list[ZooModel], list[Rejected]]:
    """Features of every model in ``zoo/models``; a model that cannot be used (pickled, corrupt, a malformed or
    mismatched card, a bad ``label.json``) or that has not learned its task (the zoo's ``learned_at``) is listed as
    rejected with its reason (one line), and the rest go on."""
    from seqtrojan.zoo.build import not_learned_reason

    models, rejected = [], []
    folder = zoo / "models"
    if not folder.is_dir():
        raise SeqTrojanError(f"{str(zoo)!r} is not a zoo (no models/ folder)")
    for path in sorted(p for p in folder.iterdir() if p.is_dir()):
        try:
            model = load_zoo_model(path)
        except SeqTrojanError as err:
            rejected.append(Rejected(path.name, " ".join(str(err).split())))
            continue
        not_learned = not_learned_reason(model.truth)
        if not_learned is not None:
            rejected.append(Rejected(path.name, not_learned))
        else:
            models.append(model)
    return models, rejected


def _matrix(models: list[ZooModel], group: str | None) -> tuple[np.ndarray, list[str]]:
    names = sorted(set.intersection(*(set(m.features) for m in models)))
    if group is not None:
        names = [n for n in names if n.startswith(group + "/")]
    return np.array([[m.features[n] for n in names] for m in models], dtype=np.float64), names


def _detector():
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    return make_pipeline(StandardScaler(), LogisticRegression(C=0.1, max_iter=2000))


def _scores(y: np.ndarray, probs: np.ndarray) -> dict[str, float]:
    """roc_auc, cross_entropy and brier of the probabilities ``probs`` of the labels ``y``."""
    from sklearn.metrics import brier_score_loss, log_loss, roc_auc_score

    clipped = np.clip(probs, 1e-6, 1 - 1e-6)
    return {
        "roc_auc": float(roc_auc_score(y, probs)),
        "cross_entropy": float(log_loss(y, clipped, labels=[0, 1])),
        "brier": float(brier_score_loss(y, probs)),
    }


def cross_validated_scores(
    models: list[ZooModel], group: str | None = None, folds: int = 5, seed: int = 0
) -> GroupScores:
    """Out-of-fold probabilities of 'backdoored' for every model, and ROC-AUC, cross-entropy and Brier score."""
    from sklearn.model_selection import StratifiedKFold

    x, names = _matrix(models, group)
    y = np.array([m.label for m in models])
    counts = np.bincount(y, minlength=2)
    if counts.min() < 2:
        raise SeqTrojanError(
            "offline detection needs at least 2 clean and 2 backdoored models (after any rejected ones), "
            f"the zoo has {counts[0]} clean and {counts[1]} backdoored"
        )
    folds = max(2, min(folds, int(counts.min())))
    x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    probs = np.zeros(len(y))
    for train, test in StratifiedKFold(folds, shuffle=True, random_state=seed).split(x, y):
        probs[test] = _detector().fit(x[train], y[train]).predict_proba(x[test])[:, 1]
    predictions = tuple(Prediction(m.model_id, int(t), float(p)) for m, t, p in zip(models, y, probs))
    return GroupScores(group or "all", len(names), len(y), folds, **_scores(y, probs), predictions=predictions)


@dataclass(frozen=True)
class FittedWeightDetector:
    """The weight detector trained on a whole zoo, to score models outside it (the attack x defense matrix)."""

    pipeline: Any
    feature_names: tuple[str, ...]

    def probability(self, model: Path) -> float:
        """P(backdoored) of the model folder ``model`` (read through the same checks as a zoo model's weights)."""
        agent, _, _ = load_agent(model)
        tensors = {k: v.detach().numpy() for k, v in agent.state_dict().items()}
        features = weight_features(tensors, agent.obs_dim, agent.cell)
        missing = sorted(set(self.feature_names) - set(features))
        if missing:
            raise SeqTrojanError(f"{str(model)!r} lacks weight features the detector was trained on: {missing[:3]}")
        x = np.nan_to_num(np.array([[features[n] for n in self.feature_names]]), nan=0.0, posinf=0.0, neginf=0.0)
        return float(self.pipeline.predict_proba(x)[0, 1])


def fit_weight_detector(zoo: Path) -> FittedWeightDetector:
    """The detector trained on every usable model of ``zoo`` (all features)."""
    models, _ = load_zoo_features(zoo)
    y = np.array([m.label for m in models])
    if len(models) == 0 or np.bincount(y, minlength=2).min() < 1:
        raise SeqTrojanError(f"the zoo {str(zoo)!r} needs clean and backdoored models to train the weight detector")
    x, names = _matrix(models, None)
    x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    return FittedWeightDetector(_detector().fit(x, y), tuple(names))


HELD_OUT_KEYS = ("lstm_sizes", "trigger_value", "curriculum")


def held_out_group_scores(models: list[ZooModel], key: str) -> HeldOutScores:
    """Does the detector generalise to a kind of model it never saw? For each value of the zoo variation ``key``
    (an architecture, a trigger's cell code, a curriculum), train on the models without that value and score the
    models with it; then score all those out-of-group predictions together. Clean models carry a (randomly drawn,
    unused) trigger value too, so leaving out a trigger value also leaves out a random share of clean models.
    Values whose held-out or remaining models lack a label are skipped and listed."""
    x, _ = _matrix(models, None)
    x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    y = np.array([m.label for m in models])
    values = np.array([json.dumps(m.truth.get("variation", {}).get(key)) for m in models])
    probs = np.full(len(y), np.nan)
    groups, skipped = [], []
    for value in sorted(set(values)):
        test = values == value
        if len(set(y[~test])) < 2 or test.sum() == 0:
            skipped.append(json.loads(value))
            continue
        probs[test] = _detector().fit(x[~test], y[~test]).predict_proba(x[test])[:, 1]
        scores = _scores(y[test], probs[test]) if len(set(y[test])) == 2 else _NO_SCORES
        groups.append(HeldOutGroup(json.loads(value), int(test.sum()), int(y[test].sum()), **scores))
    scored = ~np.isnan(probs)
    pooled = _scores(y[scored], probs[scored]) if len(set(y[scored])) == 2 else _NO_SCORES
    return HeldOutScores(key, int(scored.sum()), **pooled, groups=tuple(groups), skipped=tuple(skipped))


_NO_SCORES: dict[str, Any] = {"roc_auc": None, "cross_entropy": None, "brier": None}
"""the scores of models that all have the same label (none can be computed)"""


def _functional_at(zoo: Path) -> float:
    """The zoo config's ``functional_at`` (0.5 when the zoo has no ``zoo.json``)."""
    spec = zoo / "zoo.json"
    if not spec.exists():
        return 0.5
    try:
        at = json.loads(spec.read_text()).get("functional_at", 0.5)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
        at = None
    if not isinstance(at, (int, float)) or isinstance(at, bool) or not 0 <= at <= 1:
        raise SeqTrojanError(f"{str(spec)!r} is not a zoo config with a functional_at between 0 and 1")
    return float(at)


def _functional_split(models: list[ZooModel], predictions: Sequence[Prediction], at: float) -> FunctionalSplit:
    """Backdoored models whose backdoor works (final trojan-env success >= ``at``) and those whose training did
    not make it work, each scored against all clean models with the same out-of-fold predictions: does the
    detector find working backdoors, or the backdoor training procedure?"""
    from sklearn.metrics import roc_auc_score

    clean = [p.p_backdoored for m, p in zip(models, predictions) if m.label == 0]
    counts, aucs = {}, {}
    for name, keep in (("functional", lambda a: reaches(a, at)), ("not_functional", lambda a: not reaches(a, at))):
        probs = [p.p_backdoored for m, p in zip(models, predictions)
                 if m.label == 1 and m.attack_success is not None and keep(m.attack_success)]  # fmt: skip
        counts[name] = len(probs)
        aucs[f"{name}_roc_auc"] = (
            float(roc_auc_score([1] * len(probs) + [0] * len(clean), probs + clean)) if probs and clean else None
        )
    return FunctionalSplit(at, counts["functional"], counts["not_functional"], **aucs)


def detect_zoo(zoo: Path, folds: int = 5, seed: int = 0) -> DetectionResult:
    """Score the detector with all features and with each feature group alone; AUC by trigger value too. Models
    that cannot be used are skipped and listed under ``rejected`` with their reasons; the rest are scored."""
    at = _functional_at(zoo)
    models, rejected = load_zoo_features(zoo)
    # a group without features is left out (the input-code norms read the grid world's one-hot codes only)
    groups = [g for g in GROUPS if not models or _matrix(models, g)[1]]
    try:
        scores = tuple(cross_validated_scores(models, group, folds, seed) for group in (None, *groups))
    except SeqTrojanError as err:
        if not rejected:
            raise
        named = "; ".join(f"{r.model}: {r.reason}" for r in rejected[:3]) + ("; ..." if len(rejected) > 3 else "")
        raise SeqTrojanError(f"{err}; {len(rejected)} model(s) rejected ({named})") from None
    full = scores[0].predictions
    by_value: dict[str, list[tuple[int, float]]] = {}
    for m, pred in zip(models, full):
        if m.label == 1 and m.truth.get("trigger"):
            by_value.setdefault(m.truth["trigger"]["value"], []).append((1, pred.p_backdoored))
    clean = [(0, p.p_backdoored) for m, p in zip(models, full) if m.label == 0]
    from sklearn.metrics import roc_auc_score

    held_out = tuple(held_out_group_scores(models, key) for key in HELD_OUT_KEYS)
    auc_by_trigger_value = {
        value: float(roc_auc_score([t for t, _ in pairs + clean], [p for _, p in pairs + clean]))
        for value, pairs in by_value.items() if clean
    }  # fmt: skip
    return DetectionResult(tuple(rejected), scores, held_out, _functional_split(models, full, at), auc_by_trigger_value)


DETECTORS.register(
    "weight_detector", "offline: logistic regression on LSTM weight statistics, scored on a zoo", WeightDetector()
)
DETECTORS.register(
    "behaviour_detector",
    "trigger-free: how much one-step view patches raise the share of episodes ending at the adversary's goal",
    BehaviourDetector(),
)
