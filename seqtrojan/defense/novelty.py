"""The input-novelty baseline: alarm when the agent *sees* something rare, whatever its state does.

It learns from the deployed agent's own clean episodes which observations occur (no trigger knowledge): each 3x3
view's cell codes (:meth:`seqtrojan.env.core.TrojanGridCore.observe_codes`) encoded as one integer per view, and
the frequency of every (view cell, code) pair. A step's score is the rarity of what the agent saw:

* ``pattern``: ``-log((count + a) / (N + a))`` of the whole view among the N calibration views (``a`` the
  smoothing; an unseen view scores ``-log(a / (N + a))``);
* ``cells``: the sum over the view's cells of ``-log((count + a) / (N + 6a))``, the rarity of that cell's code at
  that place. A sum, not the largest: rarity saturates at "never seen", and the largest would score a view with
  one unseen (cell, code) pair like the dedicated trigger over all nine cells. Measured: on one agent of the smoke
  matrix whose clean episodes showed such a pair now and then, the largest put the threshold at that ceiling and
  the trigger was never detected (0 of 300 episodes); the sum ranks the trigger far above;
* ``both`` (the default): their sum, so that among views never seen, one with codes never seen at their places
  (the paper's dedicated trigger code) scores above one made of familiar codes.

An episode's score is its running maximum; the threshold is the split-conformal quantile of held-out clean peaks
(:func:`seqtrojan.defense.online.conformal_threshold`), as for the state monitors. Run online through
:class:`~seqtrojan.defense.monitor.MonitoredPolicy`, an alarm can reset the agent's state like theirs.

What it tells: a detection that this baseline matches is input novelty, not evidence that the state monitors read
the backdoor. A trigger drawn in ordinary codes that occur in clean episodes (an in-distribution pattern) is not
novel, and this detector cannot see it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import RecurrentState
from seqtrojan.config import EnvSection
from seqtrojan.defense.online import (
    MonitorConfig,
    conformal_threshold,
    record_clean_codes,
    split,
    view_codes,
)
from seqtrojan.env.codes import NUM_CHANNELS
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.errors import ConfigError, ShapeError

EXACT_CELLS = 24
"""views of up to this many cells are encoded exactly (6**24 < 2**63); larger ones are hashed"""
_HASH = 0x9E3779B97F4A7C15  # an odd 64-bit multiplier (the golden ratio's)


def encode_views(codes: torch.Tensor) -> torch.Tensor:
    """(B,) int64: one integer per view of ``codes`` (B, cells) int64. Exact (base 6) for views of up to
    :data:`EXACT_CELLS` cells, the paper's 3x3 included; a 64-bit polynomial hash for larger views."""
    cells = codes.shape[-1]
    if cells <= EXACT_CELLS:
        weights = [NUM_CHANNELS**i for i in range(cells)]
    else:
        weights = [((pow(_HASH, i + 1, 1 << 64) + (1 << 63)) % (1 << 64)) - (1 << 63) for i in range(cells)]
    w = torch.tensor(weights, dtype=torch.int64, device=codes.device)
    offset = 0 if cells <= EXACT_CELLS else 1  # the hash must tell code 0 from an absent cell
    return ((codes.long() + offset) * w).sum(-1)


@dataclass(frozen=True)
class NoveltyConfig:
    """What :class:`InputNovelty` counts; the calibration itself follows the :class:`MonitorConfig`."""

    features: Literal["pattern", "cells", "both"] = "both"
    """score the rarity of the whole view (pattern), of each cell's code at its place (cells), or their sum"""
    smoothing: float = 0.5
    """the additive (pseudo-)count ``a`` of the smoothed frequencies; > 0"""

    def __post_init__(self) -> None:
        if self.features not in ("pattern", "cells", "both"):
            raise ConfigError(f"novelty features must be pattern, cells or both, got {self.features!r}")
        if not self.smoothing > 0:
            raise ConfigError(f"novelty smoothing must be > 0, got {self.smoothing}")


