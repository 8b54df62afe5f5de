"""The adversary's trade-off: what a penalty on unintentional activation buys and costs.

An adversary who fears being caught by unprovoked activations can train with a harsher reward for reaching the
adversary's goal while the user's goal is correct (``env.rewards.false_activation``; by default it is the ordinary
``wrong_goal``, -1). Backdoored agents that differ only in that reward are compared on

* the attack itself: success in the normal and the trojan env on the training grid;
* stealth: the unintentional activation rate over the sweep configs (the paper's Tables 1 and 2 by default), and
  the agent's precision and recall as a trigger detector (:mod:`seqtrojan.analysis.trigger_detection`).

This module plans the agents (:func:`tradeoff_agents`: one training job per agent that is not one of the backdoored
agents already trained), measures them (:class:`~seqtrojan.experiment_results.TradeoffAgentResult`), and summarises each
penalty over its training seeds (:class:`~seqtrojan.experiment_results.PenaltySummary`: mean and standard deviation):
the confidence intervals of one agent cover the evaluation's sampling, the seeds the training's spread. The caller runs
the jobs on a job backend (:mod:`seqtrojan.jobs`; ``seqtrojan reproduce`` uses its ``jobs:`` backend).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.trigger_detection import trigger_detection
from seqtrojan.analysis.unintentional import sweep_unintentional
from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.sweep import parse_configs
from seqtrojan.experiment_results import PenaltySummary, TradeoffAgentResult, TradeoffSettings
from seqtrojan.jobs import TrainJob
from seqtrojan.stats import OverSeeds, Rate


@dataclass(frozen=True)
class TradeoffConfig:
    penalties: tuple[float, ...] = (-1.0, -3.0, -10.0)
    """false-activation rewards to compare; a value equal to the backdoored agent's own reuses that agent"""
    total_steps: int | None = None
    """training budget of each agent; None: the backdoored agent's (which can then be reused)"""
    configs: str = "paper"
    """where unintentional activations are counted: 'paper' or a list like '7x7/7,23x23/0'"""
    episodes: int = 1000
    """per config and env"""
    seed: int = 0
    """evaluation seed"""
    seeds: int = 1
    """training seeds per penalty (run.seed, run.seed + 1, ...)"""

    def __post_init__(self) -> None:
        if self.seeds < 1:
            raise ConfigError(f"tradeoff.seeds must be >= 1, got {self.seeds}")
        if not self.penalties:
            raise ConfigError("tradeoff.penalties is empty")
        if len(set(self.penalties)) != len(self.penalties):
            raise ConfigError(f"tradeoff.penalties={list(self.penalties)} names a penalty twice")
        if self.episodes < 1:
            raise ConfigError(f"tradeoff.episodes must be >= 1, got {self.episodes}")
        if self.total_steps is not None and self.total_steps < 1:
            raise ConfigError(f"tradeoff.total_steps must be >= 1, got {self.total_steps}")


def own_penalty(cfg: ExperimentConfig) -> float:
    rewards = cfg.grid_env.rewards
    return rewards.wrong_goal if rewards.false_activation is None else rewards.false_activation


def penalised_config(
    base: ExperimentConfig, penalty: float, total_steps: int | None, seed_offset: int = 0
) -> ExperimentConfig:
    """The backdoored agent's training config with another false-activation reward (and budget, and seed)."""
    grid_env = base.grid_env
    env = dataclasses.replace(grid_env, rewards=dataclasses.replace(grid_env.rewards, false_activation=penalty))
    ppo = base.ppo if total_steps is None else dataclasses.replace(base.ppo, total_steps=total_steps)
    run = dataclasses.replace(base.run, seed=base.run.seed + seed_offset)
    return dataclasses.replace(base, env=env, ppo=ppo, run=run)


def reuses_backdoor_agent(
    base: ExperimentConfig, penalty: float, cfg: TradeoffConfig, seed_offset: int = 0, trained_seeds: int = 1
) -> bool:
    """Whether this agent is one already trained: the backdoored agent of training seed ``seed_offset`` (the caller
    has ``trained_seeds`` of them, seeds 0 .. trained_seeds-1), when the penalty and the budget are its own. Its
    training config is then the same as this agent's, so training it again would repeat the same experiment."""
    return (
        seed_offset < trained_seeds and penalty == own_penalty(base) and cfg.total_steps in (None, base.ppo.total_steps)
    )


