"""The batched-env seam: what every trainer, evaluator, recorder, monitor and study asks of an env.

Two implementations: the grid world's :class:`~seqtrojan.env.core.TrojanGridCore` (natively, tensors throughout)
and :class:`~seqtrojan.world.gymnasium.GymnasiumBatchedEnv` (Gymnasium envs under a trigger wrapper). Both step
B episodes at once, reset a finished episode in the step that ends it, and answer a step with a
:class:`~seqtrojan.env.core.StepResult`: observations (after the reset), rewards, terminated / truncated / done, and
per episode the step was taken in its type (trojan or not), outcome, success, stage, length and whether the
adversary's objective judged the action.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import torch

from seqtrojan.env.core import EnvState, StepResult


@runtime_checkable
class BatchedEnv(Protocol):
    """B episodes stepped together (see the module docstring)."""

    num_envs: int
    obs_dim: int
    num_actions: int
    device: torch.device
    image: tuple[int, int, int] | None
    """(rows, cols, channels) of the observation laid out as an image, or None"""

    @property
    def num_stages(self) -> int:
        """Stages (a curriculum's grids) episodes are drawn from; 1 for a Gymnasium env."""
        ...

    def reset(self, seed: int | Sequence[int] | None = None) -> torch.Tensor:
        """A fresh episode everywhere (env ``i`` seeded ``seed + i``); the observations (B, obs_dim)."""
        ...

    def observe(self) -> torch.Tensor:
        """The current observations (B, obs_dim) float32."""
        ...

    def step(self, actions: torch.Tensor, *, check: bool = True) -> StepResult:
        """One action per env (B,) int64."""
        ...

    def set_trojan_probability(self, probability: float | Sequence[float] | torch.Tensor) -> None:
        """The chance that a new episode is a trojan one: one number, or one per stage."""
        ...

    def set_stage_weights(self, weights: Sequence[float] | torch.Tensor) -> None:
        """How often each stage is drawn for new episodes."""
        ...

    def save_state(self) -> EnvState | None:
        """The episodes in flight, as a checkpoint keeps them; None when the env cannot restore them."""
        ...

    def load_state(self, state: EnvState, obs: torch.Tensor) -> bool:
        """Restore :meth:`save_state`'s episodes; True when every env is back where the checkpoint left it (its
        observations equal ``obs``, the collector's saved ones). False leaves the envs for the caller to reset."""
        ...

    def close(self) -> None: ...
