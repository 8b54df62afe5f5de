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
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from seqtrojan.agent.checkpoint import load_agent
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
    UnintentionalResult,
    UnitResponses,
)
from seqtrojan.analysis.search import evolve_layouts, flip_rates, search_sequences
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.analysis.trigger_detection import trigger_detection
from seqtrojan.analysis.unintentional import GoalUnits, save_findings, select_goal_units, sweep_unintentional
from seqtrojan.analysis.walks import is_walkable, search_walks
from seqtrojan.env.config import GridSpec
from seqtrojan.env.core import EpisodeSnapshot
from seqtrojan.env.layout import Layout
from seqtrojan.env.render import render_rgb
from seqtrojan.evaluation.sweep import parse_configs
from seqtrojan.serde import load_json, save_json
from seqtrojan.stats import Rate

__all__ = ["ANALYSIS_FILE", "AnalysisConfig", "run_analysis"]

ENVS = ("normal", "trojan")


def run_analysis(
    clean_model: Path,
    backdoor_model: Path,
    out: Path,
    cfg: AnalysisConfig,
    device: str = "cpu",
    log: Callable[[str], None] = print,
) -> AnalysisResult:
    out.mkdir(parents=True, exist_ok=True)
    (out / "figures").mkdir(exist_ok=True)
    agents = {
        name: load_agent(path, device=device)[:2]
        for name, path in (("clean", clean_model), ("backdoor", backdoor_model))
    }
    timings: dict[str, float] = (
        json.loads((out / "timings.json").read_text()) if (out / "timings.json").exists() else {}
    )

    def timed(stage: str, fn):
        t0 = time.perf_counter()
        value = fn()
        timings[stage] = time.perf_counter() - t0
        (out / "timings.json").write_text(json.dumps(timings, indent=2))
        return value

    # 1. TRACES
    traces: dict[tuple[str, str], StateTrace] = {}
    for name, (agent, acfg) in agents.items():
        for env in ENVS:
            path = out / "traces" / f"{name}_{env}.safetensors"
            if not path.exists():
                log(f"recording {name} agent, {env} env ...")
                trace = timed(
                    f"trace_{name}_{env}",
                    lambda agent=agent, acfg=acfg, env=env, name=name: record_traces(
                        agent,
                        acfg.env,
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

    # 2. RESPONSE TYPES
    classes: dict[tuple[str, int, str], Classification] = {}
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
    finding = (
        "step responses only in the backdoored agent"
        if step_totals["backdoor"] > 0 and step_totals["clean"] == 0
        else "step responses in both agents"
        if step_totals["clean"] > 0 and step_totals["backdoor"] > 0
        else "step responses only in the clean agent"
        if step_totals["clean"] > 0
        else "no step responses in either agent"
    )
    responses = ResponsesResult(cfg.rule, per_agent, step_totals, finding)
    save_json(responses, out / "responses.json")

    # 3. FIGURES
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
                if not heat.exists():
                    plot_heatmaps(
                        traces[(name, "normal")],
                        traces[(name, "trojan")],
                        which,
                        layer,
                        cfg.trigger_step,
                        heat,
                        f"{name} agent, layer {layer} {which}: mean over {cfg.episodes} episodes",
                    )

    # 4. GOAL UNITS AND INTERVENTIONS
    goal, goal_source = _goal_units(classes, agents["backdoor"][0], traces, cfg)
    goal_record = GoalUnitsRecord(**dataclasses.asdict(goal), source=goal_source)
    save_json(goal_record, out / "goal_units.json")
    backdoor, bcfg = agents["backdoor"]
    if not (out / "interventions.json").exists():
        log("interventions ...")
        grid = GridSpec(cfg.size, (cfg.holes[0] + cfg.holes[1]) // 2)
        results = timed(
            "interventions",
            lambda: switch_experiment(
                backdoor,
                bcfg.env,
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
        save_json(InterventionsResult(grid.label, goal_record, tuple(results)), out / "interventions.json")

    # 5. UNINTENTIONAL TRIGGERS
    if not (out / "unintentional.json").exists():
        log("unintentional triggers ...")
        summaries, findings = timed(
            "unintentional",
            lambda: sweep_unintentional(
                backdoor,
                bcfg.env,
                parse_configs(cfg.unintentional_configs),
                episodes=cfg.unintentional_episodes,
                seed=cfg.seed,
            ),
        )
        save_findings(findings, out / "findings.json")
        plotted = _plot_findings(findings, backdoor, bcfg, goal, traces, cfg, out)
        flips = _goal_flips(findings, backdoor, bcfg, goal)
        unintentional = UnintentionalResult(
            tuple(s.row() for s in summaries),
            tuple(d.row() for d in trigger_detection(summaries)),
            len(findings),
            flips,
            tuple(plotted),
        )
        save_json(unintentional, out / "unintentional.json")

    # 6. SEARCH
    if not (out / "search.json").exists():
        log("searching for goal-switching layouts and sequences ...")
        layouts = timed("layout_search", lambda: evolve_layouts(backdoor, bcfg.env, goal, cfg.layout_search))
        sequences, codes = timed("sequence_search", lambda: search_sequences(backdoor, goal, cfg.sequence_search))
        found_codes = codes[np.asarray(sequences.rounded_activation) >= cfg.sequence_search.success_at]
        if len(found_codes):
            flip, base = flip_rates(backdoor, bcfg.env, found_codes, cfg.layout_search.size, cfg.layout_search.holes,
                                    cfg.intervention_episodes, cfg.seed)  # fmt: skip
            sequences = dataclasses.replace(sequences, flip_rate=flip, baseline_rate=base)
        np.save(out / "sequence_codes.npy", codes)
        sequences = dataclasses.replace(sequences, walkable=sum(is_walkable(c) for c in found_codes))
        walks = []
        for weight in cfg.walk_density_weights:
            wcfg = dataclasses.replace(cfg.walk_search, density_weight=weight)
            walk, walk_codes, walk_grids = timed(
                f"walk_search{weight:g}", lambda w=wcfg: search_walks(backdoor, goal, w)
            )
            hits = np.asarray(walk.rounded_activation) >= wcfg.success_at
            if hits.any():
                flip, base = flip_rates(backdoor, bcfg.env, walk_codes[hits], cfg.layout_search.size,
                                        cfg.layout_search.holes, cfg.intervention_episodes, cfg.seed)  # fmt: skip
                walk = dataclasses.replace(walk, flip_rate=flip, baseline_rate=base)
            np.savez(out / f"walks_weight{weight:g}.npz", codes=walk_codes, grids=walk_grids)
            walks.append(walk)
        search = SearchResult(LayoutSearch(cfg.layout_search, tuple(layouts)), sequences, tuple(walks))
        save_json(search, out / "search.json")

    summary = AnalysisResult(
        cfg,
        responses,
        goal_record,
        load_json(InterventionsResult, out / "interventions.json"),
        load_json(UnintentionalResult, out / "unintentional.json"),
        load_json(SearchResult, out / "search.json"),
        timings,
    )
    save_json(summary, out / ANALYSIS_FILE)
    return summary


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
    plotted = []
    normal_mean = {}
    for env in ENVS:
        x = traces[("backdoor", env)].states(goal.which, goal.layer)
        mask = traces[("backdoor", env)].mask
        act = goal.activation(x)
        counts = mask.sum(0)
        keep = counts >= cfg.rule.min_episodes
        normal_mean[env] = ((act * mask).sum(0) / np.maximum(counts, 1))[keep]
    for kind in ("activation", "deactivation"):
        for i, finding in enumerate([f for f in findings if f.kind == kind][: cfg.findings_to_plot]):
            replay = finding.replay(agent, acfg.env)
            series = {
                f"goal units ({len(goal.units)} {goal.which} units of layer {goal.layer})": goal.activation(
                    (replay["h"] if goal.which == "h" else replay["c"])[goal.layer]
                )
            }
            layout = Layout(np.asarray(finding.layout, dtype=np.int8))
            positions = replay["positions"]
            last = positions[-1]
            snap = EpisodeSnapshot(
                layout,
                last,
                len(positions),
                finding.trigger_step is not None,
                finding.trigger_step,
                None,
                None,
                False,
                3,
                (),
                (),
                0,
            )
            rgb = render_rgb(snap, positions[:-1], cell_px=12)
            ref_env = "trojan" if kind == "activation" else "normal"
            name = f"finding_{kind}_{i}.png"
            plot_finding(
                rgb,
                series,
                {next(iter(series)): normal_mean[ref_env]},
                finding.trigger_step,
                out / "figures" / name,
                f"{kind} on {finding.grid}: ended at the {finding.outcome.replace('_', ' ')}",
            )
            plotted.append(name)
    return plotted
