"""Editing LSTM units during an episode, and measuring what the edit does to the agent's goal.

:class:`SetUnits` is an intervention (see :class:`seqtrojan.agent.state.Intervention`): from a given episode step
on, it overwrites chosen units of one layer's h or c with given values. The paper edited the step-type units and
found that this switches the agent's goal without hurting its hole avoidance; :func:`switch_experiment` measures
exactly that, in both directions, with 95% intervals:

* **activate**: in the normal env, set the units to their mean trojan-env value after the trigger; the switch
  rate is how often the agent then reaches the adversary's goal (baseline: without the edit).
* **deactivate**: in the trojan env, set them to their mean normal-env value from the trigger on; the switch rate
  is how often the agent reaches the user's goal despite the trigger.

A control edits the same number of randomly chosen other units of the same layer to the same kind of values.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState
from seqtrojan.analysis.results import SwitchResult
from seqtrojan.analysis.traces import StateTrace
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate


class SetUnits:
    """From episode step ``from_step`` on, set ``units`` of layer ``layer``'s ``which`` ("h" or "c") to ``values``."""

    def __init__(
        self,
        layer: int,
        units: Sequence[int],
        values: Sequence[float] | np.ndarray | torch.Tensor,
        which: str = "c",
        from_step: int = 0,
    ) -> None:
        if which not in ("h", "c"):
            raise ValueError(f"which must be 'h' or 'c', got {which!r}")
        self.layer, self.which, self.from_step = layer, which, from_step
        self.units = torch.as_tensor(list(units), dtype=torch.int64)
        self.values = torch.as_tensor(values, dtype=torch.float32)
        if self.values.shape != self.units.shape:
            raise ValueError(f"{len(self.units)} units but {tuple(self.values.shape)} values")

    def __call__(self, layer: int, t: torch.Tensor | None, state: LSTMState) -> LSTMState:
        if layer != self.layer or self.units.numel() == 0:
            return state
        active = torch.ones(state.h.shape[0], dtype=torch.bool) if t is None else (t >= self.from_step)
        target = (state.h if self.which == "h" else state.c).clone()
        cols = self.units.to(target.device)
        edited = target[:, cols]
        target[:, cols] = torch.where(active.to(target.device)[:, None], self.values.to(target.device), edited)
        return LSTMState(target, state.c) if self.which == "h" else LSTMState(state.h, target)


def post_trigger_means(trace: StateTrace, layer: int, which: str, units: np.ndarray, start: int) -> np.ndarray:
    """Mean value of ``units`` over every running step from ``start`` on, over all episodes of ``trace``."""
    return running_mean_from(trace.states(which, layer), trace.mask, units, start)


def control_units(width: int, units: np.ndarray, seed: int) -> np.ndarray:
    """As many units as ``units`` (fewer if the part has not that many others), drawn from the other units of a
    part ``width`` wide: the control of an edit experiment."""
    others = np.setdiff1d(np.arange(width), units)
    if not len(others):
        return others
    return np.random.default_rng(seed).choice(others, size=min(len(units), len(others)), replace=False)


def running_mean_from(x: np.ndarray, mask: np.ndarray, units: np.ndarray, start: int) -> np.ndarray:
    """Mean value of ``units`` of ``x`` (E, T, width) over every running step (``mask`` (E, T)) from ``start`` on."""
    chosen = x[:, start:][..., units]  # (E, T', k)
    running = mask[:, start:, None]
    return (chosen * running).sum((0, 1)) / max(int(running.sum()), 1)


def switch_experiment(
    agent: RecurrentActorCritic,
    env: EnvConfig,
    grid: GridSpec,
    normal: StateTrace,
    trojan: StateTrace,
    *,
    layer: int,
    which: str,
    units: Sequence[int],
    trigger_step: int,
    episodes: int = 1000,
    seed: int = 0,
    control_seed: int = 0,
) -> list[SwitchResult]:
    """Activate and deactivate with ``units`` edited, with random other units edited, and with no edit."""
    unit_ids = np.asarray(units, dtype=np.int64)
    width = (agent.lstm_sizes if which == "h" else agent.c_widths)[layer]
    control = control_units(width, unit_ids, control_seed)
    trig_env = dataclasses.replace(env.trigger, eval_steps=(trigger_step, trigger_step))
    env = dataclasses.replace(env, trigger=trig_env)
    results = []
    for direction, in_trojan, source, goal in (
        ("activate", False, trojan, "adversary_goal"),
        ("deactivate", True, normal, "user_goal"),
    ):
        for name, chosen in (("none", np.array([], np.int64)), ("step-units", unit_ids), ("random-units", control)):
            if name != "none" and len(chosen) == 0:
                continue
            edit = None
            if len(chosen):
                values = post_trigger_means(source, layer, which, chosen, trigger_step)
                edit = SetUnits(layer, chosen.tolist(), values, which, from_step=trigger_step)
            batch = evaluate_agent(agent, env, grid, trojan=in_trojan, episodes=episodes, seed=seed, intervention=edit)
            rates = (outcome_rate(batch, goal), outcome_rate(batch, "hole"), outcome_rate(batch, "timeout"))
            results.append(SwitchResult(direction, name, *rates))
    return results
