"""Which units carry the goal, found by their effect: response types, goal units chosen by what editing them does,
and the intervention experiment, on a model of any env (``seqtrojan analyze`` on a model of a Gymnasium env:
MiniGrid, a wrapped env of the user's, an imported sb3-contrib or CleanRL agent's env; the grid world's own analysis
adds layouts, searches and walks, :mod:`seqtrojan.analysis.pipeline`).

With the trigger pinned to one step ``s`` (the env's evaluation trigger range set to ``(s, s)``), normal and trojan
episodes are recorded with their states (:func:`~seqtrojan.analysis.traces.record_traces`, the one episode source);
each layer's h and c units are classified by the rule of :mod:`seqtrojan.analysis.responses` (impulse, none, step);
the goal units are chosen by their effect (not, as in the grid world's analysis, as the c units of the layer that
deviates most, which picked units that do nothing in a MiniGrid agent whose goal lives in layer 0): for each layer's
h and c, its ``goal_units`` most persistent step-type units are set to their trojan level in ``selection_episodes``
normal episodes, and the part whose edit sends most of them to the adversary's goal wins; and the intervention
experiment, on fresh episodes, sets them, from step ``s`` on, to their mean level after the trigger in the other
episode type: in normal episodes to the trojan level ("activate": does the episode end at the adversary's goal?), in
trojan episodes to the normal level ("deactivate": does it end at the user's?), beside the same edit on as many
random units and no edit. Where an episode ended is its outcome (a Gymnasium env's ``info["reached"]``): an env
without it can be classified but not switched (the switch rates are then 0 of n).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.config import ResponseRule
from seqtrojan.analysis.interventions import SetUnits, control_units, running_mean_from
from seqtrojan.analysis.responses import Classification, classify_signals, deviation
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.analysis.unintentional import select_goal_units
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.rollout import EpisodeBatch
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.stats import Rate
from seqtrojan.world.episodes import pin_trigger

GOAL_SWITCH_FILE = "goal_switch.json"


@dataclass(frozen=True)
class PartResponses:
    """One layer's h or c units: how many respond to the trigger in each way, and which are step-type."""

    layer: int
    which: str
    """h or c"""
    counts: dict[str, int]
    """impulse / none / step"""
    step_units: tuple[int, ...]


@dataclass(frozen=True)
class SwitchArm:
    """One arm of the intervention experiment."""

    direction: str
    """activate (normal episodes, toward the adversary's goal) or deactivate (trojan episodes, toward the user's)"""
    edited: str
    """none, goal-units or random-units"""
    switched: Rate
    """episodes that ended at the other goal (activate: the adversary's; deactivate: the user's)"""


@dataclass(frozen=True)
class GoalCandidate:
    """One layer's h or c as the goal's carrier: its most persistent step-type units and how often setting them to
    their trojan level sent a normal episode to the adversary's goal (the selection episodes)."""

    layer: int
    which: str
    units: tuple[int, ...]
    activated: Rate


@dataclass(frozen=True)
class GoalSwitchReport:
    """``goal_switch.json``."""

    model: str
    env_id: str
    trigger_step: int
    episodes: int
    """recorded episodes per type for the response types"""
    intervention_episodes: int
    rule: ResponseRule
    responses: tuple[PartResponses, ...]
    candidates: tuple[GoalCandidate, ...]
    """every part with step-type units, tried on the selection episodes"""
    goal_layer: int
    goal_which: str
    goal_units: tuple[int, ...]
    goal_source: str
    """how the goal units were chosen"""
    switches: tuple[SwitchArm, ...]
    """measured on episodes other than the selection's"""


def pinned_trigger(config: ExperimentConfig, step: int | None) -> tuple[ExperimentConfig, int]:
    """The config with its evaluation trigger at one step (default: the earliest of its evaluation range)."""
    env = config.env
    trigger = getattr(env, "trigger", None)
    if trigger is None:
        raise ConfigError("the config's env has no trigger: there are no trojan episodes to analyse")
    if isinstance(step, bool) or (step is not None and (not isinstance(step, int) or step < 0)):
        raise ConfigError(f"the trigger step must be an integer >= 0, got {step!r}")
    if step is None:
        lo = trigger.eval_steps[0] if trigger.eval_steps is not None else getattr(trigger, "steps", (0, 0))[0]
        step = int(lo)
    return dataclasses.replace(config, env=pin_trigger(env, step)), step


def split_layers(
    agent: RecurrentActorCritic, trace: StateTrace
) -> tuple[dict[tuple[int, str], np.ndarray], np.ndarray]:
    """A trace's states as {(layer, "h" or "c"): (E, T, units)} (c only where the cell has one) and the mask."""
    parts = {}
    for layer in range(len(agent.lstm_sizes)):
        parts[(layer, "h")] = trace.states("h", layer)
        if trace.states("c", layer).shape[-1]:
            parts[(layer, "c")] = trace.states("c", layer)
    return parts, trace.mask


