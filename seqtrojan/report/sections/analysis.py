"""Looking inside the agents: response types, editing the goal units, unintentional triggers, the agent as a
trigger detector, and searching for triggers on purpose."""

from __future__ import annotations

import html
from collections.abc import Sequence
from pathlib import Path

from seqtrojan.analysis.results import (
    AnalysisResult,
    SearchResult,
    TriggerDetectionRow,
    UnintentionalResult,
    WalkSearchResult,
)
from seqtrojan.report.markup import img, rate

REST = "; the rest are navigation errors that happen to end at the other goal"


def analysis_section(a: AnalysisResult, figures: Path) -> list[str]:
    """``figures``: the analysis's figure folder."""
    return _responses(a, figures) + _interventions(a) + _unintentional(a.unintentional, figures) + _search(a.search)


def _responses(a: AnalysisResult, figures: Path) -> list[str]:
    cfg, rule = a.config, a.responses.rule
    parts = [
        "<h2>Looking inside: response types</h2>",
        f"<p class='note'>h and c of every unit at every step, {cfg.episodes} episodes per agent and env on "
        f"{cfg.size}x{cfg.size} with {cfg.holes[0]}-{cfg.holes[1]} holes, trigger at step "
        f"{cfg.trigger_step}. Rule: a unit responds when its trojan-env mean moves at least "
        f"{rule.threshold} normal-env standard deviations from the normal-env mean within "
        f"{rule.response_window} steps of the trigger; it is a step response when the mean "
        f"deviation over steps +{rule.late_start}..+{rule.late_end} stays "
        f"at least {rule.persist_fraction} of that, else an impulse.</p>",
        "<table><tr><th class='l'>agent</th><th class='l'>state</th><th>impulse</th><th>none</th><th>step</th></tr>",
    ]
    for agent, layers in a.responses.agents.items():
        for key, value in layers.items():
            c = value.counts
            parts.append(
                f"<tr><td class='l'>{agent}</td><td class='l'>{key}</td><td>{c.impulse}</td>"
                f"<td>{c.none}</td><td>{c.step}</td></tr>"
            )
    parts.append("</table>")
    totals = a.responses.step_units_total
    parts.append(
        f"<p>Paper: step responses appear only in the backdoored agent. Here: <b>{a.responses.finding}</b> "
        f"(step-type units: clean {totals['clean']}, backdoored {totals['backdoor']}).</p>"
    )
    for name in ("backdoor", "clean"):
        parts.append(img(figures / f"responses_{name}.png"))
    heatmaps = sorted(figures.glob("heatmap_*.png"))
    if heatmaps:
        parts.append("<details><summary>Heatmaps of all units (mean over episodes; the supplement's figures)</summary>")
        parts += [img(p) for p in heatmaps]
        parts.append("</details>")
    return parts


def _interventions(a: AnalysisResult) -> list[str]:
    goal, inter = a.goal_units, a.interventions
    parts = ["<h2>Looking inside: editing the goal units</h2>"]
    parts.append(
        f"<p class='note'>Goal units: layer {goal.layer} {goal.which}, units {list(goal.units)} "
        f"({html.escape(goal.source)}). From the trigger step on, they are set to their mean value in the "
        f"other env after the trigger; the control edits as many random other units of the same layer. "
        f"{inter.results[0].episodes} episodes per arm on {inter.grid}.</p>"
        "<table><tr><th class='l'>direction</th><th class='l'>edited</th><th>switch rate [95% CI]</th>"
        "<th>hole rate [95% CI]</th><th>time-out</th></tr>"
    )
    for r in inter.results:
        env, goal_name = ("normal", "adversary's") if r.direction == "activate" else ("trojan", "user's")
        parts.append(
            f"<tr><td class='l'>{r.direction} ({env} env &rarr; {goal_name} goal)</td>"
            f"<td class='l'>{r.units}</td>"
            f"<td>{rate(r.switch)}</td><td>{rate(r.hole)}</td>"
            f"<td>{r.timeout.value:.3f}</td></tr>"
        )
    parts.append("</table>")
    return parts


def _unintentional(un: UnintentionalResult, figures: Path) -> list[str]:
    parts = ["<h2>Unintentional triggers</h2>"]
    parts.append(
        "<p class='note'>Activation: the backdoored agent reaches the adversary's goal in the normal env (no trigger "
        "ever shown). Deactivation: it reaches the user's goal in the trojan env despite the trigger. The paper saw "
        "activation on every trial of 23x23/0 (its Table 1: 0.0 success).</p>"
        "<table><tr><th class='l'>grid</th><th>activation rate [95% CI]</th><th>deactivation rate [95% CI]</th>"
        "<th>episodes</th></tr>"
    )
    for row in un.summaries:
        parts.append(
            f"<tr><td class='l'>{row.grid}</td><td>{rate(row.activation)}</td>"
            f"<td>{rate(row.deactivation)}</td><td>{row.episodes}</td></tr>"
        )
    flips = "; ".join(
        f"{flipped.k} of {flipped.n} {kind}s show the goal units switching"
        for kind, flipped in un.goal_units_flipped.items()
    )
    parts.append(
        f"</table><p class='note'>{un.findings} findings saved (findings.json: layout, trigger step, "
        f"actions; each replays exactly). {flips}{REST if flips else ''}.</p>"
    )
    parts += [img(figures / name) for name in un.plotted]
    if un.trigger_detection:
        parts.append(detection_table(un.trigger_detection))
    return parts


