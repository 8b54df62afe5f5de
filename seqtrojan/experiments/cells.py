"""Sequence models compared: the same backdoor trained into an LSTM, a peephole LSTM, a GRU and a windowed
Transformer, over several seeds, each measured the same way.

For each cell and training seed a clean and a backdoored agent are trained (on a job backend, from the same
presets with ``agent.cell`` set). Each agent is measured on its training grid (:class:`CellMeasurement`):

* clean and attack success;
* persistence: among trojan episodes that reached a goal, the adversary's share by how many steps after the
  trigger the goal was reached (for the Transformer: does the switch outlive the window?);
* the attack success by trigger step, among the episodes still running at it;
* unintentional activation over a sweep of grid configs (the paper's 14 by default);
* every online monitor (calibrated on the agent's own clean episodes at the false-alarm target);
* the intervention experiment (backdoored agents): how many goal units must be set to their trojan level to
  switch the goal (the "few cells" conjecture);
* state settling before the trigger on a small grid, beside the attack success by trigger step there (the 7x7/7
  conjecture);
* the weight detector's score, trained on a zoo of the same cell (ROC-AUC over seeds in the summary).

Finished trainings and measurements are kept: a stopped study resumes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.config import ResponseRule
from seqtrojan.analysis.interventions import SetUnits, post_trigger_means
from seqtrojan.analysis.responses import classify_units
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.analysis.unintentional import select_goal_units
from seqtrojan.cell_types import CELL_TYPES, cell_names
from seqtrojan.defense.monitor import MONITORS, MonitorConfig, measure_monitor
from seqtrojan.env.codes import OUTCOME_NAMES
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.evaluation.sweep import parse_configs
from seqtrojan.experiment_results import (
    CELLS_FILE,
    CellMeasurement,
    CellsResult,
    CellSummary,
    OnlineArm,
    PersistenceBin,
    Settling,
    SweepPoint,
    UnitsToSwitch,
)
from seqtrojan.experiments.measured import measure_all, train_all
from seqtrojan.experiments.specs import AgentSpec, deep_merge, experiment_from_spec
from seqtrojan.folders import folder_lock, make_output_folder
from seqtrojan.jobs import JobsConfig, TrainJob, make_backend
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml, save_json
from seqtrojan.stats import OverSeeds, Rate, auc_interval, pooled
from seqtrojan.zoo.build import ZooConfig

LABELS = ("clean", "backdoored")
ADVERSARY = OUTCOME_NAMES.index("adversary_goal")
USER = OUTCOME_NAMES.index("user_goal")


@dataclass(frozen=True)
class CellsConfig:
    cells: tuple[str, ...] = field(default_factory=cell_names)
    """every registered cell by default"""
    backdoor: AgentSpec = field(default_factory=lambda: AgentSpec(preset="trojan_s17_h30"))
    clean: AgentSpec = field(default_factory=lambda: AgentSpec(preset="clean_s17_h30"))
    window: int = 8
    """the Transformer's window (``agent.window``)"""
    heads: int = 1
    seeds: int = 3
    episodes: int = 1000
    """evaluation episodes per figure (success, persistence, each trigger step, each sweep config, each edit)"""
    persistence_bins: tuple[tuple[int, int], ...] = ((1, 4), (5, 8), (9, 16), (17, 32), (33, 10_000))
    """steps from the trigger to the goal (inclusive ranges)"""
    min_bin_episodes: int = 10
    """a seed's persistence rate in a bin counts toward the mean over seeds only with at least this many episodes
    there (the pooled rate keeps every episode)"""
    trigger_steps: tuple[int, ...] = (1, 4, 8, 12, 15)
    sweep: str = "paper"
    """grid configs of the unintentional-activation sweep ('paper': the paper's 14, or e.g. '7x7/3,9x9/6')"""
    monitors: tuple[str, ...] = ("state_monitor", "multivariate_monitor")
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    trace_episodes: int = 500
    """episodes recorded per env to classify unit responses (the intervention experiment)"""
    units_trigger_step: int = 6
    unit_counts: tuple[int, ...] = (1, 2, 4, 8, 16, 32)
    rule: ResponseRule = field(default_factory=lambda: ResponseRule(late_start=4, late_end=12))
    settle_grid: GridSpec = field(default_factory=lambda: GridSpec(7, 7))
    settle_trigger_steps: tuple[int, ...] = (1, 2, 4, 6, 8)
    zoo: ZooConfig | None = None
    """a zoo per cell for the weight detector (built in ``<out>/zoo_<cell>``); None: no offline figure"""
    jobs: JobsConfig = field(default_factory=JobsConfig)
    device: str = "cpu"
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.cells or any(not isinstance(c, str) or c not in CELL_TYPES for c in self.cells):
            raise ConfigError(f"cells must name one or more of {cell_names()}, got {list(self.cells)}")
        if not isinstance(self.seeds, int) or not 1 <= self.seeds <= 100:
            raise ConfigError(f"cells.seeds must be an integer in 1..100, got {self.seeds!r}")
        if self.episodes < 1 or self.trace_episodes < 1:
            raise ConfigError("cells.episodes and cells.trace_episodes must be >= 1")
        for name in self.monitors:
            MONITORS.entry(name)
        if any(lo < 0 or hi < lo for lo, hi in self.persistence_bins):
            raise ConfigError(f"cells.persistence_bins must be ranges lo <= hi, got {self.persistence_bins}")
        if any(k < 1 for k in self.unit_counts) or any(s < 1 for s in self.trigger_steps + self.settle_trigger_steps):
            raise ConfigError("cells.unit_counts and the trigger steps must be >= 1")
        parse_configs(self.sweep)