def classify_parts(
    normal: StateTrace, trojan: StateTrace, agent: RecurrentActorCritic, trigger_step: int, rule: ResponseRule
) -> dict[tuple[int, str], Classification]:
    """Response types per (layer, h/c) from recorded normal and trojan episodes with the trigger at one step;
    a part with too few running episodes after the trigger is left out."""
    normal_parts, normal_mask = split_layers(agent, normal)
    trojan_parts, trojan_mask = split_layers(agent, trojan)
    classes = {}
    for key, x in normal_parts.items():
        z, counts = deviation(x, normal_mask, trojan_parts[key], trojan_mask, rule.eps)
        try:
            classes[key] = classify_signals(z, counts, trigger_step, rule)
        except ConfigError:
            continue
    if not classes:
        raise ConfigError(
            f"too few episodes still running {rule.late_end} steps after the trigger (step {trigger_step}) to classify "
            f"any unit: record more episodes, or lower the rule's min_episodes / late_end"
        )
    return classes


def analyze_goal_switch(
    agent: RecurrentActorCritic,
    config: ExperimentConfig,
    *,
    model: str = "",
    trigger_step: int | None = None,
    episodes: int = 300,
    intervention_episodes: int = 300,
    goal_units: int = 8,
    selection_episodes: int = 100,
    rule: ResponseRule = ResponseRule(),  # noqa: B008 (frozen)
    seed: int = 0,
    device: torch.device | str = "cpu",
) -> GoalSwitchReport:
    """Response types, goal units and the intervention experiment of one model (see the module docstring)."""
    for name, value in (("episodes", episodes), ("intervention_episodes", intervention_episodes),
                        ("goal_units", goal_units), ("selection_episodes", selection_episodes)):  # fmt: skip
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"{name} must be a positive integer, got {value!r}")
    pinned, step = pinned_trigger(config, trigger_step)
    grids = list(config.grids[-1:])
    recorded = {
        kind: record_traces(agent, pinned.env, grids, episodes=episodes, trojan=kind == "trojan", seed=seed,
                            device=device)
        for kind in ("normal", "trojan")
    }  # fmt: skip
    classes = classify_parts(recorded["normal"], recorded["trojan"], agent, step, rule)
    responses = tuple(
        PartResponses(layer, which, c.counts(), tuple(int(u) for u in c.units("step")))
        for (layer, which), c in sorted(classes.items())
    )
    parts = {kind: split_layers(agent, trace) for kind, trace in recorded.items()}

    def edit(key: tuple[int, str], units: np.ndarray, level_of: str) -> SetUnits:
        """``units`` of ``key`` set from the trigger step on to their level after it in ``level_of`` episodes."""
        states, mask = parts[level_of]
        level = running_mean_from(states[key], mask, units, step)
        return SetUnits(key[0], units.tolist(), level, key[1], from_step=step)

    def run(trojan: bool, count: int, run_seed: int, intervention: SetUnits | None) -> EpisodeBatch:
        grid = grids[0] if grids else None
        return evaluate_agent(agent, pinned.env, grid, trojan=trojan, episodes=count, seed=run_seed, device=device,
                              intervention=intervention)  # fmt: skip

    candidates = []
    for key, cl in sorted(classes.items()):
        step_units = cl.units("step")
        picked = step_units[np.argsort(-cl.late[step_units])][:goal_units]
        if len(picked):
            batch = run(False, selection_episodes, seed + 2, edit(key, picked, "trojan"))
            activated = outcome_rate(batch, "adversary_goal")
            candidates.append(GoalCandidate(key[0], key[1], tuple(int(u) for u in picked), activated))
    if candidates:
        best = max(candidates, key=lambda c: c.activated.value)
        layer, which, units = best.layer, best.which, np.asarray(best.units, dtype=np.int64)
        source = (f"the {len(units)} most persistent step-type {which} units of layer {layer}, the part whose edit "
                  f"switched most of {selection_episodes} selection episodes ({best.activated.value:.3f})")  # fmt: skip
    else:  # no step-type units anywhere: the grid's fallback (most persistent units of any type)
        layer, which, units, source = select_goal_units(classes, goal_units)
    control = control_units(parts["normal"][0][(layer, which)].shape[-1], units, seed)
    switches = []
    for direction, in_trojan, source_kind, target in (("activate", False, "trojan", "adversary_goal"),
                                                      ("deactivate", True, "normal", "user_goal")):  # fmt: skip
        for edited, chosen in (("none", None), ("goal-units", units), ("random-units", control)):
            if chosen is not None and len(chosen) == 0:
                continue
            intervention = None if chosen is None else edit((layer, which), chosen, source_kind)
            batch = run(in_trojan, intervention_episodes, seed + 1, intervention)
            switches.append(SwitchArm(direction, edited, outcome_rate(batch, target)))
    where = config.grids[-1].label if config.is_grid else config.gym_env.id
    return GoalSwitchReport(
        model, where, step, episodes, intervention_episodes, rule, responses, tuple(candidates), layer, which,
        tuple(int(u) for u in units), source, tuple(switches),
    )  # fmt: skip
