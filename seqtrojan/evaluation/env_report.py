"""One model measured on its own env, whatever the env: clean success, trojan success and the trojan's persistence,
each a :class:`~seqtrojan.stats.Rate`, and each episode type's mean return (``seqtrojan evaluate`` on a model of a
Gymnasium env; a grid-world model's table is the sweep over grid configs, :mod:`seqtrojan.evaluation.sweep`).

Every episode runs in its own slot of the one episode source (:func:`seqtrojan.world.episodes.episode_env`), with
evaluation-phase trigger steps, through the one episode loop. Persistence at horizon k: among trojan episodes still
running k steps after the trigger's first step, the share that ended at the adversary's goal (or object) -- whether
the switch holds over time.

Where the adversary's objective is a target action (``objective: target_action``, POPGym and MinAtar), the switch
is read from the actions instead: the target share (per trojan episode, the share of the actions the adversary
judged that were the target action; its mean over episodes) beside the same share in normal episodes from the same
step on (how often the clean behaviour picks that action anyway), and action persistence at horizon k (among
trojan episodes still running k steps after the trigger's first step, the share whose action at that step was the
target).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.codes import REACHED_ADV_GOAL
from seqtrojan.env.rollout import EpisodeBatch, EpisodeStep, run_episodes
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import concat_batches
from seqtrojan.stats import Mean, Rate
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
    clean_return: Mean | None = None
    """normal episodes' mean return (the env's own reward)"""
    trojan_return: Mean | None = None
    """trojan episodes' mean return under the objective in force (the adversary's from the trigger on)"""
    trojan_env_return: Mean | None = None
    """trojan episodes' mean return under the env's own reward throughout (what the user loses)"""
    target_action: int | None = None
    """the adversary's target action (objective ``target_action``), else None"""
    target_share: Mean | None = None
    """trojan episodes: per episode, the share of the adversary-judged actions that were the target action"""
    clean_target_share: Mean | None = None
    """normal episodes: the same share from the trojan episodes' trigger steps on (the clean baseline)"""
    action_persistence: tuple[Persistence, ...] = ()
    """per horizon: trojan episodes whose action k steps after the trigger's first step was the target"""


class ActionLog:
    """An :class:`~seqtrojan.env.rollout.EpisodeRecorder` of every running episode's action per step (for the
    target-action measures)."""

    def __init__(self) -> None:
        self.actions: list[torch.Tensor] = []  # per step (B,) int64, -1 once the episode has ended

    def on_step(self, step: EpisodeStep) -> None:
        self.actions.append(torch.where(step.running.cpu(), step.action.cpu(), -1))

    def on_end(self, batch: EpisodeBatch) -> None:
        """Nothing to finish: :meth:`table` reads the actions."""

    def table(self) -> torch.Tensor:
        """(E, T) int64: episode e's action at step t (-1 after its end)."""
        return torch.stack(self.actions, dim=1) if self.actions else torch.zeros((0, 0), dtype=torch.int64)


@dataclass(frozen=True)
class EpisodeOutcomes:
    """Episodes of one type as the episode loop ended them, with each one's trigger step (-1: none), actions
    ((E, T), -1 after an episode's end) and env-reward returns."""

    batch: EpisodeBatch
    trigger_step: torch.Tensor  # (E,) int64
    actions: torch.Tensor | None = None  # (E, T) int64
    env_returns: torch.Tensor | None = None  # (E,) float32

    @property
    def mean_return(self) -> Mean | None:
        return None if self.batch.returns is None else Mean.of(self.batch.returns)

    def target_shares(self, target: int, first_steps: torch.Tensor) -> torch.Tensor:
        """(E,) float: per episode, the share of its actions from step ``first_steps[e]`` on that were ``target``
        (NaN where no action was taken from there on)."""
        assert self.actions is not None
        steps = torch.arange(self.actions.shape[1])[None, :]
        judged = (steps >= first_steps[:, None]) & (first_steps[:, None] >= 0) & (self.actions >= 0)
        hits = (judged & (self.actions == target)).sum(dim=1).float()
        counts = judged.sum(dim=1).float()
        return torch.where(counts > 0, hits / counts.clamp(min=1), float("nan"))

    def action_persistence(self, target: int, horizons: Sequence[int]) -> tuple[Persistence, ...]:
        assert self.actions is not None
        out = []
        for k in horizons:
            at = self.trigger_step + k
            lasting = self.batch.trojan & (self.trigger_step >= 0) & (self.batch.length > at)
            index = at.clamp(0, max(self.actions.shape[1] - 1, 0))[:, None]
            chosen = self.actions.gather(1, index)[:, 0] if self.actions.numel() else torch.zeros_like(at)
            out.append(Persistence(k, Rate(int((lasting & (chosen == target)).sum()), int(lasting.sum()))))
        return tuple(out)

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
    batches, triggers, actions, env_returns = [], [], [], []
    was_training = agent.training
    agent.eval()
    try:
        for start, count in episode_chunks(config.env, episodes):
            env = episode_env(config.env, grid, count, trojan=trojan, device=device)
            policy = AgentPolicy(agent, greedy=greedy, seed=seed + start, step_counter=lambda env=env: env.t)
            log = ActionLog()
            batches.append(run_episodes(env, policy, seed=seed + start, recorders=[log]))
            triggers.append(env.on_step.cpu())
            actions.append(log.table())
            env_returns.append(getattr(env, "env_returns", torch.full((count,), float("nan"))).cpu())
    finally:
        agent.train(was_training)
    width = max(a.shape[1] for a in actions)
    padded = [torch.nn.functional.pad(a, (0, width - a.shape[1]), value=-1) for a in actions]
    return EpisodeOutcomes(concat_batches(batches), torch.cat(triggers), torch.cat(padded), torch.cat(env_returns))


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
    report = EnvEvaluationReport(
        model, where, label, episodes, seed, greedy, normal.success, normal.reached(REACHED_ADV_GOAL),
        None if trojan is None else trojan.success, None if trojan is None else trojan.reached(REACHED_ADV_GOAL),
        () if trojan is None else trojan.persistence(horizons), clean_return=normal.mean_return,
        trojan_return=None if trojan is None else trojan.mean_return,
        trojan_env_return=None if trojan is None else _mean_of_finite(trojan.env_returns),
    )  # fmt: skip
    target = target_action_of(config)
    if trojan is None or target is None:
        return report
    effect = trojan.trigger_step + (config.gym_env.trigger.delay if config.gym_env.trigger is not None else 0)
    shares, clean_shares = trojan.target_shares(target, effect), normal.target_shares(target, effect)
    return dataclasses.replace(
        report, target_action=target, target_share=_mean_of_finite(shares),
        clean_target_share=_mean_of_finite(clean_shares),
        action_persistence=trojan.action_persistence(target, horizons),
    )  # fmt: skip


def target_action_of(config: ExperimentConfig) -> int | None:
    """The adversary's target action where the env's trigger objective is ``target_action``, else None."""
    trigger = None if config.is_grid else config.gym_env.trigger
    return trigger.target_action if trigger is not None and trigger.objective == "target_action" else None


def _mean_of_finite(values: torch.Tensor | None) -> Mean | None:
    if values is None:
        return None
    kept = values[torch.isfinite(values)]
    return Mean.of(kept) if kept.numel() else None
