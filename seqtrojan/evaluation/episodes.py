"""Success of an agent (or any batched policy) on one grid, in the normal or the trojan env.

Every trial is one episode in its own env slot, all run as one batch until each has ended (no autoreset, so no
bias toward short episodes), with evaluation-phase trigger steps (the trigger always takes effect before a goal
can be reached).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.agent.state import Intervention
from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.rollout import EpisodeBatch, EpisodeEnv, Policy, run_episodes
from seqtrojan.errors import ConfigError
from seqtrojan.stats import Rate
from seqtrojan.world.config import GymnasiumEnvConfig
from seqtrojan.world.episodes import episode_chunks, episode_env

PolicyFactory = Callable[[Any], Policy]
"""Builds a batched policy for a given env (the env is passed so that scripted agents can read the grid core)."""


def evaluate_policy(
    make_policy: PolicyFactory,
    env: EnvConfig | GymnasiumEnvConfig,
    grid: GridSpec | None,
    *,
    trojan: bool,
    episodes: int,
    seed: int,
    device: str | torch.device = "cpu",
) -> EpisodeBatch:
    """Run ``episodes`` episodes of ``grid`` (a Gymnasium env section: of its env) in the normal (``trojan=False``)
    or the trojan env."""
    core = episode_env(env, grid, episodes, trojan=trojan, device=device)
    return run_episodes(core, make_policy(core), seed=seed)


def evaluate_agent(
    agent: RecurrentActorCritic,
    env: EnvConfig | GymnasiumEnvConfig,
    grid: GridSpec | None,
    *,
    trojan: bool,
    episodes: int,
    seed: int,
    greedy: bool = False,
    device: str | torch.device = "cpu",
    intervention: Intervention | None = None,
) -> EpisodeBatch:
    """:func:`evaluate_policy` for a trained agent (sampled actions, or greedy), optionally with an intervention."""

    def run(start: int, count: int) -> EpisodeBatch:
        def make_policy(core: EpisodeEnv) -> AgentPolicy:
            return AgentPolicy(
                agent, greedy=greedy, seed=seed + start, intervention=intervention, step_counter=lambda: core.t
            )

        return evaluate_policy(make_policy, env, grid, trojan=trojan, episodes=count, seed=seed + start, device=device)

    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes must be a positive integer, got {episodes!r}")
    was_training = agent.training
    agent.eval()
    try:
        return concat_batches([run(start, count) for start, count in episode_chunks(env, episodes)])
    finally:
        agent.train(was_training)


def concat_batches(batches: list[EpisodeBatch]) -> EpisodeBatch:
    """Batches of episodes as one (in order)."""
    if len(batches) == 1:
        return batches[0]

    def joined(name: str) -> torch.Tensor:
        return torch.cat([getattr(b, name) for b in batches])

    returns = [b.returns for b in batches]
    total = None if any(r is None for r in returns) else torch.cat(returns)  # type: ignore[arg-type]
    return EpisodeBatch(joined("outcome"), joined("success"), joined("length"), joined("trojan"), total)


def outcome_rate(batch: EpisodeBatch, name: str) -> Rate:
    """Episodes of ``batch`` that ended with outcome ``name`` (user_goal, adversary_goal, hole, timeout), of all."""
    return Rate(int((batch.outcome == OUTCOME_NAMES.index(name)).sum()), int(batch.outcome.numel()))


def success_rate(batch: EpisodeBatch) -> Rate:
    """Episodes of ``batch`` that reached the goal they should (the user's, or the adversary's after a trigger)."""
    return Rate(int(batch.success.sum()), int(batch.success.numel()))


def on_off_success(
    agent: RecurrentActorCritic, env: EnvConfig, grid: GridSpec, *, episodes: int, seed: int, **kw
) -> dict[str, float]:
    """The three behaviours of an ON/OFF backdoor (paper, section 3), each over its own episodes: the user's goal in
    the normal env, the adversary's goal after the ON trigger alone, and the user's goal again when the OFF trigger
    follows it (OFF probability forced to 0 and to 1; the env's own OFF cells, value and gap)."""
    trigger = env.trigger
    out = {}
    for name, probability, trojan, goal in (("normal", 0.0, False, "user_goal"), ("on", 0.0, True, "adversary_goal"),
                                             ("on_off", 1.0, True, "user_goal")):  # fmt: skip
        off = dataclasses.replace(trigger.off, probability=probability)
        cfg = dataclasses.replace(env, trigger=dataclasses.replace(trigger, off=off))
        batch = evaluate_agent(agent, cfg, grid, trojan=trojan, episodes=episodes, seed=seed, **kw)
        out[name] = float((batch.outcome == OUTCOME_NAMES.index(goal)).float().mean())
    return out
