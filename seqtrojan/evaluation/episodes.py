"""Success of an agent on one grid, in the normal or the trojan env: one batched episode per trial."""

from __future__ import annotations

import dataclasses

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.agent.state import Intervention
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.env.rollout import EpisodeBatch, run_episodes


def evaluate_agent(
    agent: RecurrentActorCritic,
    env: EnvConfig,
    grid: GridSpec,
    *,
    trojan: bool,
    episodes: int,
    seed: int,
    greedy: bool = False,
    device: str | torch.device = "cpu",
    intervention: Intervention | None = None,
) -> EpisodeBatch:
    """Run ``episodes`` episodes (one per env slot, all at once) in the normal (``trojan=False``) or trojan env,
    with evaluation-phase trigger steps (the trigger always comes before a goal can be reached)."""
    env_cfg = dataclasses.replace(env, size=grid.size, holes=grid.holes, max_steps=grid.max_steps)
    core = TrojanGridCore(env_cfg, episodes, device=device, trojan_probability=1.0 if trojan else 0.0, phase="eval")
    policy = AgentPolicy(agent, greedy=greedy, seed=seed, intervention=intervention, step_counter=lambda: core.t)
    was_training = agent.training
    agent.eval()
    try:
        return run_episodes(core, policy, seed=seed)
    finally:
        agent.train(was_training)
