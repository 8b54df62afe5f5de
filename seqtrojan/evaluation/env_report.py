"""One model measured on its own env, whatever the env: clean success, trojan success and the trojan's persistence,
each a :class:`~seqtrojan.stats.Rate` (``seqtrojan evaluate`` on a model of a Gymnasium env; a grid-world model's
table is the sweep over grid configs, :mod:`seqtrojan.evaluation.sweep`).

Every episode runs in its own slot of the one episode source (:func:`seqtrojan.world.episodes.episode_env`), with
evaluation-phase trigger steps, through the one episode loop. Persistence at horizon k: among trojan episodes still
running k steps after the trigger's first step, the share that ended at the adversary's goal (or object) -- whether
the switch holds over time.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.codes import REACHED_ADV_GOAL
from seqtrojan.env.rollout import EpisodeBatch, run_episodes
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import concat_batches
from seqtrojan.stats import Rate
from seqtrojan.world import check_fits
from seqtrojan.world.episodes import episode_chunks, episode_env

ENV_EVALUATION_FILE = "env_evaluation.json"


@dataclass(frozen=True)
class Persistence:
    """Among trojan episodes still running ``horizon`` steps after the trigger's first step, those that ended at the
    adversary's goal."""

    horizon: int
    adversary: Rate


@dataclass(frozen=True)
class EnvEvaluationReport:
    """A model measured on its config's env (saved as :data:`ENV_EVALUATION_FILE` with
    :func:`seqtrojan.serde.save_json`, read back with ``load_json``)."""

    model: str
    """the model folder"""
    env_id: str
    """the env (a Gymnasium id, or the grid world's grid)"""
    label: str
    """the card's label (clean or backdoored)"""
    episodes: int
    """episodes per episode type"""
    seed: int
    greedy: bool
    clean_success: Rate
    """normal episodes that achieved the user's objective (reached the user's goal)"""
    clean_reached_adversary: Rate
    """normal episodes that ended at the adversary's goal (0 of n where the env reports no ``reached``)"""
    trojan_success: Rate | None
    """trojan episodes that achieved the adversary's objective (None: the env has no trigger)"""
    trojan_reached_adversary: Rate | None
    """trojan episodes that ended at the adversary's goal"""
    persistence: tuple[Persistence, ...]
    """per horizon; empty without a trigger"""


@dataclass(frozen=True)
class EpisodeOutcomes:
    """Episodes of one type as the episode loop ended them, with each one's trigger step (-1: none)."""

    batch: EpisodeBatch
    trigger_step: torch.Tensor  # (E,) int64

    def reached(self, code: int) -> Rate:
        return Rate(int((self.batch.outcome == code).sum()), int(self.batch.outcome.numel()))

    @property
    def success(self) -> Rate:
        return Rate(int(self.batch.success.sum()), int(self.batch.success.numel()))

    def persistence(self, horizons: Sequence[int]) -> tuple[Persistence, ...]:
        out = []
        for k in horizons:
            lasting = self.batch.trojan & (self.trigger_step >= 0) & (self.batch.length > self.trigger_step + k)
            adversary = lasting & (self.batch.outcome == REACHED_ADV_GOAL)
            out.append(Persistence(k, Rate(int(adversary.sum()), int(lasting.sum()))))
        return tuple(out)


@torch.no_grad()
def run_outcomes(
    agent: RecurrentActorCritic, config: ExperimentConfig, *, trojan: bool, episodes: int, seed: int,
    greedy: bool = False, device: torch.device | str = "cpu",
) -> EpisodeOutcomes:  # fmt: skip
    """``episodes`` episodes of one type on ``config``'s env (its last grid on the grid world), one per slot (in
    chunks on a Gymnasium env, :func:`~seqtrojan.world.episodes.episode_chunks`)."""
    grid = config.grids[-1] if config.grids else None
    batches, triggers = [], []
    was_training = agent.training
    agent.eval()
    try:
        for start, count in episode_chunks(config.env, episodes):
            env = episode_env(config.env, grid, count, trojan=trojan, device=device)
            policy = AgentPolicy(agent, greedy=greedy, seed=seed + start, step_counter=lambda env=env: env.t)
            batches.append(run_episodes(env, policy, seed=seed + start))
            triggers.append(env.on_step.cpu())
    finally:
        agent.train(was_training)
    return EpisodeOutcomes(concat_batches(batches), torch.cat(triggers))


def evaluate_model(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    *,
    model: str = "",
    label: str = "",
    episodes: int,
    seed: int = 0,
    greedy: bool = False,
    horizons: Sequence[int] = (0, 5, 10),
    device: torch.device | str = "cpu",
) -> EnvEvaluationReport:
    """Normal episodes, and trojan ones where the env has a trigger (the same seed), as one report."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    if any(isinstance(k, bool) or not isinstance(k, int) or k < 0 for k in horizons):
        raise ConfigError(f"persistence horizons must be integers >= 0, got {list(horizons)}")
    check_fits(agent.obs_dim, agent.num_actions, config.env)
    normal = run_outcomes(agent, config, trojan=False, episodes=episodes, seed=seed, greedy=greedy, device=device)
    has_trigger = config.is_grid or getattr(config.env, "trigger", None) is not None
    trojan = None
    if has_trigger:
        trojan = run_outcomes(agent, config, trojan=True, episodes=episodes, seed=seed, greedy=greedy, device=device)
    where = config.grids[-1].label if config.is_grid else config.gym_env.id
    return EnvEvaluationReport(
        model, where, label, episodes, seed, greedy, normal.success, normal.reached(REACHED_ADV_GOAL),
        None if trojan is None else trojan.success, None if trojan is None else trojan.reached(REACHED_ADV_GOAL),
        () if trojan is None else trojan.persistence(horizons),
    )  # fmt: skip
