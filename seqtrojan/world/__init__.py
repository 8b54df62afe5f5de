"""One world: every env, the built-in grid world or a Gymnasium env, behind one batched-env seam.

    env = make_batched_env(config.env, num_envs=64, seed=0)      # a BatchedEnv, whatever config.env is
    spec = env_spec(config.env)                                   # obs_dim, num_actions, image layout

:data:`ENV_KINDS` maps each kind of ``env:`` section (its config class) to what builds its batched env; a new kind
of env is one class with the :class:`~seqtrojan.world.protocol.BatchedEnv` methods and one entry here.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.errors import ConfigError
from seqtrojan.serde import to_dict
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig
from seqtrojan.world.protocol import BatchedEnv

__all__ = [
    "ENV_KINDS",
    "BatchedEnv",
    "EnvSpec",
    "GymnasiumEnvConfig",
    "WrapperTriggerConfig",
    "check_fits",
    "env_spec",
    "make_batched_env",
]


@dataclass(frozen=True)
class EnvSpec:
    """What an agent must fit: inputs, actions, and the observation's image layout (for a conv encoder)."""

    obs_dim: int
    num_actions: int
    image: tuple[int, int, int] | None = None


def _grid(
    env: Any, num_envs: int, seed: int | Sequence[int], device: torch.device | str, grids: Sequence[GridSpec] | None,
    phase: str, trojan_probability: float | Sequence[float], registered_only: bool,
) -> BatchedEnv:  # fmt: skip
    return TrojanGridCore(
        env, num_envs, seed=seed, device=device, grids=grids, trojan_probability=trojan_probability,
        phase="eval" if phase == "eval" else "train",
    )  # fmt: skip


def _gymnasium(
    env: Any, num_envs: int, seed: int | Sequence[int], device: torch.device | str, grids: Sequence[GridSpec] | None,
    phase: str, trojan_probability: float | Sequence[float], registered_only: bool,
) -> BatchedEnv:  # fmt: skip
    from seqtrojan.world.gymnasium import GymnasiumBatchedEnv
    from seqtrojan.world.workers import WorkerBatchedEnv

    p = float(torch.as_tensor(trojan_probability, dtype=torch.float64).reshape(-1)[0])
    kind = WorkerBatchedEnv if env.vectorization == "workers" else GymnasiumBatchedEnv
    batched = kind(env, num_envs, 0, device, phase=phase, trojan_probability=p, registered_only=registered_only)
    batched.reset(seed)
    return batched


EnvBuilder = Callable[..., BatchedEnv]
ENV_KINDS: dict[type, EnvBuilder] = {EnvConfig: _grid, GymnasiumEnvConfig: _gymnasium}
"""config class of an ``env:`` section -> the builder of its batched env"""


def make_batched_env(
    env: EnvConfig | GymnasiumEnvConfig,
    num_envs: int,
    *,
    seed: int | Sequence[int] = 0,
    device: torch.device | str = "cpu",
    grids: Sequence[GridSpec] | None = None,
    phase: str = "train",
    trojan_probability: float | Sequence[float] = 0.0,
    registered_only: bool = False,
) -> BatchedEnv:
    """``num_envs`` episodes of the env ``env`` describes, seeded ``seed`` (env ``i``: ``seed + i``). ``grids``: the
    grid world's curriculum stages; ``phase`` "eval" draws trigger steps from the evaluation range;
    ``registered_only``: a config read from a model card (a Gymnasium id must be registered, never imported)."""
    builder = ENV_KINDS[type(env)]
    return builder(env, num_envs, seed, device, grids, phase, trojan_probability, registered_only)


def check_fits(obs_dim: int, num_actions: int, env: EnvConfig | GymnasiumEnvConfig) -> None:
    """Refuse, in one line, an agent of ``obs_dim`` inputs and ``num_actions`` actions for an env whose spaces
    differ (a tampered card, or a config edited after training): before any episode is run."""
    spec = env_spec(env)
    if (spec.obs_dim, spec.num_actions) != (obs_dim, num_actions):
        where = env.id if isinstance(env, GymnasiumEnvConfig) else f"the grid world ({env.grid.label})"
        raise ConfigError(
            f"the agent reads {obs_dim} inputs and chooses among {num_actions} actions, but {where} gives "
            f"{spec.obs_dim} inputs and {spec.num_actions} actions"
        )


_SPECS: dict[str, EnvSpec] = {}


def env_spec(env: EnvConfig | GymnasiumEnvConfig, registered_only: bool = False) -> EnvSpec:
    """The inputs, actions and image layout of ``env``'s observations (a Gymnasium env is made once to read its
    spaces; the answer is remembered for the process)."""
    if isinstance(env, EnvConfig):
        return EnvSpec(env.obs_dim, env.num_actions)
    key = json.dumps(to_dict(env), sort_keys=True, default=str)
    if key not in _SPECS:
        batched = make_batched_env(env, 1, registered_only=registered_only)
        try:
            _SPECS[key] = EnvSpec(batched.obs_dim, batched.num_actions, batched.image)
        finally:
            batched.close()
    return _SPECS[key]
