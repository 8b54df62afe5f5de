"""``seqtrojan analyze``: look inside a clean and a backdoored agent (the paper's section 5.2 and open problem 3).

Stages (each skipped when its output exists under ``out``):

1. record h and c of every layer at every step, both agents, both envs (the paper: 27x27, 90-100 holes, trigger at
   step 12, 350 trials) -> ``traces/``;
2. classify every unit as impulse / none / step (:mod:`seqtrojan.analysis.responses`) -> ``responses.json``;
3. plot representative units and heatmaps of all units -> ``figures/``;
4. edit the backdoored agent's step units and measure goal switches and hole avoidance -> ``interventions.json``;
5. sweep grid configs for unintentional activations and deactivations, keep and plot findings, and score the
   agent as a trigger detector (precision / recall) -> ``unintentional.json``, ``findings.json``;
6. search for goal-switching layouts, free observation sequences (are they walkable?) and walks through grids
   (:mod:`seqtrojan.analysis.walks`) -> ``search.json``.

``analysis.json`` gathers the results for the report: an :class:`~seqtrojan.analysis.results.AnalysisResult`, as
each stage's file is the matching type of :mod:`seqtrojan.analysis.results` (saved and loaded with
:mod:`seqtrojan.serde`, so that a wrong key fails at load with its dotted path).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.config import AnalysisConfig
from seqtrojan.analysis.interventions import switch_experiment
from seqtrojan.analysis.plots import plot_finding, plot_heatmaps, plot_unit_responses
from seqtrojan.analysis.responses import Classification, classify_units
from seqtrojan.analysis.results import (
    ANALYSIS_FILE,
    AnalysisResult,
    GoalUnitsRecord,
    InterventionsResult,
    LayoutSearch,
    ResponseCounts,
    ResponsesResult,
    SearchResult,
    SequenceSearchResult,
    UnintentionalResult,
    UnitResponses,
    WalkSearchResult,
)
from seqtrojan.analysis.search import evolve_layouts, flip_rates, search_sequences
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.analysis.trigger_detection import trigger_detection
from seqtrojan.analysis.unintentional import GoalUnits, save_findings, select_goal_units, sweep_unintentional
from seqtrojan.analysis.walks import is_walkable, search_walks
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.config import GridSpec
from seqtrojan.env.core import EpisodeSnapshot
from seqtrojan.env.layout import Layout
from seqtrojan.env.render import render_rgb
from seqtrojan.evaluation.sweep import parse_configs
from seqtrojan.serde import load_json, save_json
from seqtrojan.stats import Rate
from seqtrojan.timings import Timings

__all__ = ["ANALYSIS_FILE", "AnalysisConfig", "run_analysis"]

ENVS = ("normal", "trojan")


Agents = dict[str, tuple[RecurrentActorCritic, ExperimentConfig]]
"""'clean' / 'backdoor' -> the agent and its config"""
Traces = dict[tuple[str, str], StateTrace]
"""(agent, env) -> its recorded states"""
Classes = dict[tuple[str, int, str], Classification]
"""(agent, layer, 'h' / 'c') -> every unit's response type"""


