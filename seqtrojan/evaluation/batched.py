"""Success of an agent on any env of a config, the grid world or a Gymnasium env, as one kind of result
(:class:`~seqtrojan.env.rollout.EpisodeBatch`).

On the grid world every trial is one episode in its own env slot (:func:`seqtrojan.evaluation.episodes.
evaluate_agent`). A Gymnasium env is a Python object per slot, so :func:`run_quota_episodes` runs a few slots
(``num_envs``), each a fixed quota of episodes one after another (the quota, not the first to finish, decides
which episodes count: no bias toward short episodes).
"""

from __future__ import annotations

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import act
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.rollout import EpisodeBatch
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent
from seqtrojan.world import check_fits, make_batched_env
from seqtrojan.world.config import GymnasiumEnvConfig
from seqtrojan.world.protocol import BatchedEnv

GYM_EVAL_ENVS = 32
"""env slots of a Gymnasium evaluation (each runs its quota of episodes)"""


@torch.no_grad()
def run_quota_episodes(
    agent: RecurrentActorCritic, env: BatchedEnv, episodes: int, *, seed: int, greedy: bool = False
) -> EpisodeBatch:
    """``episodes`` episodes over ``env``'s slots, slot ``i`` running ``episodes // B`` (+1 for the first
    ``episodes % B``) in a row from a reset seeded ``seed``; returns them in slot order, then episode order."""
    b, dev = env.num_envs, env.device
    quota = torch.tensor([episodes // b + (i < episodes % b) for i in range(b)])
    obs = env.reset(seed)
    state = agent.initial_state(b, dev)
    start = torch.ones(b, device=dev)
    generator = torch.Generator(device=dev).manual_seed(seed)
    done_count = torch.zeros(b, dtype=torch.int64)
    found: list[list[tuple[int, bool, int, bool]]] = [[] for _ in range(b)]
    while bool((done_count < quota).any()):
        out, actions, _ = act(agent, obs, state, generator, greedy=greedy, episode_start=start)
        state = out.state
        result = env.step(actions, check=False)
        done = result.done.cpu()
        for i in done.nonzero().flatten().tolist():
            if done_count[i] < quota[i]:
                found[i].append(
                    (int(result.outcome[i]), bool(result.success[i]), int(result.length[i]), bool(result.trojan[i]))
                )
            done_count[i] += 1
        obs, start = result.obs, result.done.to(torch.float32)
    rows = [row for slot in found for row in slot]
    return EpisodeBatch(
        torch.tensor([r[0] for r in rows], dtype=torch.int64),
        torch.tensor([r[1] for r in rows], dtype=torch.bool),
        torch.tensor([r[2] for r in rows], dtype=torch.int64),
        torch.tensor([r[3] for r in rows], dtype=torch.bool),
    )


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
    if trojan and isinstance(env_cfg, GymnasiumEnvConfig) and env_cfg.trigger is None:
        raise ConfigError(f"trojan episodes of {env_cfg.id!r} need env.trigger")
    check_fits(agent.obs_dim, agent.num_actions, env_cfg)
    env = make_batched_env(
        env_cfg, min(GYM_EVAL_ENVS, episodes), seed=seed, device=device, phase="eval",
        trojan_probability=1.0 if trojan else 0.0, registered_only=registered_only,
    )  # fmt: skip
    was_training = agent.training
    agent.eval()
    try:
        return run_quota_episodes(agent, env, episodes, seed=seed, greedy=greedy)
    finally:
        agent.train(was_training)
        env.close()
