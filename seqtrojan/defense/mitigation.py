"""Mitigation: make a (possibly) backdoored agent safe to use, measured like the monitor.

* **fine-pruning** (Liu et al. 2018), needs no knowledge of the trigger: units of the last LSTM layer that are the
  least active on the agent's own clean episodes (mean |h|) are pruned -- their gate weights and biases are zeroed,
  so their c and h stay 0 -- and the pruned agent is then fine-tuned with PPO on clean (normal-env) episodes.
* **fine-tuning** alone on clean episodes.
* **state bounds** (UNIT-style, needs no knowledge of the trigger): every unit's h and c is clipped at every step
  to the range it takes on the agent's own clean episodes (:mod:`seqtrojan.defense.state_bounds`).
* **resetting the step-type units** (an oracle upper bound: finding them needs trigger episodes): an intervention
  holds the goal units at their normal-env level at every step.

For each: attack success (adversary's goal in the trojan env) and clean success (user's goal in the normal env)
before and after, with 95% intervals.

Each mitigation is a function ``(MitigationContext) -> dict[str, MitigationArm]`` (the rows it adds to the
mitigation table, by name) registered in :data:`MITIGATIONS`; :func:`run_mitigation` runs every registered one in
registration order, so a new mitigation is its function plus one registration line.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqtrojan.agent.checkpoint import save_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.interventions import SetUnits
from seqtrojan.analysis.traces import record_traces
from seqtrojan.analysis.unintentional import GoalUnits
from seqtrojan.config import BackdoorConfig, CurriculumConfig, ExperimentConfig
from seqtrojan.defense.results import MitigationArm, MitigationResult
from seqtrojan.defense.state_bounds import StateBoundsConfig, calibrate_bounds
from seqtrojan.env.config import GridSpec
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.registry import Registry


@dataclass(frozen=True)
class MitigationConfig:
    prune_fraction: float = 0.25
    """share of the last layer's units that fine-pruning removes"""
    finetune_steps: int = 500_000
    """PPO env steps on clean episodes (0 skips fine-tuning)"""
    calibration_episodes: int = 300
    """clean episodes that fine-pruning ranks units on and that state bounds are fitted on"""
    eval_episodes: int = 1000
    seed: int = 0
    state_bounds: StateBoundsConfig = field(default_factory=StateBoundsConfig)
    """the ``state_bounds`` mitigation's quantile, margin, parts and layers"""


def measure(agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec | None, episodes: int, seed: int,
            title: str, intervention=None, units: tuple[int, ...] = ()) -> MitigationArm:  # fmt: skip
    """``agent``'s clean success (normal env) and attack success (trojan env), as the table's row ``title``."""
    rates = []
    for trojan, goal in ((False, "user_goal"), (True, "adversary_goal")):
        batch = evaluate_agent(agent, cfg.env, grid, trojan=trojan, episodes=episodes, seed=seed,
                               intervention=intervention)  # fmt: skip
        rates.append(outcome_rate(batch, goal))
    return MitigationArm(title, clean_success=rates[0], attack_success=rates[1], units=units)


def prune_units(agent: RecurrentActorCritic, layer: int, units: np.ndarray) -> RecurrentActorCritic:
    """A copy whose ``units`` of ``layer`` are removed: their h is 0 at every step (each cell says how:
    ``silence_units``; e.g. an LSTM zeroes the units' gate rows, a Transformer its output norm's weight and bias)."""
    pruned = copy.deepcopy(agent)
    pruned.layers[layer].silence_units(torch.as_tensor(units, dtype=torch.int64))
    pruned._weight_cache.clear()
    return pruned


def least_active_units(agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec | None, episodes: int,
                       fraction: float, seed: int) -> np.ndarray:  # fmt: skip
    grids = [grid] if grid is not None else []
    trace = record_traces(agent, cfg.env, grids, episodes=episodes, trojan=False, trigger_step=None, seed=seed)
    return least_active(trace.h[-1], trace.mask, fraction)


def least_active(h: np.ndarray, mask: np.ndarray, fraction: float) -> np.ndarray:
    """The ``fraction`` (at least one) of the units of ``h`` (E, T, units) with the smallest mean |h| over the
    running steps (``mask`` (E, T)), least active first."""
    activity = (np.abs(h) * mask[..., None]).sum((0, 1)) / max(int(mask.sum()), 1)
    return np.argsort(activity)[: max(1, round(fraction * h.shape[-1]))]


def finetune(agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec | None, steps: int, out: Path,
             seed: int, label: str | None = None):  # fmt: skip
    """PPO on the normal env only (the defender's clean episodes), starting from ``agent``'s weights, saved as
    ``out/start`` with ``label`` (its card's; None: its config's), which the fine-tuned model inherits. A finished
    fine-tune in ``out`` is reused and a stopped one resumed."""
    from seqtrojan.agent.checkpoint import load_agent
    from seqtrojan.train.trainer import train_or_resume

    start = save_agent(out / "start", agent, cfg, label=cfg.label if label is None else label)
    tune_cfg = dataclasses.replace(
        cfg,
        env=cfg.grid_env.with_grid(grid) if grid is not None else cfg.env,
        ppo=dataclasses.replace(cfg.ppo, total_steps=steps),
        curriculum=CurriculumConfig(),
        backdoor=BackdoorConfig(enabled=False),
        run=dataclasses.replace(cfg.run, out_dir=str(out), name="finetune", seed=seed, init_from=str(start),
                                progress=False, eval_episodes=0, checkpoint_every=10**12),
    )  # fmt: skip
    model_dir, _ = train_or_resume(tune_cfg)
    tuned, _, _ = load_agent(model_dir)
    return tuned


