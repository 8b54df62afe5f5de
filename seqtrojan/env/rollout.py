"""Run exactly one episode per env slot and collect outcomes (no autoreset, so no bias toward short episodes)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.stats import wilson_interval

Policy = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class EpisodeBatch:
    """Outcomes of one episode per env: all tensors (B,)."""

    outcome: torch.Tensor  # int64 outcome code
    success: torch.Tensor  # bool
    length: torch.Tensor  # int64
    trojan: torch.Tensor  # bool

    def rate(self, name: str) -> float:
        return float((self.outcome == OUTCOME_NAMES.index(name)).float().mean())

    @property
    def success_rate(self) -> float:
        return float(self.success.float().mean())

    def success_interval(self, confidence: float = 0.95) -> tuple[float, float]:
        return wilson_interval(int(self.success.sum()), int(self.success.numel()), confidence)


def run_episodes(core: TrojanGridCore, policy: Policy, seed: int | None = None, fresh: bool = True) -> EpisodeBatch:
    """Step until every env has finished one episode; return the outcomes.

    ``fresh`` resets every env first (with ``seed`` if given); ``fresh=False`` runs the episodes already set up
    (e.g. hand-built with ``core.set_episode``). A policy with a ``reset(num_envs)`` method is reset first.
    """
    obs = core.reset(seed=seed) if fresh else core.observe()
    if hasattr(policy, "reset"):
        policy.reset(core.num_envs)
    b = core.num_envs
    finished = torch.zeros(b, dtype=torch.bool, device=core.device)
    outcome = torch.zeros(b, dtype=torch.int64, device=core.device)
    success = torch.zeros(b, dtype=torch.bool, device=core.device)
    length = torch.zeros(b, dtype=torch.int64, device=core.device)
    trojan = core.trojan.clone()
    limit = max(g.time_limit for g in core.grids)
    for _ in range(limit):
        result = core.step(policy(obs), autoreset=False, check=False)
        new = result.done & ~finished
        outcome = torch.where(new, result.outcome, outcome)
        success = torch.where(new, result.success, success)
        length = torch.where(new, result.length, length)
        finished |= result.done
        obs = result.obs
        if bool(finished.all()):
            break
    return EpisodeBatch(outcome.cpu(), success.cpu(), length.cpu(), trojan.cpu())