class InputNovelty:
    """Rarity of the observation among clean episodes' observations (see the module docstring)."""

    def __init__(
        self, keys: np.ndarray, key_counts: np.ndarray, cell_counts: np.ndarray, total: int, threshold: float,
        options: NoveltyConfig | None = None,
    ) -> None:  # fmt: skip
        self.options = options or NoveltyConfig()
        a = self.options.smoothing
        order = np.argsort(keys)
        self.keys = torch.as_tensor(np.asarray(keys)[order], dtype=torch.int64)  # (K,) seen views, sorted
        counts = torch.as_tensor(np.asarray(key_counts)[order], dtype=torch.float64)  # (K,)
        self.key_counts = counts
        self.cell_counts = torch.as_tensor(cell_counts, dtype=torch.float64)  # (cells, 6)
        self.total = int(total)
        self.pattern_rarity = (-torch.log((counts + a) / (total + a))).float()  # (K,)
        self.unseen_rarity = float(-np.log(a / (total + a)))
        self.cell_rarity = (-torch.log((self.cell_counts + a) / (total + NUM_CHANNELS * a))).float()  # (cells, 6)
        self.threshold = threshold

    @property
    def units(self) -> tuple[int, ...]:
        return ()

    @classmethod
    def from_codes(
        cls, codes: np.ndarray, threshold: float = float("inf"), options: NoveltyConfig | None = None
    ) -> InputNovelty:
        """Count the views ``codes`` (N, cells) int64 (every step of the statistics episodes)."""
        codes = np.asarray(codes, dtype=np.int64)
        if codes.ndim != 2 or len(codes) == 0:
            raise ShapeError(f"novelty statistics need (views, cells) codes, got shape {codes.shape}")
        keys, counts = np.unique(encode_views(torch.from_numpy(codes)).numpy(), return_counts=True)
        cells = np.stack([np.bincount(codes[:, i], minlength=NUM_CHANNELS) for i in range(codes.shape[1])])
        return cls(keys, counts, cells, len(codes), threshold, options)

    grid_only = True
    """it reads the grid world's view codes (:func:`~seqtrojan.defense.online.monitor_applies`)"""

    @classmethod
    def calibrate(
        cls, agent: RecurrentActorCritic, env: EnvSection, grid: GridSpec | None, cfg: MonitorConfig,
        device: str | torch.device = "cpu", options: NoveltyConfig | None = None,
    ) -> InputNovelty:  # fmt: skip
        """Counts from the first half of ``cfg.calibration_episodes`` clean episodes, the threshold from the
        other half's per-episode peak scores."""
        if not isinstance(env, EnvConfig) or grid is None:
            raise ConfigError("input_novelty reads the grid world's view codes: it watches grid-world agents only")
        clean = record_clean_codes(agent, env, grid, episodes=cfg.calibration_episodes, seed=cfg.seed, device=device)
        half = split(cfg.calibration_episodes)
        detector = cls.from_codes(clean.codes[:half][clean.mask[:half]], options=options)
        held = clean.codes[half:]  # (E, T, cells)
        scores = detector.score_codes(torch.from_numpy(held.reshape(-1, held.shape[-1]))).numpy()
        scores = np.where(clean.mask[half:], scores.reshape(held.shape[:2]), -np.inf)
        detector.threshold = conformal_threshold(scores.max(1), cfg.false_alarm_target)
        return detector

    def score_codes(self, codes: torch.Tensor) -> torch.Tensor:
        """(B,) float32 rarity of the views ``codes`` (B, cells) int64."""
        features = self.options.features
        score = torch.zeros(codes.shape[0], dtype=torch.float32, device=codes.device)
        if features in ("pattern", "both"):
            keys = self.keys.to(codes.device)
            q = encode_views(codes)
            idx = torch.searchsorted(keys, q).clamp(max=max(len(keys) - 1, 0))
            seen = keys[idx] == q if len(keys) else torch.zeros_like(q, dtype=torch.bool)
            rarity = self.pattern_rarity.to(codes.device)[idx] if len(keys) else score
            score = score + torch.where(seen, rarity, torch.full_like(score, self.unseen_rarity))
        if features in ("cells", "both"):
            table = self.cell_rarity.to(codes.device)  # (cells, 6)
            per_cell = table.gather(1, codes.long().T).T  # (B, cells)
            score = score + per_cell.sum(-1)
        return score

    def score_step(self, obs: torch.Tensor, state: RecurrentState, t: torch.Tensor) -> torch.Tensor:
        """(B,) the rarity of the observation the agent acted on (its state is not read)."""
        return self.score_codes(view_codes(obs))