@dataclass(frozen=True)
class MitigationContext:
    """What every mitigation is given: the agent to mitigate, its config, the grid, the settings, a folder of its
    own, the oracle's goal units (None: none found, or a clean agent) and the agent's label (its card's; None: its
    config's; the fine-tuned models inherit it)."""

    agent: RecurrentActorCritic
    cfg: ExperimentConfig
    grid: GridSpec | None
    """the grid world's grid (None: a Gymnasium env's agent, measured on its env)"""
    mcfg: MitigationConfig
    out: Path
    goal: GoalUnits | None = None
    label: str | None = None

    def measure(self, agent: RecurrentActorCritic, title: str, intervention: Any = None,
                units: tuple[int, ...] = ()) -> MitigationArm:  # fmt: skip
        """``agent`` measured like every other row (the same episodes and seed)."""
        return measure(agent, self.cfg, self.grid, self.mcfg.eval_episodes, self.mcfg.seed + 7, title, intervention,
                       units)  # fmt: skip


Mitigation = Callable[[MitigationContext], dict[str, MitigationArm]]
"""A mitigation: the rows it adds to the mitigation table, by name (none where it does not apply)."""

MITIGATIONS: Registry[Mitigation] = Registry("defense", "mitigation")
"""Every mitigation :func:`run_mitigation` runs, in registration order."""


@MITIGATIONS.register("fine_pruning", "prune the least-active last-layer units, then fine-tune on clean episodes")
def fine_pruning(ctx: MitigationContext) -> dict[str, MitigationArm]:
    mcfg = ctx.mcfg
    units = least_active_units(ctx.agent, ctx.cfg, ctx.grid, mcfg.calibration_episodes, mcfg.prune_fraction,
                               mcfg.seed)  # fmt: skip
    pruned = prune_units(ctx.agent, len(ctx.agent.lstm_sizes) - 1, units)
    kept = tuple(int(u) for u in units)
    rows = {"pruned": ctx.measure(pruned, f"pruned {len(kept)} least-active units", units=kept)}
    if mcfg.finetune_steps > 0:
        tuned = finetune(pruned, ctx.cfg, ctx.grid, mcfg.finetune_steps, ctx.out / "fine_pruning", mcfg.seed,
                         ctx.label)  # fmt: skip
        rows["fine_pruned"] = ctx.measure(tuned, "fine-pruning (pruned, then fine-tuned on clean episodes)",
                                          units=kept)  # fmt: skip
    return rows


@MITIGATIONS.register("fine_tuning", "fine-tune with PPO on clean episodes only")
def fine_tuning(ctx: MitigationContext) -> dict[str, MitigationArm]:
    if ctx.mcfg.finetune_steps <= 0:
        return {}
    tuned = finetune(ctx.agent, ctx.cfg, ctx.grid, ctx.mcfg.finetune_steps, ctx.out / "fine_tuning", ctx.mcfg.seed,
                     ctx.label)  # fmt: skip
    return {"fine_tuned": ctx.measure(tuned, "fine-tuning on clean episodes")}


@MITIGATIONS.register("state_bounds", "clip every unit's h and c at every step to its range on clean episodes (UNIT)")
def state_bounds(ctx: MitigationContext) -> dict[str, MitigationArm]:
    sb = ctx.mcfg.state_bounds
    bounds = calibrate_bounds(ctx.agent, ctx.cfg.env, ctx.grid, sb, episodes=ctx.mcfg.calibration_episodes,
                              seed=ctx.mcfg.seed)  # fmt: skip
    title = (f"every unit clipped to its clean [{sb.quantile:g}, {1 - sb.quantile:g}] quantiles "
             f"+- {sb.margin:g} sd ({'+'.join(sb.parts)})")  # fmt: skip
    return {"state_bounds": ctx.measure(ctx.agent, title, intervention=bounds.clipper())}


@MITIGATIONS.register("unit_reset", "hold the step-type units at their normal level (oracle: needs the trigger)")
def unit_reset(ctx: MitigationContext) -> dict[str, MitigationArm]:
    goal = ctx.goal
    if goal is None:
        return {}
    hold = SetUnits(goal.layer, list(goal.units), list(goal.normal_mean), goal.which, from_step=0)
    title = "holding the step units at their normal level (oracle: needs the trigger to find them)"
    units = tuple(int(u) for u in goal.units)
    return {"reset_goal_units_oracle": ctx.measure(ctx.agent, title, intervention=hold, units=units)}


def run_mitigation(
    agent: RecurrentActorCritic, cfg: ExperimentConfig, grid: GridSpec | None, mcfg: MitigationConfig, out: Path,
    goal: GoalUnits | None = None, label: str | None = None,
) -> MitigationResult:  # fmt: skip
    """The agent before any mitigation (row ``before``), then the rows of every registered mitigation. ``label``:
    the agent's card's (None: its config's), which its fine-tuned models inherit."""
    out.mkdir(parents=True, exist_ok=True)
    ctx = MitigationContext(agent, cfg, grid, mcfg, out, goal, label)
    rows = {"before": ctx.measure(agent, "no mitigation")}
    for name, own in mitigation_rows(ctx).items():
        for key, arm in own.items():
            if key in rows:
                raise ConfigError(f"mitigation {name!r} returned row {key!r}, which another row already has")
            rows[key] = arm
    return rows


def mitigation_rows(ctx: MitigationContext) -> dict[str, dict[str, MitigationArm]]:
    """Every registered mitigation's rows, by mitigation (in registration order; the last row of each is the whole
    mitigation, earlier ones its steps, e.g. fine-pruning's pruned agent before its fine-tuning)."""
    ctx.out.mkdir(parents=True, exist_ok=True)
    return {name: mitigation(ctx) for name, mitigation in MITIGATIONS.items()}
