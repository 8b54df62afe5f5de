"""``seqtrojan defend``: the online monitor and the mitigations on one model; ``seqtrojan zoo``: build a zoo and
score offline detection on it. Results are typed (:mod:`seqtrojan.defense.results`), saved as JSON files that the
report reads."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.analysis.responses import ResponseRule, classify_units
from seqtrojan.analysis.results import GoalUnitsRecord
from seqtrojan.analysis.traces import record_traces
from seqtrojan.analysis.unintentional import GoalUnits, select_goal_units
from seqtrojan.config import EnvSection
from seqtrojan.defense.mitigation import MITIGATIONS, MitigationConfig, run_mitigation
from seqtrojan.defense.monitor import MonitorConfig, StateMonitor, measure_monitor
from seqtrojan.defense.results import DEFENSE_FILE, DefenseResult
from seqtrojan.env.config import EnvConfig, GridSpec, min_steps_to_goal
from seqtrojan.errors import ConfigError, SeqTrojanError
from seqtrojan.serde import save_json


@dataclass(frozen=True)
class DefenseConfig:
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    mitigation: MitigationConfig = field(default_factory=MitigationConfig)
    grid: tuple[int, int] | None = None
    """grid-world models: (size, holes) to defend on; None: the model's training grid (a Gymnasium env's model is
    defended on its env)"""
    oracle_episodes: int = 300
    """trojan-env episodes used only by the oracle that locates the step-type units (needs the trigger)"""
    goal_units: int = 8
    """units the oracle reset holds (see seqtrojan.analysis.unintentional.select_goal_units)"""


def run_defense(model: Path, out: Path, cfg: DefenseConfig, device: str = "cpu",
                log: Callable[[str], None] = print) -> DefenseResult:  # fmt: skip
    agent, acfg, card = load_agent(model, device=device)
    if cfg.grid is not None and not acfg.is_grid:
        raise ConfigError(f"grid={list(cfg.grid)} names a grid, but {str(model)!r} is a model of a Gymnasium env")
    grid = GridSpec.parse(cfg.grid) if cfg.grid is not None else (acfg.grids[-1] if acfg.is_grid else None)
    where = grid.label if grid is not None else acfg.gym_env.id
    out.mkdir(parents=True, exist_ok=True)
    log(f"calibrating the monitor on {cfg.monitor.calibration_episodes} clean episodes of {where} ...")
    monitor = StateMonitor.calibrate(agent, acfg.env, grid, cfg.monitor, device)
    measured = measure_monitor(agent, acfg.env, grid, monitor, cfg.monitor, device)
    oracle = _oracle_goal_units(agent, acfg, grid, cfg) if acfg.backdoor.enabled else None
    goal = oracle[0] if oracle is not None else None
    log(f"mitigation: {', '.join(MITIGATIONS.names())} ...")
    mitigation = run_mitigation(agent, acfg, grid, cfg.mitigation, out / "mitigation", goal, card["label"])
    result = DefenseResult(
        model=str(model),
        label=card["label"],
        grid=where,
        trigger_value=_drawn(acfg.env),
        monitor=measured,
        oracle_goal_units=GoalUnitsRecord(**dataclasses.asdict(oracle[0]), source=oracle[1]) if oracle else None,
        mitigation=mitigation,
    )
    save_json(result, out / DEFENSE_FILE)
    return result


def _drawn(env: EnvSection) -> str:
    """What the env's trigger draws: the grid world's cell codes, or a Gymnasium trigger wrapper's patch."""
    if isinstance(env, EnvConfig):
        return env.trigger.drawn_codes
    t = env.trigger
    if t is None:
        return "none"
    what = f"{t.color} {t.object}" if t.patch == "minigrid" else f"value {t.value:g}"
    return f"{what} on {[list(c) for c in t.cells]}"


def _oracle_goal_units(agent, acfg, grid: GridSpec | None, cfg: DefenseConfig) -> tuple[GoalUnits, str] | None:
    """The backdoored agent's step-type units, found with trigger episodes (so: an oracle, an upper bound). The
    trigger shows at step min(12, N - 2) on an N x N grid, or at the first step of a Gymnasium trigger's
    evaluation range."""
    if grid is not None:
        trigger = max(1, min(12, min_steps_to_goal(grid.size) - 2))
    else:
        wrapped = acfg.gym_env.trigger
        trigger = (wrapped.eval_steps or wrapped.steps)[0]
    grids = [grid] if grid is not None else []
    kw: dict[str, Any] = {"episodes": cfg.oracle_episodes, "trigger_step": trigger, "seed": cfg.monitor.seed + 11}
    normal = record_traces(agent, acfg.env, grids, trojan=False, **kw)
    trojan = record_traces(agent, acfg.env, grids, trojan=True, **kw)
    rule = ResponseRule(min_episodes=max(10, cfg.oracle_episodes // 10), late_start=4, late_end=12)
    classes = {}
    for layer in range(len(agent.lstm_sizes)):
        for which in ("c", "h"):
            try:
                classes[(layer, which)] = classify_units(normal, trojan, layer, which, trigger, rule)
            except SeqTrojanError:  # too few long episodes on a small grid: no oracle
                return None
    layer, which, units, source = select_goal_units(classes, cfg.goal_units)
    return GoalUnits.from_traces(normal, trojan, layer, which, units, trigger), f"oracle: {source}"
