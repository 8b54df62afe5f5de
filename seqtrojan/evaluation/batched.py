"""Success of an agent on any env of a config, the grid world or a Gymnasium env, as one kind of result
(:class:`~seqtrojan.env.rollout.EpisodeBatch`), through the one episode source: every trial is one episode in its
own env slot (:func:`seqtrojan.evaluation.episodes.evaluate_agent`; a Gymnasium env's slots in chunks)."""

from __future__ import annotations

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.rollout import EpisodeBatch
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent
from seqtrojan.world import check_fits
from seqtrojan.world.gymnasium import check_registered


def evaluate_on_env(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    *,
    trojan: bool,
    episodes: int,
    seed: int,
    greedy: bool = False,
    device: str | torch.device = "cpu",
    grid: GridSpec | None = None,
    registered_only: bool = False,
) -> EpisodeBatch:
    """``episodes`` evaluation episodes (evaluation-phase trigger steps) of ``config``'s env, normal or trojan:
    on the grid world, of ``grid`` (default: the curriculum's last); ``registered_only``: the config came from a
    model card (a Gymnasium id must be registered)."""
    if episodes < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    env_cfg = config.env
    if isinstance(env_cfg, EnvConfig):
        return evaluate_agent(
            agent, env_cfg, grid or config.grids[-1], trojan=trojan, episodes=episodes, seed=seed, greedy=greedy,
            device=device,
        )  # fmt: skip
    if registered_only:
        check_registered(env_cfg.id)
    if trojan and env_cfg.trigger is None:
        raise ConfigError(f"trojan episodes of {env_cfg.id!r} need env.trigger")
    check_fits(agent.obs_dim, agent.num_actions, env_cfg)
    return evaluate_agent(
        agent, env_cfg, None, trojan=trojan, episodes=episodes, seed=seed, greedy=greedy, device=device
    )  # fmt: skip
