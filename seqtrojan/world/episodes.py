"""The one episode source: ``episodes`` slots of any env section, one episode each, for the episode loop
(:func:`seqtrojan.env.rollout.run_episodes`) that evaluation, state traces, interventions, monitors and
mitigations run through.

    env = episode_env(cfg.env, grid, 500, trojan=True, device="cpu")   # the grid core, or a Gymnasium env
    batch = run_episodes(env, policy, seed=0)

On the grid world the slots are a :class:`~seqtrojan.env.core.TrojanGridCore` of ``grid`` (the calls made before
this seam existed, unchanged); a Gymnasium env section gives a :class:`~seqtrojan.world.gymnasium.
GymnasiumBatchedEnv` of that many envs (``grid`` is then ignored). Both with evaluation-phase trigger steps, or the
trigger pinned at ``trigger_step``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.rollout import EpisodeEnv
from seqtrojan.errors import ConfigError
from seqtrojan.world.config import GymnasiumEnvConfig

GYMNASIUM_SLOTS = 1024
"""most episodes one batch of Gymnasium env slots runs at once (each slot is an env object): longer evaluations run
in chunks (:func:`episode_chunks`)"""


def episode_chunks(env: EnvConfig | GymnasiumEnvConfig, episodes: int) -> list[tuple[int, int]]:
    """(first episode, count) of the batches ``episodes`` episodes run in: one batch on the grid world (its slots are
    tensors), batches of :data:`GYMNASIUM_SLOTS` on a Gymnasium env. Chunk ``(start, n)`` is seeded ``seed + start``,
    so its slot ``j`` is episode ``start + j`` of the whole run."""
    size = episodes if isinstance(env, EnvConfig) else GYMNASIUM_SLOTS
    return [(start, min(size, episodes - start)) for start in range(0, episodes, max(size, 1))]


def pin_trigger(env: EnvConfig | GymnasiumEnvConfig, step: int) -> EnvConfig | GymnasiumEnvConfig:
    """``env`` with its evaluation trigger always at ``step``."""
    if isinstance(env, EnvConfig):
        return dataclasses.replace(env, trigger=dataclasses.replace(env.trigger, eval_steps=(step, step)))
    if env.trigger is None:
        raise ConfigError(f"{env.id!r} has no env.trigger to show at step {step}")
    return dataclasses.replace(env, trigger=dataclasses.replace(env.trigger, eval_steps=(step, step)))


def episode_env(
    env: EnvConfig | GymnasiumEnvConfig,
    grid: GridSpec | None,
    episodes: int,
    *,
    trojan: bool,
    device: str | torch.device = "cpu",
    seed: int | Sequence[int] = 0,
    grids: Sequence[GridSpec] | None = None,
    trigger_step: int | None = None,
) -> EpisodeEnv:
    """``episodes`` slots of normal (``trojan=False``) or trojan episodes of ``env`` (on the grid world: of
    ``grid``, or drawn from ``grids``), seeded ``seed``, evaluation phase."""
    if trigger_step is not None:
        env = pin_trigger(env, trigger_step)
    p = 1.0 if trojan else 0.0
    if isinstance(env, EnvConfig):
        stages = tuple(grids) if grids is not None else None
        where = grid if grid is not None else (stages[0] if stages else env.grid)
        return TrojanGridCore(
            env.with_grid(where), episodes, seed=seed, device=device, grids=stages, trojan_probability=p, phase="eval"
        )
    from seqtrojan.world.gymnasium import GymnasiumBatchedEnv
    from seqtrojan.world.workers import WorkerBatchedEnv

    if env.vectorization == "async":  # the episode loop steps envs without resetting them: not Gymnasium's vector env
        env = dataclasses.replace(env, vectorization="sync")
    kind = WorkerBatchedEnv if env.vectorization == "workers" else GymnasiumBatchedEnv
    batched = kind(env, episodes, 0, device, phase="eval", trojan_probability=p)
    batched.reset(seed)
    return batched