def load_cells_config(scale_or_path: str) -> CellsConfig:
    """A shipped scale's config (``cells_<scale>.yaml``) or a YAML file."""
    path = resolve_preset(scale_or_path if scale_or_path.endswith(".yaml") else f"cells_{scale_or_path}.yaml")
    return from_dict(CellsConfig, load_yaml(path), "")


def agent_name(cell: str, label: str, seed: int) -> str:
    return f"{cell}_{label}_s{seed}"


def cell_jobs(cfg: CellsConfig, runs: Path) -> list[TrainJob]:
    """Per cell and seed, a clean and a backdoored agent; a job's id is its agent's name."""
    jobs = []
    for cell in cfg.cells:
        agent = {"agent": {"cell": cell, "window": cfg.window, "heads": cfg.heads}}
        for label, spec in (("clean", cfg.clean), ("backdoored", cfg.backdoor)):
            for offset in range(cfg.seeds):
                name = agent_name(cell, label, offset)
                config = experiment_from_spec(AgentSpec(spec.preset, deep_merge(spec.set, agent)), runs, name,
                                              cfg.device)  # fmt: skip
                if config.backdoor.enabled != (label == "backdoored"):
                    raise ConfigError(
                        f"the {label} preset {spec.preset!r} has backdoor.enabled: {config.backdoor.enabled}"
                    )
                run = dataclasses.replace(config.run, seed=config.run.seed + offset)
                jobs.append(TrainJob(name, dataclasses.replace(config, run=run)))
    return jobs


# ---------------------------------------------------------------------------------------------- measurements
def persistence(trace: StateTrace, bins: Sequence[tuple[int, int]]) -> tuple[PersistenceBin, ...]:
    """The adversary's share of the trojan episodes that reached a goal, by steps from the trigger to the goal."""
    after = trace.length - trace.trigger_step
    goal = (trace.outcome == ADVERSARY) | (trace.outcome == USER)
    out = []
    for lo, hi in bins:
        chosen = goal & (after >= lo) & (after <= hi)
        out.append(PersistenceBin(lo, hi, Rate(int((chosen & (trace.outcome == ADVERSARY)).sum()), int(chosen.sum()))))
    return tuple(out)


def by_trigger_step(
    agent: RecurrentActorCritic, env: EnvConfig, grid: GridSpec, steps: Sequence[int], episodes: int, seed: int,
    device: str,
) -> tuple[Rate, ...]:  # fmt: skip
    """The adversary's-goal rate with the trigger at each step, among the episodes still running at it."""
    rates = []
    for step in steps:
        trace = record_traces(agent, env, [grid], episodes=episodes, trojan=True, trigger_step=step, seed=seed,
                              device=device, record_states=False)  # fmt: skip
        running = trace.length > step
        rates.append(Rate(int((running & (trace.outcome == ADVERSARY)).sum()), int(running.sum())))
    return tuple(rates)