def run_analysis(
    clean_model: Path,
    backdoor_model: Path,
    out: Path,
    cfg: AnalysisConfig,
    device: str = "cpu",
    log: Callable[[str], None] = print,
) -> AnalysisResult:
    """Run every stage of the module docstring not yet done under ``out``; write and return ``analysis.json``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "figures").mkdir(exist_ok=True)
    agents: Agents = {
        name: load_agent(path, device=device)[:2]
        for name, path in (("clean", clean_model), ("backdoor", backdoor_model))
    }
    timer = Timings(out / "timings.json")
    traces = record_all_traces(agents, cfg, out, device, timer, log)
    classes, responses = classify_responses(agents, traces, cfg)
    save_json(responses, out / "responses.json")
    plot_responses(agents, classes, traces, cfg, out)
    goal, goal_source = _goal_units(classes, agents["backdoor"][0], traces, cfg)
    goal_record = GoalUnitsRecord(**dataclasses.asdict(goal), source=goal_source)
    save_json(goal_record, out / "goal_units.json")
    backdoor = agents["backdoor"]
    if not (out / "interventions.json").exists():
        log("interventions ...")
        save_json(run_interventions(backdoor, traces, goal, goal_record, cfg, timer), out / "interventions.json")
    if not (out / "unintentional.json").exists():
        log("unintentional triggers ...")
        save_json(run_unintentional(backdoor, traces, goal, cfg, out, timer), out / "unintentional.json")
    if not (out / "search.json").exists():
        log("searching for goal-switching layouts and sequences ...")
        save_json(run_searches(backdoor, goal, cfg, out, timer), out / "search.json")

    summary = AnalysisResult(
        cfg,
        responses,
        goal_record,
        load_json(InterventionsResult, out / "interventions.json"),
        load_json(UnintentionalResult, out / "unintentional.json"),
        load_json(SearchResult, out / "search.json"),
        timer.times,
    )
    save_json(summary, out / ANALYSIS_FILE)
    return summary


def record_all_traces(
    agents: Agents, cfg: AnalysisConfig, out: Path, device: str, timer: Timings, log: Callable[[str], None]
) -> Traces:
    """1. h and c of every layer at every step, each agent in each env (``traces/<agent>_<env>.safetensors``,
    recorded when missing)."""
    traces: Traces = {}
    for name, (agent, acfg) in agents.items():
        for env in ENVS:
            path = out / "traces" / f"{name}_{env}.safetensors"
            if not path.exists():
                log(f"recording {name} agent, {env} env ...")
                trace = timer.timed(
                    f"trace_{name}_{env}",
                    functools.partial(
                        record_traces,
                        agent,
                        acfg.grid_env,
                        cfg.grids,
                        episodes=cfg.episodes,
                        trojan=env == "trojan",
                        trigger_step=cfg.trigger_step,
                        seed=cfg.seed,
                        device=device,
                        meta={"agent": name},
                    ),
                )
                trace.save(path)
            traces[(name, env)] = StateTrace.load(path)
    return traces


def classify_responses(agents: Agents, traces: Traces, cfg: AnalysisConfig) -> tuple[Classes, ResponsesResult]:
    """2. Every unit's response type (impulse / none / step), per agent, layer and state, and what they show."""
    classes: Classes = {}
    per_agent: dict[str, dict[str, UnitResponses]] = {}
    for name, (agent, _) in agents.items():
        per_layer = per_agent.setdefault(name, {})
        for layer in range(len(agent.lstm_sizes)):
            for which in ("h", "c"):
                cl = classify_units(
                    traces[(name, "normal")], traces[(name, "trojan")], layer, which, cfg.trigger_step, cfg.rule
                )
                classes[(name, layer, which)] = cl
                per_layer[f"layer{layer}.{which}"] = UnitResponses(
                    ResponseCounts(**cl.counts()),
                    tuple(int(u) for u in cl.units("step")),
                    tuple(int(u) for u in cl.units("impulse")),
                )
    step_totals = {n: sum(v.counts.step for v in per_agent[n].values()) for n in agents}
    return classes, ResponsesResult(cfg.rule, per_agent, step_totals, _step_finding(step_totals))


def _step_finding(step_totals: dict[str, int]) -> str:
    if step_totals["backdoor"] > 0 and step_totals["clean"] == 0:
        return "step responses only in the backdoored agent"
    if step_totals["clean"] > 0 and step_totals["backdoor"] > 0:
        return "step responses in both agents"
    if step_totals["clean"] > 0:
        return "step responses only in the clean agent"
    return "no step responses in either agent"


def plot_responses(agents: Agents, classes: Classes, traces: Traces, cfg: AnalysisConfig, out: Path) -> None:
    """3. Each agent's representative units and a heatmap of every layer's h and c (``figures/``, drawn when
    missing)."""
    for name, (agent, _) in agents.items():
        figure = out / "figures" / f"responses_{name}.png"
        if not figure.exists():
            picks = _representatives(classes, name, len(agent.lstm_sizes))
            plot_unit_responses(
                traces[(name, "normal")],
                traces[(name, "trojan")],
                picks,
                cfg.trigger_step,
                figure,
                f"{name} agent: representative units (blue normal env, red trojan env)",
            )
        for layer in range(len(agent.lstm_sizes)):
            for which in ("h", "c"):
                heat = out / "figures" / f"heatmap_{name}_layer{layer}_{which}.png"
                width = (agent.lstm_sizes if which == "h" else agent.c_widths)[layer]
                if width and not heat.exists():  # a GRU has no c units to plot
                    plot_heatmaps(
                        traces[(name, "normal")],
                        traces[(name, "trojan")],
                        which,
                        layer,
                        cfg.trigger_step,
                        heat,
                        f"{name} agent, layer {layer} {which}: mean over {cfg.episodes} episodes",
                    )


