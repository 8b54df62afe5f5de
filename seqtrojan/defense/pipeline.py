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
from seqtrojan.defense.mitigation import MITIGATIONS, MitigationConfig, run_mitigation
from seqtrojan.defense.monitor import MonitorConfig, StateMonitor, measure_monitor
from seqtrojan.defense.results import DEFENSE_FILE, DefenseResult
from seqtrojan.env.config import GridSpec, min_steps_to_goal
from seqtrojan.errors import SeqTrojanError
from seqtrojan.serde import save_json


@dataclass(frozen=True)
class DefenseConfig:
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    mitigation: MitigationConfig = field(default_factory=MitigationConfig)
    grid: tuple[int, int] | None = None
    """(size, holes) to defend on; None: the model's training grid"""
    oracle_episodes: int = 300
    """trojan-env episodes used only by the oracle that locates the step-type units (needs the trigger)"""
    goal_units: int = 8
    """units the oracle reset holds (see seqtrojan.analysis.unintentional.select_goal_units)"""


def run_defense(model: Path, out: Path, cfg: DefenseConfig, device: str = "cpu",
                log: Callable[[str], None] = print) -> DefenseResult:  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    agent, acfg, card = load_agent(model, device=device)
    grid = GridSpec.parse(cfg.grid) if cfg.grid is not None else acfg.grids[-1]
    log(f"calibrating the monitor on {cfg.monitor.calibration_episodes} clean episodes of {grid.label} ...")
    monitor = StateMonitor.calibrate(agent, acfg.grid_env, grid, cfg.monitor, device)
    measured = measure_monitor(agent, acfg.grid_env, grid, monitor, cfg.monitor, device)
    oracle = _oracle_goal_units(agent, acfg, grid, cfg) if acfg.backdoor.enabled else None
    goal = oracle[0] if oracle is not None else None
    log(f"mitigation: {', '.join(MITIGATIONS.names())} ...")
    mitigation = run_mitigation(agent, acfg, grid, cfg.mitigation, out / "mitigation", goal, card["label"])
    result = DefenseResult(
        model=str(model),
        label=card["label"],
        grid=grid.label,
        trigger_value=acfg.grid_env.trigger.drawn_codes,
        monitor=measured,
        oracle_goal_units=GoalUnitsRecord(**dataclasses.asdict(oracle[0]), source=oracle[1]) if oracle else None,
        mitigation=mitigation,
    )
    save_json(result, out / DEFENSE_FILE)
    return result


def _oracle_goal_units(agent, acfg, grid: GridSpec, cfg: DefenseConfig) -> tuple[GoalUnits, str] | None:
    """The backdoored agent's step-type units, found with trigger episodes (so: an oracle, an upper bound)."""
    trigger = max(1, min(12, min_steps_to_goal(grid.size) - 2))
    kw: dict[str, Any] = {"episodes": cfg.oracle_episodes, "trigger_step": trigger, "seed": cfg.monitor.seed + 11}
    normal = record_traces(agent, acfg.env, [grid], trojan=False, **kw)
    trojan = record_traces(agent, acfg.env, [grid], trojan=True, **kw)
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