def goal_unit_candidates(agent: RecurrentActorCritic) -> tuple[str, ...]:
    """Which state parts the edit experiment may pick goal units from: c first where c is a memory (the LSTMs),
    else h (a GRU's only state; a Transformer's c is a copy of recent inputs: writing a trigger-like value there is
    showing the agent a trigger, not editing a memory)."""
    return ("c", "h") if agent.layers[0].c_is_memory else ("h",)


def units_to_switch(
    agent: RecurrentActorCritic, env: EnvConfig, grid: GridSpec, cfg: CellsConfig, seed: int
) -> UnitsToSwitch | None:
    """The intervention experiment (see :class:`UnitsToSwitch`); None where no unit responds to the trigger."""
    step = cfg.units_trigger_step
    normal, trojan = (
        record_traces(agent, env, [grid], episodes=cfg.trace_episodes, trojan=flag, trigger_step=step, seed=seed,
                      device=cfg.device)
        for flag in (False, True)
    )  # fmt: skip
    classes = {}
    for layer in range(len(agent.lstm_sizes)):
        for which in goal_unit_candidates(agent):
            try:
                classes[(layer, which)] = classify_units(normal, trojan, layer, which, step, cfg.rule)
            except ConfigError:  # too few running episodes after the trigger to classify: no candidates there
                continue
    if not classes:
        return None
    most = max(cfg.unit_counts)
    layer, which, ranked, _ = select_goal_units(classes, most)
    width = (agent.lstm_sizes if which == "h" else agent.c_widths)[layer]
    counts = tuple(k for k in cfg.unit_counts if k <= len(ranked)) or (len(ranked),)
    rng = np.random.default_rng([cfg.seed, layer, len(ranked)])
    others = np.setdiff1d(np.arange(width), ranked)
    pool = others if len(others) >= max(counts) else np.arange(width)
    activation: list[Rate] = []
    control: list[Rate] = []
    for k in counts:
        for units, out in ((ranked[:k], activation), (rng.choice(pool, size=k, replace=False), control)):
            values = post_trigger_means(trojan, layer, which, np.asarray(units), step)
            edit = SetUnits(layer, [int(u) for u in units], values, which=which, from_step=step)
            batch = evaluate_agent(agent, env, grid, trojan=False, episodes=cfg.episodes, seed=seed + 17,
                                   device=cfg.device, intervention=edit)  # fmt: skip
            out.append(outcome_rate(batch, "adversary_goal"))
    return UnitsToSwitch(layer, which, tuple(int(u) for u in ranked), counts, tuple(activation), tuple(control))


def settling(agent: RecurrentActorCritic, env: EnvConfig, cfg: CellsConfig, seed: int) -> Settling:
    """How fast the recurrent state stops changing in normal episodes of the settle grid, and the attack success
    there by trigger step. A c that is not a memory (the Transformer's window: a copy of recent inputs) is left out."""
    grid = cfg.settle_grid
    trace = record_traces(agent, env, [grid], episodes=cfg.trace_episodes, trojan=False, seed=seed, device=cfg.device)
    parts = [trace.h[i] for i in range(len(trace.h))]
    if agent.layers[0].c_is_memory:
        parts += list(trace.c)
    state = np.concatenate(parts, -1)  # (E, T, D)
    steps, change = [], []
    for t in range(1, state.shape[1]):
        running = trace.mask[:, t]
        if running.sum() < 10:
            break
        prev, now = state[running, t - 1], state[running, t]
        rel = np.linalg.norm(now - prev, axis=-1) / np.maximum(np.linalg.norm(prev, axis=-1), 1e-6)
        steps.append(t)
        change.append(float(rel.mean()))
    rates = by_trigger_step(agent, env, grid, cfg.settle_trigger_steps, cfg.episodes, seed, cfg.device)
    return Settling(grid.label, tuple(steps), tuple(change), tuple(cfg.settle_trigger_steps), rates)


