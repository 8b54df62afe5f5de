"""Mitigation: make a (possibly) backdoored agent safe to use, measured like the monitor.

* **fine-pruning** (Liu et al. 2018), needs no knowledge of the trigger: units of the last LSTM layer that are the
  least active on the agent's own clean episodes (mean |h|) are pruned -- their gate weights and biases are zeroed,
  so their c and h stay 0 -- and the pruned agent is then fine-tuned with PPO on clean (normal-env) episodes.
* **fine-tuning** alone on clean episodes.
* **resetting the step-type units** (an oracle upper bound: finding them needs trigger episodes): an intervention
  holds the goal units at their normal-env level at every step.

For each: attack success (adversary's goal in the trojan env) and clean success (user's goal in the normal env)
before and after, with 95% intervals.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np
import torch
from torch import nn

from seqtrojan.agent.checkpoint import save_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.interventions import SetUnits
from seqtrojan.analysis.traces import record_traces
from seqtrojan.analysis.unintentional import GoalUnits
from seqtrojan.config import BackdoorConfig, CurriculumConfig, ExperimentConfig
from seqtrojan.defense.results import MitigationArm, MitigationResult
from seqtrojan.env.config import GridSpec
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate


@dataclass(frozen=True)
class MitigationConfig:
    prune_fraction: float = 0.25
    """share of the last layer's units that fine-pruning removes"""
    finetune_steps: int = 500_000
    """PPO env steps on clean episodes (0 skips fine-tuning)"""
    calibration_episodes: int = 300
    eval_episodes: int = 1000
    seed: int = 0


def measure(agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec, episodes: int, seed: int,
            intervention=None) -> MitigationArm:  # fmt: skip
    rates = []
    for trojan, goal in ((False, "user_goal"), (True, "adversary_goal")):
        batch = evaluate_agent(agent, cfg.env, grid, trojan=trojan, episodes=episodes, seed=seed,
                               intervention=intervention)  # fmt: skip
        rates.append(outcome_rate(batch, goal))
    return MitigationArm(clean_success=rates[0], attack_success=rates[1])


def prune_units(agent: RecurrentActorCritic, layer: int, units: np.ndarray) -> RecurrentActorCritic:
    """A copy whose ``units`` of ``layer`` are removed: zero gate rows and biases keep their c and h at 0."""
    pruned = copy.deepcopy(agent)
    cell = cast(nn.LSTMCell, pruned.cells[layer])
    hidden = cell.hidden_size
    rows = torch.as_tensor(np.concatenate([units + g * hidden for g in range(4)]), dtype=torch.int64)
    with torch.no_grad():
        for p in (cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh):
            p[rows] = 0.0
    pruned._weight_cache.clear()
    return pruned


def least_active_units(agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec, episodes: int,
                       fraction: float, seed: int) -> np.ndarray:  # fmt: skip
    trace = record_traces(agent, cfg.env, [grid], episodes=episodes, trojan=False, trigger_step=None, seed=seed)
    layer = len(agent.lstm_sizes) - 1
    activity = (np.abs(trace.h[layer]) * trace.mask[..., None]).sum((0, 1)) / max(int(trace.mask.sum()), 1)
    k = max(1, round(fraction * agent.lstm_sizes[layer]))
    return np.argsort(activity)[:k]


def finetune(agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec, steps: int, out: Path, seed: int):
    """PPO on the normal env only (the defender's clean episodes), starting from ``agent``'s weights. A finished
    fine-tune in ``out`` is reused and a stopped one resumed."""
    from seqtrojan.agent.checkpoint import load_agent
    from seqtrojan.train.trainer import train_or_resume

    start = save_agent(out / "start", agent, cfg, label=cfg.label)
    tune_cfg = dataclasses.replace(
        cfg,
        env=cfg.env.with_grid(grid),
        ppo=dataclasses.replace(cfg.ppo, total_steps=steps),
        curriculum=CurriculumConfig(),
        backdoor=BackdoorConfig(enabled=False),
        run=dataclasses.replace(cfg.run, out_dir=str(out), name="finetune", seed=seed, init_from=str(start),
                                progress=False, eval_episodes=0, checkpoint_every=10**12),
    )  # fmt: skip
    model_dir, _ = train_or_resume(tune_cfg)
    tuned, _, _ = load_agent(model_dir)
    return tuned


def run_mitigation(
    agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec, mcfg: MitigationConfig, out: Path,
    goal: GoalUnits | None = None,
) -> MitigationResult:  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    n, seed = mcfg.eval_episodes, mcfg.seed + 7
    before = measure(agent, cfg, grid, n, seed)
    units = least_active_units(agent, cfg, grid, mcfg.calibration_episodes, mcfg.prune_fraction, mcfg.seed)
    pruned = prune_units(agent, len(agent.lstm_sizes) - 1, units)
    pruned_arm = measure(pruned, cfg, grid, n, seed)
    fine_pruned = fine_tuned = oracle = None
    if mcfg.finetune_steps > 0:
        fine_pruned = measure(finetune(pruned, cfg, grid, mcfg.finetune_steps, out / "fine_pruning", mcfg.seed),
                              cfg, grid, n, seed)  # fmt: skip
        fine_tuned = measure(finetune(agent, cfg, grid, mcfg.finetune_steps, out / "fine_tuning", mcfg.seed),
                             cfg, grid, n, seed)  # fmt: skip
    if goal is not None:
        hold = SetUnits(goal.layer, list(goal.units), list(goal.normal_mean), goal.which, from_step=0)
        oracle = measure(agent, cfg, grid, n, seed, intervention=hold)
    return MitigationResult(grid.label, n, before, tuple(int(u) for u in units), pruned_arm, fine_pruned,
                            fine_tuned, oracle)  # fmt: skip
