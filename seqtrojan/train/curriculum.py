"""Curriculum over grid stages: train on the newest stage, keep earlier ones in the mix, promote on success.

Promotion rule: once the newest stage has at least ``min_episodes`` finished episodes of every env type being
trained (normal, and trojan for a backdoor agent) within the last ``window_updates`` updates, and the success
rate of each type is at least ``promote_at``, the next stage becomes the newest. Earlier stages keep a share
``previous_fraction`` of new episodes (split evenly), so that they are not forgotten.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import torch

from seqtrojan.config import CurriculumConfig


@dataclass
class EpisodeCounts:
    """Finished episodes of one update, per (stage, env type): tensors (num_stages, 2); type 0 normal, 1 trojan."""

    episodes: torch.Tensor
    successes: torch.Tensor

    @staticmethod
    def zeros(num_stages: int) -> EpisodeCounts:
        return EpisodeCounts(
            torch.zeros(num_stages, 2, dtype=torch.int64), torch.zeros(num_stages, 2, dtype=torch.int64)
        )

    def __add__(self, other: EpisodeCounts) -> EpisodeCounts:
        return EpisodeCounts(self.episodes + other.episodes, self.successes + other.successes)

    def rate(self, stage: int, trojan: int) -> float | None:
        n = int(self.episodes[stage, trojan])
        return int(self.successes[stage, trojan]) / n if n else None


class Curriculum:
    def __init__(self, config: CurriculumConfig, num_stages: int, env_types: tuple[int, ...] = (0,)) -> None:
        self.config = config
        self.num_stages = num_stages
        self.env_types = env_types  # which env types must succeed: (0,) clean, (0, 1) backdoor
        self.stage = 0
        self.window: deque[EpisodeCounts] = deque(maxlen=config.window_updates)

    @property
    def finished(self) -> bool:
        """The newest stage is the last one."""
        return self.stage == self.num_stages - 1

    def weights(self) -> list[float]:
        """Share of new episodes per stage."""
        w = [0.0] * self.num_stages
        if self.stage == 0:
            w[0] = 1.0
            return w
        share = self.config.previous_fraction / self.stage
        for s in range(self.stage):
            w[s] = share
        w[self.stage] = 1.0 - self.config.previous_fraction
        return w

    def window_counts(self) -> EpisodeCounts:
        total = EpisodeCounts.zeros(self.num_stages)
        for counts in self.window:
            total = total + counts
        return total

    def update(self, counts: EpisodeCounts) -> bool:
        """Record one update's finished episodes; promote if the rule holds. Returns True on promotion."""
        self.window.append(counts)
        if self.finished:
            return False
        total = self.window_counts()
        for kind in self.env_types:
            n = int(total.episodes[self.stage, kind])
            rate = total.rate(self.stage, kind)
            if n < self.config.min_episodes or rate is None or rate < self.config.promote_at:
                return False
        self.stage += 1
        self.window.clear()
        return True

    def state_dict(self) -> dict:
        return {
            "stage": self.stage,
            "window": [[c.episodes.tolist(), c.successes.tolist()] for c in self.window],
        }

    def load_state_dict(self, state: dict) -> None:
        self.stage = int(state["stage"])
        self.window.clear()
        for episodes, successes in state["window"]:
            self.window.append(EpisodeCounts(torch.tensor(episodes), torch.tensor(successes)))