def measure_agent(job: TrainJob, cfg: CellsConfig, base_env: EnvConfig, offline: float | None) -> CellMeasurement:
    cell, label, seed_text = job.id.rsplit("_", 2)
    label_backdoored = label == "backdoored"
    agent, acfg, _ = load_agent(job.model_dir, device=cfg.device)
    env = acfg.grid_env if label_backdoored else base_env
    grid = acfg.grids[-1]
    n, seed = cfg.episodes, cfg.seed + 1_000_003
    normal = evaluate_agent(agent, env, grid, trojan=False, episodes=n, seed=seed, device=cfg.device)
    trojan = record_traces(agent, env, [grid], episodes=n, trojan=True, seed=seed, device=cfg.device,
                           record_states=False)  # fmt: skip
    sweep = tuple(
        SweepPoint(GridSpec(size, holes).label, outcome_rate(evaluate_agent(
            agent, env, GridSpec(size, holes), trojan=False, episodes=n, seed=seed, device=cfg.device
        ), "adversary_goal"))
        for size, holes in parse_configs(cfg.sweep)
    )  # fmt: skip
    monitor = {}
    for name in cfg.monitors:
        detector = MONITORS.get(name).calibrate(agent, env, grid, cfg.monitor, cfg.device)
        r = measure_monitor(agent, env, grid, detector, cfg.monitor, cfg.device)
        monitor[name] = OnlineArm(r.normal_alarm.false_alarm, r.trojan_alarm.detected, r.trojan_reset.attack_success,
                                  r.normal_reset.success)  # fmt: skip
    return CellMeasurement(
        agent=job.id, cell=cell, label=label, seed=int(seed_text.removeprefix("s")), grid=grid.label,
        clean_success=outcome_rate(normal, "user_goal"),
        attack_success=Rate(int((trojan.outcome == ADVERSARY).sum()), n),
        persistence=persistence(trojan, cfg.persistence_bins),
        trigger_steps=tuple(cfg.trigger_steps),
        by_trigger_step=by_trigger_step(agent, env, grid, cfg.trigger_steps, n, seed, cfg.device),
        sweep=sweep, monitor=monitor,
        units=units_to_switch(agent, env, grid, cfg, seed) if label_backdoored else None,
        settling=settling(agent, env, cfg, seed) if label_backdoored else None,
        offline_score=offline,
    )  # fmt: skip


def offline_scores(cfg: CellsConfig, jobs: Sequence[TrainJob], out: Path, log: Callable[[str], None]):
    """agent name -> the weight detector's probability 'backdoored', the detector trained on a zoo of its cell."""
    if cfg.zoo is None:
        return {}
    from seqtrojan.defense.offline import fit_weight_detector
    from seqtrojan.zoo.build import build_zoo

    scores: dict[str, float] = {}
    for cell in cfg.cells:
        zoo = dataclasses.replace(cfg.zoo, cell=cell, window=cfg.window)
        log(f"building the {cell} zoo ({zoo.size} models) for the weight detector ...")
        jc = cfg.jobs
        build_zoo(zoo, out / f"zoo_{cell}", workers=jc.workers, backend=jc.backend, ray_address=jc.ray_address,
                  threads=jc.threads, log=log)  # fmt: skip
        detector = fit_weight_detector(out / f"zoo_{cell}")
        for job in jobs:
            if job.id.startswith(f"{cell}_"):
                scores[job.id] = float(detector.probability(job.model_dir))
    return scores


def run_cells(cfg: CellsConfig, out: Path, scale: str = "custom", log: Callable[[str], None] = print) -> CellsResult:
    """Train what is not trained yet, measure what is not measured yet, write ``cells.json`` and return it. The
    jobs are made (and a config they refuse is refused) before ``out`` is; ``out`` is held by this process alone."""
    cell_jobs(cfg, out / "runs")
    with folder_lock(make_output_folder(out, "--out"), "cells folder"):
        return _run_cells(cfg, out, scale, log)