@dataclass(frozen=True)
class TradeoffAgent:
    """One agent of the trade-off: a penalty and a training seed."""

    penalty: float
    seed_offset: int
    config: ExperimentConfig
    """its training config (what it is measured with)"""
    job: TrainJob | None
    """the job that trains it; None when it is the backdoored agent of training seed ``seed_offset`` (reused, not
    trained again)"""


def tradeoff_agents(
    base: ExperimentConfig, cfg: TradeoffConfig, runs_dir: Path, trained_seeds: int = 1
) -> list[TradeoffAgent]:
    """The agents, penalty by penalty and seed by seed. ``trained_seeds``: how many training seeds of the backdoored
    agent ``base`` exist (seed k trained with run.seed = base's + k); the base penalty's first ``trained_seeds``
    seeds are those agents. Each one trained is a job whose run is ``<runs_dir>/backdoor_penalty<penalty>``
    (``..._seed<seed>`` after the first seed) and whose id is that name."""
    agents = []
    for penalty in cfg.penalties:
        for offset in range(cfg.seeds):
            train_cfg = penalised_config(base, penalty, cfg.total_steps, offset)
            if reuses_backdoor_agent(base, penalty, cfg, offset, trained_seeds):
                agents.append(TradeoffAgent(penalty, offset, train_cfg, None))
                continue
            name = f"backdoor_penalty{penalty:g}" + (f"_seed{train_cfg.run.seed}" if offset else "")
            run = dataclasses.replace(train_cfg.run, out_dir=str(runs_dir), name=name)
            train_cfg = dataclasses.replace(train_cfg, run=run)
            agents.append(TradeoffAgent(penalty, offset, train_cfg, TrainJob(name, train_cfg)))
    return agents


def summarise_penalties(agents: Sequence[TradeoffAgentResult]) -> tuple[PenaltySummary, ...]:
    """Per penalty (in order of first appearance), over its training seeds: success, activation and recall."""
    out = []
    for penalty in dict.fromkeys(a.penalty for a in agents):
        mine = [a for a in agents if a.penalty == penalty]
        out.append(
            PenaltySummary(
                penalty=penalty,
                normal_success=OverSeeds(tuple(a.normal_success.value for a in mine)),
                trojan_success=OverSeeds(tuple(a.trojan_success.value for a in mine)),
                activation=OverSeeds(tuple(a.activation.value for a in mine)),
                recall=OverSeeds(tuple(a.detection.recall.value for a in mine)),
            )
        )
    return tuple(out)


def settings(cfg: TradeoffConfig) -> TradeoffSettings:
    return TradeoffSettings(cfg.penalties, cfg.total_steps, cfg.configs, cfg.episodes, cfg.seed, cfg.seeds)


def measure_tradeoff_agent(
    agent: RecurrentActorCritic, train_cfg: ExperimentConfig, cfg: TradeoffConfig, penalty: float, model: str
) -> TradeoffAgentResult:
    """Attack success on the training grid and stealth over the sweep configs, for one agent (``model``: its
    folder, as the result names it)."""
    grid = train_cfg.grids[-1]
    (home,), _ = sweep_unintentional(agent, train_cfg.grid_env, [(grid.size, grid.holes)], episodes=cfg.episodes,
                                     seed=cfg.seed, keep=0)  # fmt: skip
    summaries, _ = sweep_unintentional(
        agent, train_cfg.grid_env, parse_configs(cfg.configs), episodes=cfg.episodes, seed=cfg.seed, keep=0
    )
    rows = tuple(s.row() for s in summaries)
    return TradeoffAgentResult(
        penalty=penalty,
        seed=train_cfg.run.seed,
        model=model,
        training_grid=grid.label,
        normal_success=Rate(home.normal_outcomes.get("user_goal", 0), cfg.episodes),
        trojan_success=Rate(home.trojan_outcomes.get("adversary_goal", 0), cfg.episodes),
        activation=Rate(sum(r.activation.k for r in rows), sum(r.activation.n for r in rows)),
        detection=trigger_detection(summaries)[-1].row(),
        per_config=rows,
    )