def run_interventions(
    backdoor: tuple[RecurrentActorCritic, ExperimentConfig],
    traces: Traces,
    goal: GoalUnits,
    goal_record: GoalUnitsRecord,
    cfg: AnalysisConfig,
    timer: Timings,
) -> InterventionsResult:
    """4. Edit the backdoored agent's goal units: goal switches and hole avoidance."""
    agent, bcfg = backdoor
    grid = GridSpec(cfg.size, (cfg.holes[0] + cfg.holes[1]) // 2)
    results = timer.timed(
        "interventions",
        lambda: switch_experiment(
            agent,
            bcfg.grid_env,
            grid,
            traces[("backdoor", "normal")],
            traces[("backdoor", "trojan")],
            layer=goal.layer,
            which=goal.which,
            units=list(goal.units),
            trigger_step=cfg.trigger_step,
            episodes=cfg.intervention_episodes,
            seed=cfg.seed,
        ),
    )
    return InterventionsResult(grid.label, goal_record, tuple(results))


def run_unintentional(
    backdoor: tuple[RecurrentActorCritic, ExperimentConfig],
    traces: Traces,
    goal: GoalUnits,
    cfg: AnalysisConfig,
    out: Path,
    timer: Timings,
) -> UnintentionalResult:
    """5. Sweep grid configs for unintentional activations and deactivations (``findings.json``, the first ones
    plotted), check which findings switch the goal units, and score the agent as a trigger detector."""
    agent, bcfg = backdoor
    summaries, findings = timer.timed(
        "unintentional",
        lambda: sweep_unintentional(
            agent,
            bcfg.grid_env,
            parse_configs(cfg.unintentional_configs),
            episodes=cfg.unintentional_episodes,
            seed=cfg.seed,
        ),
    )
    save_findings(findings, out / "findings.json")
    plotted = _plot_findings(findings, agent, bcfg, goal, traces, cfg, out)
    flips = _goal_flips(findings, agent, bcfg, goal)
    return UnintentionalResult(
        tuple(s.row() for s in summaries),
        tuple(d.row() for d in trigger_detection(summaries)),
        len(findings),
        flips,
        tuple(plotted),
    )


def run_searches(
    backdoor: tuple[RecurrentActorCritic, ExperimentConfig], goal: GoalUnits, cfg: AnalysisConfig, out: Path,
    timer: Timings,
) -> SearchResult:  # fmt: skip
    """6. Goal-switching layouts, free observation sequences (``sequence_codes.npy``) and walks through grids, one
    search per density weight (``walks_weight<w>.npz``)."""
    agent, bcfg = backdoor
    layouts = timer.timed("layout_search", lambda: evolve_layouts(agent, bcfg.grid_env, goal, cfg.layout_search))
    sequences = _sequence_search(backdoor, goal, cfg, out, timer)
    walks = tuple(_walk_search(backdoor, goal, cfg, weight, out, timer) for weight in cfg.walk_density_weights)
    return SearchResult(LayoutSearch(cfg.layout_search, tuple(layouts)), sequences, walks)


def _sequence_search(
    backdoor: tuple[RecurrentActorCritic, ExperimentConfig], goal: GoalUnits, cfg: AnalysisConfig, out: Path,
    timer: Timings,
) -> SequenceSearchResult:  # fmt: skip
    """Free observation sequences that switch the goal units: how often the found ones flip the goal in grids, and
    how many are walkable."""
    agent, bcfg = backdoor
    sequences, codes = timer.timed("sequence_search", lambda: search_sequences(agent, goal, cfg.sequence_search))
    found_codes = codes[np.asarray(sequences.rounded_activation) >= cfg.sequence_search.success_at]
    if len(found_codes):
        flip, base = flip_rates(agent, bcfg.grid_env, found_codes, cfg.layout_search.size, cfg.layout_search.holes,
                                cfg.intervention_episodes, cfg.seed)  # fmt: skip
        sequences = dataclasses.replace(sequences, flip_rate=flip, baseline_rate=base)
    np.save(out / "sequence_codes.npy", codes)
    return dataclasses.replace(sequences, walkable=sum(is_walkable(c) for c in found_codes))


def _walk_search(
    backdoor: tuple[RecurrentActorCritic, ExperimentConfig], goal: GoalUnits, cfg: AnalysisConfig, weight: float,
    out: Path, timer: Timings,
) -> WalkSearchResult:  # fmt: skip
    """Walks through grids that switch the goal units, with density weight ``weight``, and how often the found
    ones flip the goal."""
    agent, bcfg = backdoor
    wcfg = dataclasses.replace(cfg.walk_search, density_weight=weight)
    walk, walk_codes, walk_grids = timer.timed(f"walk_search{weight:g}", lambda: search_walks(agent, goal, wcfg))
    hits = np.asarray(walk.rounded_activation) >= wcfg.success_at
    if hits.any():
        flip, base = flip_rates(agent, bcfg.grid_env, walk_codes[hits], cfg.layout_search.size,
                                cfg.layout_search.holes, cfg.intervention_episodes, cfg.seed)  # fmt: skip
        walk = dataclasses.replace(walk, flip_rate=flip, baseline_rate=base)
    np.savez(out / f"walks_weight{weight:g}.npz", codes=walk_codes, grids=walk_grids)
    return walk


def _representatives(classes, name: str, layers: int, per_type: int = 2) -> list[tuple[str, int, int, str]]:
    picks = []
    for kind in ("step", "impulse", "none"):
        candidates = []
        for layer in range(layers):
            for which in ("c", "h"):
                cl = classes[(name, layer, which)]
                for u in cl.units(kind):
                    candidates.append((float(cl.late[u] if kind == "step" else cl.peak[u]), which, layer, int(u)))
        candidates.sort(reverse=kind != "none")
        picks += [(which, layer, unit, kind) for _, which, layer, unit in candidates[:per_type]]
    return picks


def _goal_units(classes, agent, traces, cfg: AnalysisConfig) -> tuple[GoalUnits, str]:
    mine = {(layer, which): cl for (name, layer, which), cl in classes.items() if name == "backdoor"}
    layer, which, units, source = select_goal_units(mine, cfg.goal_units)
    goal = GoalUnits.from_traces(
        traces[("backdoor", "normal")], traces[("backdoor", "trojan")], layer, which, units, cfg.trigger_step
    )
    return goal, source


def _goal_flips(findings, agent, acfg, goal: GoalUnits) -> dict[str, Rate]:
    """How many findings of each kind show the goal units actually switching (activation crossing 0.5 upward for an
    activation, downward after the trigger for a deactivation), as opposed to a navigation error that happens to
    end at the other goal: per kind, flipped findings of that kind's findings."""
    counts: dict[str, dict[str, int]] = {}
    for finding in findings:
        replay = finding.replay(agent, acfg.env)
        level = goal.activation((replay["h"] if goal.which == "h" else replay["c"])[goal.layer])
        if finding.kind == "activation":
            flipped = bool((level >= 0.5).any())
        else:
            after = level[finding.trigger_step :] if finding.trigger_step is not None else level
            flipped = bool(len(after)) and bool((after < 0.5).any()) and bool((level >= 0.5).any())
        kind = counts.setdefault(finding.kind, {"findings": 0, "flipped": 0})
        kind["findings"] += 1
        kind["flipped"] += int(flipped)
    return {kind: Rate(c["flipped"], c["findings"]) for kind, c in counts.items()}


def _plot_findings(findings, agent, acfg, goal: GoalUnits, traces, cfg: AnalysisConfig, out: Path) -> list[str]:
    """The first ``cfg.findings_to_plot`` findings of each kind, replayed and drawn with the goal units over time
    beside their mean in the env the agent behaved as if it were in (the paper's Figure 9)."""
    reference = _goal_unit_means(traces, goal, cfg.rule.min_episodes)
    plotted = []
    for kind in ("activation", "deactivation"):
        for i, finding in enumerate([f for f in findings if f.kind == kind][: cfg.findings_to_plot]):
            name = f"finding_{kind}_{i}.png"
            ref_env = "trojan" if kind == "activation" else "normal"
            _plot_one_finding(finding, agent, acfg, goal, reference[ref_env], out / "figures" / name)
            plotted.append(name)
    return plotted


def _goal_unit_means(traces, goal: GoalUnits, min_episodes: int) -> dict[str, np.ndarray]:
    """env -> the backdoored agent's mean goal-unit activation per step, over the steps with enough episodes."""
    means = {}
    for env in ENVS:
        trace = traces[("backdoor", env)]
        act, mask = goal.activation(trace.states(goal.which, goal.layer)), trace.mask
        counts = mask.sum(0)
        means[env] = ((act * mask).sum(0) / np.maximum(counts, 1))[counts >= min_episodes]
    return means


def _plot_one_finding(finding, agent, acfg, goal: GoalUnits, reference: np.ndarray, path: Path) -> None:
    replay = finding.replay(agent, acfg.env)
    label = f"goal units ({len(goal.units)} {goal.which} units of layer {goal.layer})"
    series = {label: goal.activation((replay["h"] if goal.which == "h" else replay["c"])[goal.layer])}
    positions = replay["positions"]
    snap = EpisodeSnapshot(
        layout=Layout(np.asarray(finding.layout, dtype=np.int8)),
        agent=positions[-1],
        t=len(positions),
        trojan=finding.trigger_step is not None,
        on_step=finding.trigger_step,
        off_step=None,
        visible=None,
        adversary_active=False,
        view_size=acfg.env.view_size,
        on_cells=(),
        off_cells=(),
        time_limit=0,
    )
    title = f"{finding.kind} on {finding.grid}: ended at the {finding.outcome.replace('_', ' ')}"
    plot_finding(render_rgb(snap, positions[:-1], cell_px=12), series, {label: reference}, finding.trigger_step,
                 path, title)  # fmt: skip