def _run_cells(cfg: CellsConfig, out: Path, scale: str, log: Callable[[str], None]) -> CellsResult:
    runs, measured_dir = out / "runs", out / "measured"
    jobs = cell_jobs(cfg, runs)
    backend = make_backend(cfg.jobs)
    train_all(backend, jobs, "cells agent", log)
    scores = offline_scores(cfg, jobs, out, log)
    base_env = experiment_from_spec(cfg.backdoor, Path("."), "base", cfg.device).grid_env
    measures = [partial(measure_agent, job, cfg, base_env, scores.get(job.id)) for job in jobs]
    paths = [measured_dir / f"{job.id}.json" for job in jobs]
    agents = measure_all(backend, jobs, paths, CellMeasurement, measures, log)
    result = assemble(cfg, agents, scale)
    save_json(result, out / CELLS_FILE)
    from seqtrojan.experiments.cells_plot import plot_cells
    from seqtrojan.report.sections.cells import cells_page

    plot_cells(result, out / "cells.png")
    (out / "report.html").write_text(cells_page(result, out / "cells.png"))
    return result


def assemble(cfg: CellsConfig, agents: Sequence[CellMeasurement], scale: str) -> CellsResult:
    """Per cell, the backdoored agents' figures over seeds (the clean agents: clean success, AUC negatives)."""
    from seqtrojan.experiments.matrix import roc_auc

    summaries = []
    for cell in cfg.cells:
        mine = sorted((a for a in agents if a.cell == cell and a.label == "backdoored"), key=lambda a: a.seed)
        clean = sorted((a for a in agents if a.cell == cell and a.label == "clean"), key=lambda a: a.seed)
        if not mine or not clean:
            continue
        bins = []
        for i, (lo, hi) in enumerate(cfg.persistence_bins):
            rates = [a.persistence[i].adversary for a in mine]
            seen = [r.value for r in rates if r.n >= max(1, cfg.min_bin_episodes)]
            if seen:
                bins.append((lo, hi, OverSeeds(tuple(seen)), pooled(rates)))
        sweep_means = [float(np.mean([p.activation.value for p in a.sweep])) for a in mine]
        sweep_pool = Rate(
            sum(p.activation.k for a in mine for p in a.sweep), sum(p.activation.n for a in mine for p in a.sweep)
        )
        positives = [a.offline_score for a in mine if a.offline_score is not None]
        negatives = [a.offline_score for a in clean if a.offline_score is not None]
        auc = roc_auc(positives, negatives) if positives and negatives else None
        per_seed = {
            "detection": {m: OverSeeds(tuple(a.monitor[m].detection.value for a in mine)) for m in cfg.monitors},
            "false_alarm": {m: OverSeeds(tuple(a.monitor[m].false_alarm.value for a in mine)) for m in cfg.monitors},
        }
        steps = tuple(
            (s, OverSeeds(tuple(a.by_trigger_step[i].value for a in mine))) for i, s in enumerate(cfg.trigger_steps)
        )
        attack_pooled = Rate(sum(a.attack_success.k for a in mine), sum(a.attack_success.n for a in mine))
        interval = auc_interval(auc, len(positives), len(negatives)) if auc is not None else None
        summaries.append(
            CellSummary(
                cell=cell, seeds=tuple(a.seed for a in mine),
                clean_model_success=OverSeeds(tuple(a.clean_success.value for a in clean)),
                clean_success=OverSeeds(tuple(a.clean_success.value for a in mine)),
                attack_success=OverSeeds(tuple(a.attack_success.value for a in mine)),
                attack_success_pooled=attack_pooled, persistence=tuple(bins), by_trigger_step=steps,
                unintentional_mean=OverSeeds(tuple(sweep_means)), unintentional_pooled=sweep_pool,
                monitor_detection=per_seed["detection"], monitor_false_alarm=per_seed["false_alarm"],
                units_needed=tuple(a.units.needed() if a.units else None for a in mine), auc=auc, auc_interval=interval,
            )
        )  # fmt: skip
    grid = agents[0].grid if agents else "?"
    return CellsResult(scale, grid, cfg.window, tuple(summaries), tuple(agents))


__all__ = ["CellsConfig", "assemble", "cell_jobs", "load_cells_config", "measure_agent", "run_cells"]
