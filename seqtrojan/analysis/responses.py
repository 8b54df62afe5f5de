"""Classifying each LSTM unit's response to the trigger: impulse, none or step (the paper's section 5.2).

The rule compares one agent's unit in the trojan env (trigger at step t0) with the same unit in the normal env,
both averaged over many episodes, in units of the normal env's spread:

    z(t) = |mean_trojan(t) - mean_normal(t)| / (std_normal(t) + eps)      for t >= t0

* **none**: the unit never moves far: ``max z`` over the response window ``[t0, t0 + response_window)`` is below
  ``threshold``;
* **step**: it moves and stays away: the mean of z over the late window ``[t0 + late_start, t0 + late_end)`` is at
  least ``persist_fraction * threshold``;
* **impulse**: it moves, then returns (the late mean falls below that).

Only steps where at least ``min_episodes`` episodes of both envs are still running count (episodes are ragged).
All of it is :class:`ResponseRule`, so the rule is documented in one place and tunable from config.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from seqtrojan.analysis.config import ResponseRule
from seqtrojan.analysis.traces import StateTrace
from seqtrojan.errors import ConfigError

TYPES = ("impulse", "none", "step")


@dataclass(frozen=True)
class Classification:
    """Per unit: its type, peak deviation in the response window, mean deviation in the late window."""

    types: np.ndarray  # (units,) of "impulse" / "none" / "step"
    peak: np.ndarray  # (units,)
    late: np.ndarray  # (units,)

    def units(self, kind: str) -> np.ndarray:
        return np.flatnonzero(self.types == kind)

    def counts(self) -> dict[str, int]:
        return {kind: int((self.types == kind).sum()) for kind in TYPES}


def masked_mean_std(x: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and standard deviation over episodes of (E, T, units) where ``mask`` (E, T); and counts (T,)."""
    m = mask[..., None].astype(np.float64)
    n = m.sum(0)  # (T, 1)
    safe = np.maximum(n, 1)
    mean = (x * m).sum(0) / safe
    var = (((x - mean) ** 2) * m).sum(0) / safe
    return mean, np.sqrt(var), n[:, 0]


def deviation(
    normal: np.ndarray, normal_mask: np.ndarray, trojan: np.ndarray, trojan_mask: np.ndarray, eps: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """z(t, unit) and the number of usable episodes per step (the smaller of the two envs)."""
    steps = min(normal.shape[1], trojan.shape[1])
    mean_n, std_n, count_n = masked_mean_std(normal[:, :steps], normal_mask[:, :steps])
    mean_t, _, count_t = masked_mean_std(trojan[:, :steps], trojan_mask[:, :steps])
    return np.abs(mean_t - mean_n) / (std_n + eps), np.minimum(count_n, count_t)


def classify_signals(z: np.ndarray, counts: np.ndarray, trigger_step: int, rule: ResponseRule) -> Classification:
    """Classify units from deviations ``z`` (T, units) and usable-episode ``counts`` (T,)."""
    steps = z.shape[0]
    usable = counts >= rule.min_episodes
    t0 = trigger_step
    window = [t for t in range(t0, min(t0 + rule.response_window, steps)) if usable[t]]
    late = [t for t in range(t0 + rule.late_start, min(t0 + rule.late_end, steps)) if usable[t]]
    if not window or not late:
        raise ConfigError(
            f"too few steps after the trigger (step {t0}) with >= {rule.min_episodes} running episodes in both envs "
            f"to classify responses; record more or longer episodes, or lower min_episodes / late_start"
        )
    peak = z[window].max(0)
    late_mean = z[late].mean(0)
    types = np.where(
        peak < rule.threshold, "none", np.where(late_mean >= rule.persist_fraction * rule.threshold, "step", "impulse")
    )
    return Classification(types.astype("<U7"), peak, late_mean)


def classify_units(
    normal: StateTrace, trojan: StateTrace, layer: int, which: str, trigger_step: int, rule: ResponseRule
) -> Classification:
    """Classify one layer's h or c units of one agent from its normal-env and trojan-env traces."""
    z, counts = deviation(normal.states(which, layer), normal.mask, trojan.states(which, layer), trojan.mask, rule.eps)
    return classify_signals(z, counts, trigger_step, rule)
