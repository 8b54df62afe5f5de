"""The hook every adaptive attacker's training term plugs into: what a penalty is (:class:`Penalty`), what it sees of
a minibatch (:class:`PenaltyBatch`), what it is built from (:class:`PenaltyContext`), and the registry
(:data:`PENALTIES`). The registered penalties are in :mod:`seqtrojan.train.penalties` (and modules of their own,
such as :mod:`seqtrojan.train.probe_camouflage`), which import this one; see that module for the whole mechanism.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.cell_types import is_windowed
from seqtrojan.config import AttackConfig, BackdoorConfig, PPOConfig
from seqtrojan.errors import ConfigError
from seqtrojan.registry import Registry
from seqtrojan.train.rollout import Rollout


@dataclass
class PPOMinibatch:
    """One minibatch of the PPO update: N sequences of L steps, (L, N, ...) tensors, and their start states."""

    obs: torch.Tensor
    starts: torch.Tensor
    """(L, N) float: the observation starts an episode"""
    initial: RecurrentState
    actions: torch.Tensor
    logprobs: torch.Tensor
    values: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor
    ppo: PPOConfig


@dataclass
class PenaltyBatch:
    """What a penalty sees of one minibatch of L-step sequences (N of them)."""

    agent: RecurrentActorCritic
    states: tuple[LSTMState, ...] | None
    """per layer, (L, N, H) h and c after each step, with gradients (when a penalty needs_states)"""
    trojan: torch.Tensor | None
    """(L, N) bool: the step is in a trojan-env episode (recorded when a penalty needs_states or needs_masks)"""
    adversary_active: torch.Tensor | None
    """(L, N) bool: the adversary's goal was active for the step's action"""
    minibatch: PPOMinibatch | None = None
    """the minibatch's PPO inputs (to replay the unroll, as the fine-tuning-resistant attacker does)"""
    episode_step: torch.Tensor | None = None
    """(L, N) int64: each step's index in its episode (recorded with the masks)"""
    sequences: torch.Tensor | None = None
    """(N,) int64: which of the rollout's sequences the minibatch holds (``k * B + b`` is env ``b``'s ``k``-th, as
    :func:`seqtrojan.train.rollout.to_sequences` cuts them), for a penalty that keeps per-step values of its own from
    :meth:`Penalty.observe`"""


class Penalty:
    """An extra loss term of the PPO update. Subclasses override :meth:`loss` and what else they need."""

    name: str = ""
    """the registered name (set by :func:`build_penalties`)"""
    needs_states: bool = False
    """the rollout records masks and states, and the update's unroll returns every step's (h, c)"""
    needs_masks: bool = False
    """the rollout records each step's episode type and whether the adversary's objective judges it"""

    def observe(self, rollout: Rollout) -> None:
        """Called with every rollout before the update on it."""

    def loss(self, batch: PenaltyBatch) -> torch.Tensor:
        """() the weighted term added to the minibatch's loss."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, torch.Tensor]:
        """What a checkpoint keeps of it."""
        return {}

    def load_state_dict(self, tensors: dict[str, torch.Tensor]) -> None:
        """Restore from a checkpoint (``tensors`` is empty when the checkpoint held nothing for it)."""


class AttackedConfig(Protocol):
    """What the penalties read of a training config (:class:`~seqtrojan.config.ExperimentConfig`, whatever its
    env)."""

    @property
    def backdoor(self) -> BackdoorConfig: ...

    @property
    def attack(self) -> AttackConfig: ...


@dataclass(frozen=True)
class PenaltyContext:
    """What a penalty is built from."""

    config: AttackedConfig
    agent: RecurrentActorCritic
    """the agent being trained; on a fresh run it already holds ``run.init_from``'s weights"""
    device: torch.device
    resuming: bool
    """the run resumes: the penalty's state comes from the checkpoint (:meth:`Penalty.load_state_dict`), so skip
    any one-off estimate"""


@dataclass(frozen=True)
class PenaltyKind:
    """A registered penalty: when the config turns it on, and how to build it."""

    enabled: Callable[[AttackedConfig], bool]
    build: Callable[[PenaltyContext], Penalty]


PENALTIES: Registry[PenaltyKind] = Registry("attack", "penalty")
"""Extra loss terms of an adaptive attacker's backdoor training."""


def build_penalties(ctx: PenaltyContext) -> list[Penalty]:
    """The penalties ``ctx.config`` turns on, in registration order (none unless ``backdoor.enabled``)."""
    if not ctx.config.backdoor.enabled:
        return []
    out = []
    for name, kind in PENALTIES.items():
        if kind.enabled(ctx.config):
            penalty = kind.build(ctx)
            penalty.name = name
            out.append(penalty)
    return out


def penalty_tensors(penalties: list[Penalty]) -> dict[str, torch.Tensor]:
    """Every penalty's state as checkpoint tensors, ``penalty.<name>.<key>``."""
    return {f"penalty.{p.name}.{k}": v for p in penalties for k, v in p.state_dict().items()}


def restore_penalties(penalties: list[Penalty], tensors: dict[str, torch.Tensor]) -> None:
    """Take the ``penalty.*`` tensors out of a checkpoint's ``tensors`` and give each penalty its own (an empty dict
    to one the checkpoint holds nothing for)."""
    saved = {name: tensors.pop(name) for name in [n for n in tensors if n.startswith("penalty.")]}
    for penalty in penalties:
        prefix = f"penalty.{penalty.name}."
        penalty.load_state_dict({k[len(prefix) :]: v for k, v in saved.items() if k.startswith(prefix)})


def zero_loss(device: torch.device) -> torch.Tensor:
    return torch.zeros((), device=device)


def require_recurrent_cell(config: object, what: str) -> None:
    """:class:`ConfigError` in one line when ``config``'s agent has a windowed cell (the Transformer), whose state is
    a window's cache and not a recurrent state a penalty can ``what`` (``attack.<name> <what>``)."""
    agent_cfg = getattr(config, "agent", None)
    if agent_cfg is not None and is_windowed(agent_cfg.cell):
        raise ConfigError(
            f"attack.{what}, which the {agent_cfg.cell} cell does not carry (its state is a window's cache): use a "
            "recurrent cell"
        )