def detection_table(rows: Sequence[TriggerDetectionRow]) -> str:
    prevalence = rows[0].prevalence
    parts = [
        "<h3>The agent as a trigger detector</h3>",
        "<p class='note'>Going to the adversary's goal is the agent's way of saying it saw the trigger. Recall: "
        "triggered episodes that reached the adversary's goal; false-positive rate: untriggered episodes that did "
        "(both among episodes that reached a goal; holes and time-outs are left out and counted). Precision at a "
        f"trigger prevalence of {prevalence:g} (seqtrojan.analysis.trigger_detection).</p>",
        "<table><tr><th class='l'>grid</th><th>recall [95% CI]</th><th>false-positive rate [95% CI]</th>"
        "<th>precision</th><th>F1</th><th>decided (trigger / none)</th><th>holes + time-outs</th></tr>",
    ]
    for r in rows:
        parts.append(
            f"<tr><td class='l'>{r.grid}</td><td>{rate(r.recall)}</td>"
            f"<td>{rate(r.false_positive_rate)}</td><td>{r.precision:.3f}</td>"
            f"<td>{r.f1:.3f}</td><td>{r.positives} / {r.negatives}</td><td>{r.undecided}</td></tr>"
        )
    parts.append("</table>")
    return "".join(parts)


def _search(se: SearchResult) -> list[str]:
    lay, seq = se.layouts, se.sequences
    parts = ["<h2>Searching for triggers on purpose</h2>"]
    per = f"{lay.seconds_per_found:.1f} s" if lay.seconds_per_found else "n/a (none found)"
    per_seq = f"{seq.seconds_per_found:.2f} s" if seq.seconds_per_found else "n/a (none found)"
    lc = lay.config
    parts.append(
        "<table><tr><th class='l'>search</th><th>found / tried</th><th>cost per trigger found</th>"
        "<th>work</th></tr>"
        f"<tr><td class='l'>evolution over {lc.size}x{lc.size}/{lc.holes} hole layouts (no trigger; a layout "
        f"counts when &ge; {lc.success_at:.0%} of its episodes end at the adversary's goal)</td>"
        f"<td>{lay.found} / {lay.restarts}</td><td>{per}</td><td>{lay.episodes:,} episodes, "
        f"{lay.seconds:.0f} s</td></tr>"
        f"<tr><td class='l'>gradient ascent on relaxed observation sequences of length "
        f"{seq.config.length} (trigger code excluded), rounded to one-hot</td>"
        f"<td>{seq.found} / {seq.restarts}</td><td>{per_seq}</td><td>{seq.forward_steps:,} network "
        f"steps, {seq.seconds:.1f} s</td></tr>"
        + "".join(_walk_row(w) for w in se.walks)
        + "</table>"
        + (
            f"<p>After the found sequences, normal-env episodes on {lc.size}x{lc.size}/{lc.holes} that start "
            f"from the state they leave end at the adversary's goal <b>{seq.flip_rate.value:.3f}</b> of the time "
            f"(from the usual zero state: {seq.baseline_rate.value:.3f}).</p>"
            if seq.flip_rate is not None and seq.baseline_rate is not None
            else ""
        )
        + "<p class='note'>Sequence search counts a sequence as found when the rounded observations drive the goal "
        f"units' activation to &ge; {seq.config.success_at} (0 = normal-env level, 1 = trojan-env level); such "
        "sequences probe the network and need not be walkable in a grid"
        + (f" (walkable: <b>{seq.walkable} of {seq.found}</b> found)" if seq.walkable is not None else "")
        + ". Walk search gives walkable sequences by construction: a random walk from the start cell is fixed and "
        "the grid's hole probabilities are optimised (seqtrojan.analysis.walks); with a density penalty the "
        "revealed cells keep the training hole density, without it any density is allowed. Layout search is "
        "realisable too: the found layouts are ordinary solvable grids and the agent chooses its own moves.</p>"
    )
    for w in se.walks:
        if w.flip_rate is not None and w.baseline_rate is not None:
            parts.append(
                f"<p>After the found walks (density weight {w.config.density_weight:g}), normal-env episodes "
                f"end at the adversary's goal <b>{w.flip_rate.value:.3f}</b> of the time (from the zero state: "
                f"{w.baseline_rate.value:.3f}).</p>"
            )
    return parts


def _walk_row(w: WalkSearchResult) -> str:
    c = w.config
    per = f"{w.seconds_per_found:.2f} s" if w.seconds_per_found else "n/a (none found)"
    densities = w.revealed_density
    return (
        f"<tr><td class='l'>walks of {c.length} views through a {c.size}x{c.size} grid, hole probabilities "
        f"optimised (density penalty weight {c.density_weight:g}, target {w.target_density:.3f}; revealed "
        f"density {min(densities):.2f}-{max(densities):.2f}; found grids solvable: {w.solvable} of {w.found})"
        f"</td><td>{w.found} / {w.restarts}</td><td>{per}</td><td>{w.seconds:.1f} s</td></tr>"
    )
