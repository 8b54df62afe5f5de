"""Unintentional triggers: ordinary observation sequences that switch the backdoored agent's goal.

* **activation**: in the normal env (no trigger ever shown) the agent ends at the adversary's goal;
* **deactivation**: in the trojan env (trigger shown) it ends at the user's goal.

:func:`sweep_unintentional` runs many episodes per grid config and keeps every such episode as a
:class:`Finding` (its layout, trigger step and actions), so it can be replayed exactly (the agent's states are
recomputed from the observations) and plotted with the goal-keeping units over time (the paper's Figure 9).
The goal-keeping units are summarised by :class:`GoalUnits`: an activation level that is 0 at the units' mean
normal-env value and 1 at their mean trojan-env value after the trigger.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.interventions import post_trigger_means
from seqtrojan.analysis.results import UnintentionalRow
from seqtrojan.analysis.traces import StateTrace, record_traces, replay_states
from seqtrojan.env.codes import GRID_OUTCOMES, OUTCOME_NAMES
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.layout import Layout
from seqtrojan.stats import Rate


@dataclass(frozen=True)
class GoalUnits:
    """Units that keep the goal (e.g. the step-type units) and where they sit in each env."""

    layer: int
    which: str
    units: tuple[int, ...]
    normal_mean: tuple[float, ...]
    trojan_mean: tuple[float, ...]

    @classmethod
    def from_traces(
        cls,
        normal: StateTrace,
        trojan: StateTrace,
        layer: int,
        which: str,
        units: Sequence[int] | np.ndarray,
        trigger_step: int,
    ) -> GoalUnits:
        idx = np.asarray(units, dtype=np.int64)
        n = post_trigger_means(normal, layer, which, idx, trigger_step)
        t = post_trigger_means(trojan, layer, which, idx, trigger_step)
        return cls(layer, which, tuple(int(u) for u in idx), tuple(map(float, n)), tuple(map(float, t)))

    def activation(self, states: np.ndarray) -> np.ndarray:
        """(..., units of the layer) -> (...): projection onto the normal-to-trojan direction, 0 normal, 1 trojan."""
        x = states[..., list(self.units)]
        n, t = np.asarray(self.normal_mean), np.asarray(self.trojan_mean)
        d = t - n
        return ((x - n) * d).sum(-1) / max(float((d * d).sum()), 1e-12)


def select_goal_units(classes: dict, count: int) -> tuple[int, str, np.ndarray, str]:
    """Pick the units that most plausibly keep the goal, from per-(layer, which) classifications.

    Memory lives in the cell state, so c units come first: per layer, the ``count`` step-type c units with the
    largest late deviation; the layer whose picks deviate most in total wins. Editing a few of the most persistent
    units is what the paper did; editing every step-type unit (often most of a layer, since the agent's whole
    trajectory changes after the trigger) also destroys its navigation. Falls back to h units, then to the most
    persistent units whatever their type. Returns (layer, which, units, how they were chosen).
    """
    for which in ("c", "h"):
        options = []
        for (layer, w), cl in classes.items():
            if w != which:
                continue
            step = cl.units("step")
            picked = step[np.argsort(-cl.late[step])][:count]
            if len(picked):
                options.append((float(cl.late[picked].sum()), layer, picked))
        if options:
            _, layer, picked = max(options, key=lambda o: o[0])
            return layer, which, picked, f"the {len(picked)} most persistent step-type {which} units of layer {layer}"
    layer, which = max(classes, key=lambda key: float(np.sort(classes[key].late)[-count:].sum()))
    picked = np.argsort(-classes[(layer, which)].late)[:count]
    return layer, which, picked, f"no step-type units: the {len(picked)} most persistent {which} units of layer {layer}"


@dataclass(frozen=True)
class Finding:
    kind: str  # activation / deactivation
    grid: str
    layout: list[list[int]]
    trigger_step: int | None
    actions: list[int]
    outcome: str
    seed: int
    episode: int

    def replay(self, agent: RecurrentActorCritic, env: EnvConfig) -> dict[str, Any]:
        return replay_states(
            agent, env, Layout(np.asarray(self.layout, dtype=np.int8)), self.actions, trigger_step=self.trigger_step
        )


@dataclass(frozen=True)
class SweepSummary:
    """One grid of the sweep, as the sweep counts it; results store it typed (:meth:`row`: each rate a
    :class:`~seqtrojan.stats.Rate`)."""

    grid: str
    episodes: int
    activation_rate: float
    activation_ci: tuple[float, float]
    deactivation_rate: float
    deactivation_ci: tuple[float, float]
    normal_outcomes: dict[str, int] = field(default_factory=dict)
    """episodes per outcome (user_goal, adversary_goal, hole, timeout) in the normal env"""
    trojan_outcomes: dict[str, int] = field(default_factory=dict)
    """the same in the trojan env (trigger at the evaluation steps)"""

    @property
    def activation(self) -> Rate:
        return Rate(self.normal_outcomes.get("adversary_goal", 0), self.episodes)

    @property
    def deactivation(self) -> Rate:
        return Rate(self.trojan_outcomes.get("user_goal", 0), self.episodes)

    def row(self) -> UnintentionalRow:
        return UnintentionalRow(
            self.grid, self.activation, self.deactivation, dict(self.normal_outcomes), dict(self.trojan_outcomes)
        )


def sweep_unintentional(
    agent: RecurrentActorCritic,
    env: EnvConfig,
    configs: Sequence[tuple[int, int]],
    *,
    episodes: int = 1000,
    seed: int = 0,
    keep: int = 50,
) -> tuple[list[SweepSummary], list[Finding]]:
    """Activation rate (normal env) and deactivation rate (trojan env, evaluation trigger steps) per config, and up
    to ``keep`` findings of each kind per config."""
    summaries, findings = [], []
    for size, holes in configs:
        grid = GridSpec(size, holes)
        counts, outcomes = {}, {}
        for kind, trojan, target in (("activation", False, "adversary_goal"), ("deactivation", True, "user_goal")):
            trace = record_traces(
                agent,
                env,
                [grid],
                episodes=episodes,
                trojan=trojan,
                trigger_step=None,
                seed=seed,
                record_states=False,
            )
            hits = np.flatnonzero(trace.outcome == OUTCOME_NAMES.index(target))
            outcomes[kind] = {name: int((trace.outcome == i).sum()) for i, name in enumerate(GRID_OUTCOMES) if i}
            counts[kind] = len(hits)
            for e in hits[:keep]:
                n = int(trace.length[e])
                step = int(trace.trigger_step[e])
                findings.append(
                    Finding(
                        kind,
                        grid.label,
                        trace.layouts[e].tolist(),
                        step if step >= 0 else None,
                        trace.actions[e, :n].tolist(),
                        target,
                        seed,
                        int(e),
                    )
                )
        activation, deactivation = Rate(counts["activation"], episodes), Rate(counts["deactivation"], episodes)
        summaries.append(
            SweepSummary(
                grid.label,
                episodes,
                activation.value,
                activation.interval,
                deactivation.value,
                deactivation.interval,
                outcomes["activation"],
                outcomes["deactivation"],
            )
        )
    return summaries, findings


def save_findings(findings: Sequence[Finding], path: Path) -> Path:
    path.write_text(json.dumps([dataclasses.asdict(f) for f in findings]))
    return path


def load_findings(path: Path) -> list[Finding]:
    return [Finding(**f) for f in json.loads(path.read_text())]
