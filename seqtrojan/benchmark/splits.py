"""A zoo as a benchmark: its models read with their truth and factors, and split into train, test and holdout.

Holdout holds every model with a held-out factor value (an architecture, an env, a cell kind the train split never
shows; poisoned models by a held-out attack value, a trigger value or a recipe, together with a random share of the
clean models, so that the split has both classes); the other models are split into train and test by label,
``test_share`` of each label to test. The assignment is a pure function of the model ids, their truth and the seed,
written to ``splits.json``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from seqtrojan.errors import ConfigError, SeqTrojanError

SPLITS = ("train", "test", "holdout")
ATTACK_FACTORS = frozenset({"trigger_value", "attack"})
"""factors that describe a poisoned model's attack: a clean model has the value ``none`` and belongs, when scores
are broken down, to every attack value's group (an attack's AUC is its poisoned models against all clean ones)"""


@dataclass(frozen=True)
class ZooEntry:
    """One usable zoo model: its folder, its truth (1 poisoned, 0 clean) and its factors (name -> value)."""

    model_id: str
    folder: Path
    label: int
    factors: dict[str, str]


@dataclass(frozen=True)
class SplitConfig:
    test_share: float = 0.5
    """share of each label's non-holdout models put in test"""
    holdout: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """factor -> values whose models only the holdout split holds (factor values as :func:`model_factors` writes
    them, e.g. ``lstm_sizes: ["[64, 32]"]``)"""
    holdout_clean_share: float = 0.25
    """share of the clean models put in holdout when every held-out factor is an attack factor"""
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.test_share < 1:
            raise ConfigError(f"test_share must be in (0, 1), got {self.test_share}")
        if not 0 <= self.holdout_clean_share < 1:
            raise ConfigError(f"holdout_clean_share must be in [0, 1), got {self.holdout_clean_share}")


def model_factors(truth: Mapping) -> dict[str, str]:
    """A zoo model's factors from its ``label.json``: env, cell, widths and, for a poisoned model, the trigger's
    cell value (``none`` for a clean one); in a zoo that draws attack recipes (its models record ``attack``), the
    recipe too (``none`` for a clean one). A zoo without recipes has no ``attack`` factor, so its breakdowns stay
    as they were."""
    variation = truth.get("variation", {})
    poisoned = truth.get("label") == "backdoored"
    factors = {
        "env": str(variation.get("env", "grid")),
        "cell": str(variation.get("cell", "lstm")),
        "lstm_sizes": json.dumps(variation.get("lstm_sizes")),
        "trigger_value": str(variation.get("trigger_value")) if poisoned else "none",
    }
    if "attack" in variation:
        factors["attack"] = str(variation["attack"]) if poisoned else "none"
    return factors


def assign_splits(entries: Sequence[ZooEntry], cfg: SplitConfig) -> dict[str, str]:
    """model id -> train, test or holdout (see the module docstring)."""
    unknown = sorted(set(cfg.holdout) - {name for e in entries for name in e.factors})
    if unknown:
        raise ConfigError(f"holdout names factors the zoo's models do not have: {unknown}")
    rng = np.random.default_rng([cfg.seed, 104729])
    out: dict[str, str] = {}
    held = [e for e in entries if any(e.factors.get(k) in values for k, values in cfg.holdout.items())]
    out.update({e.model_id: "holdout" for e in held})
    if cfg.holdout and set(cfg.holdout) <= ATTACK_FACTORS:
        clean = [e for e in entries if e.label == 0]
        count = round(cfg.holdout_clean_share * len(clean))
        out.update({clean[i].model_id: "holdout" for i in sorted(rng.permutation(len(clean))[:count])})
    for label in (0, 1):
        rest = [e for e in entries if e.label == label and e.model_id not in out]
        order = rng.permutation(len(rest))
        test = round(cfg.test_share * len(rest))
        for rank, i in enumerate(order):
            out[rest[i].model_id] = "test" if rank < test else "train"
    return out


def check_trainable(entries: Sequence[ZooEntry], splits: Mapping[str, str]) -> None:
    """The train split must hold both labels (a one-line error naming the counts otherwise)."""
    train = [e.label for e in entries if splits[e.model_id] == "train"]
    if len(set(train)) < 2:
        raise SeqTrojanError(
            f"the train split holds {train.count(0)} clean and {train.count(1)} poisoned models: a benchmark needs "
            "both (a larger zoo, or a smaller test_share)"
        )
