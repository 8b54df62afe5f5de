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

``analysis.json`` gathers the results for the report.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.analysis.interventions import switch_experiment
from seqtrojan.analysis.plots import plot_finding, plot_heatmaps, plot_unit_responses
from seqtrojan.analysis.responses import Classification, ResponseRule, classify_units
from seqtrojan.analysis.search import (
    LayoutSearchConfig,
    SequenceSearchConfig,
    evolve_layouts,
    flip_rates,
    search_sequences,
)
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.analysis.trigger_detection import trigger_detection
from seqtrojan.analysis.unintentional import GoalUnits, save_findings, select_goal_units, sweep_unintentional
from seqtrojan.analysis.walks import WalkSearchConfig, is_walkable, search_walks
from seqtrojan.env.config import GridSpec
from seqtrojan.env.core import EpisodeSnapshot
from seqtrojan.env.layout import Layout
from seqtrojan.env.render import render_rgb
from seqtrojan.evaluation.sweep import parse_configs

ENVS = ("normal", "trojan")


@dataclass(frozen=True)
class AnalysisConfig:
    size: int = 27
    """grid of the recorded episodes (the paper: 27x27)"""
    holes: tuple[int, int] = (90, 100)
    """inclusive range of hole counts, one drawn per episode (the paper: roughly 90-100)"""
    episodes: int = 350
    """trials per agent and env (the paper: 350)"""
    trigger_step: int = 12
    """the trigger's step in the trojan env (the paper: 12)"""
    seed: int = 0
    rule: ResponseRule = field(default_factory=ResponseRule)
    intervention_episodes: int = 1000
    unintentional_configs: str = "paper"
    """'paper' (includes 23x23/0, the paper's example) or a list like '23x23/0,27x27/27'"""
    unintentional_episodes: int = 1000
    goal_units: int = 8
    """how many units the goal-unit edits and plots use (see select_goal_units)"""
    findings_to_plot: int = 2
    """per kind (activation, deactivation)"""
    layout_search: LayoutSearchConfig = field(default_factory=LayoutSearchConfig)
    sequence_search: SequenceSearchConfig = field(default_factory=SequenceSearchConfig)
    walk_search: WalkSearchConfig = field(default_factory=WalkSearchConfig)
    walk_density_weights: tuple[float, ...] = (2.0, 0.0)
    """one walk search per weight of the hole-density penalty (2: ordinary density; 0: any density)"""

    @property
    def grids(self) -> list[GridSpec]:
        lo, hi = self.holes
        return [GridSpec(self.size, h) for h in range(lo, hi + 1)]


def run_analysis(
    clean_model: Path,
    backdoor_model: Path,
    out: Path,
    cfg: AnalysisConfig,
    device: str = "cpu",
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
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
    responses: dict[str, Any] = {"rule": dataclasses.asdict(cfg.rule), "agents": {}}
    for name, (agent, _) in agents.items():
        per_agent = {}
        for layer in range(len(agent.lstm_sizes)):
            for which in ("h", "c"):
                cl = classify_units(
                    traces[(name, "normal")], traces[(name, "trojan")], layer, which, cfg.trigger_step, cfg.rule
                )
                classes[(name, layer, which)] = cl
                per_agent[f"layer{layer}.{which}"] = {
                    "counts": cl.counts(),
                    "step_units": cl.units("step").tolist(),
                    "impulse_units": cl.units("impulse").tolist(),
                }
        responses["agents"][name] = per_agent
    step_totals = {n: sum(v["counts"]["step"] for v in responses["agents"][n].values()) for n in agents}
    responses["step_units_total"] = step_totals
    responses["finding"] = (
        "step responses only in the backdoored agent"
        if step_totals["backdoor"] > 0 and step_totals["clean"] == 0
        else "step responses in both agents"
        if step_totals["clean"] > 0 and step_totals["backdoor"] > 0
        else "step responses only in the clean agent"
        if step_totals["clean"] > 0
        else "no step responses in either agent"
    )
    (out / "responses.json").write_text(json.dumps(responses, indent=2))

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
    (out / "goal_units.json").write_text(json.dumps({**dataclasses.asdict(goal), "source": goal_source}, indent=2))
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
        record: dict[str, Any] = {"grid": grid.label, "goal_units": dataclasses.asdict(goal)}
        record["results"] = [dataclasses.asdict(r) for r in results]
        (out / "interventions.json").write_text(json.dumps(record, indent=2))

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
        (out / "unintentional.json").write_text(
            json.dumps(
                {
                    "summaries": [dataclasses.asdict(s) for s in summaries],
                    "trigger_detection": [dataclasses.asdict(d) for d in trigger_detection(summaries)],
                    "findings": len(findings),
                    "goal_units_flipped": flips,
                    "plotted": plotted,
                },
                indent=2,
            )
        )

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
        sequences_walkable = sum(is_walkable(c) for c in found_codes)
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
            walks.append(
                {
                    "config": dataclasses.asdict(wcfg),
                    **dataclasses.asdict(walk),
                    "seconds_per_found": walk.seconds / walk.found if walk.found else None,
                }
            )
        found = sum(r.found for r in layouts)
        seconds = sum(r.seconds for r in layouts)
        (out / "search.json").write_text(
            json.dumps(
                {
                    "layouts": {
                        "config": dataclasses.asdict(cfg.layout_search),
                        "restarts": len(layouts),
                        "found": found,
                        "seconds": seconds,
                        "episodes": sum(r.episodes for r in layouts),
                        "seconds_per_found": seconds / found if found else None,
                        "runs": [dataclasses.asdict(r) for r in layouts],
                    },
                    "sequences": {
                        "config": dataclasses.asdict(cfg.sequence_search),
                        **dataclasses.asdict(sequences),
                        "seconds_per_found": sequences.seconds / sequences.found if sequences.found else None,
                        "walkable": sequences_walkable,
                    },
                    "walks": walks,
                },
                indent=2,
            )
        )

    summary = {
        "config": dataclasses.asdict(cfg),
        "responses": responses,
        "goal_units": {**dataclasses.asdict(goal), "source": goal_source},
        "interventions": json.loads((out / "interventions.json").read_text()),
        "unintentional": json.loads((out / "unintentional.json").read_text()),
        "search": json.loads((out / "search.json").read_text()),
        "timings": timings,
    }
    (out / "analysis.json").write_text(json.dumps(summary, indent=2))
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


def _goal_flips(findings, agent, acfg, goal: GoalUnits) -> dict[str, dict[str, int]]:
    """How many findings of each kind show the goal units actually switching (activation crossing 0.5 upward for an
    activation, downward after the trigger for a deactivation), as opposed to a navigation error that happens to
    end at the other goal."""
    out: dict[str, dict[str, int]] = {}
    for finding in findings:
        replay = finding.replay(agent, acfg.env)
        level = goal.activation((replay["h"] if goal.which == "h" else replay["c"])[goal.layer])
        if finding.kind == "activation":
            flipped = bool((level >= 0.5).any())
        else:
            after = level[finding.trigger_step :] if finding.trigger_step is not None else level
            flipped = bool(len(after)) and bool((after < 0.5).any()) and bool((level >= 0.5).any())
        counts = out.setdefault(finding.kind, {"findings": 0, "flipped": 0})
        counts["findings"] += 1
        counts["flipped"] += int(flipped)
    return out


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
