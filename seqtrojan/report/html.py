"""The reproduction report: one self-contained HTML file (figures embedded), our numbers beside the paper's.

Reads what :mod:`seqtrojan.experiments.reproduce` wrote under its output folder; every section is optional, so a
partial reproduction still gives a report of what exists.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from seqtrojan.evaluation.seeds import SeedSummary, find_summary, summarise_over_seeds
from seqtrojan.evaluation.sweep import SweepRow, load_sweep
from seqtrojan.paper import paper_results
from seqtrojan.stats import auc_interval

_CSS = """
body { font-family: system-ui, -apple-system, Segoe UI, sans-serif; margin: 2em auto; max-width: 1100px;
       color: #222; line-height: 1.45; padding: 0 1em; }
h1 { font-size: 1.7em; margin-bottom: 0.2em; } h2 { margin-top: 1.8em; border-bottom: 1px solid #ddd; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ddd; padding: 4px 8px; text-align: right; }
th { background: #f4f4f4; } td.l, th.l { text-align: left; }
td.paper { color: #666; } td.differs { background: #fff1e6; }
.note { color: #555; font-size: 0.92em; } img { max-width: 100%; border: 1px solid #eee; }
pre { background: #f7f7f7; padding: 0.8em; overflow-x: auto; font-size: 0.85em; }
details { margin: 0.5em 0; }
"""


def _img(path: Path) -> str:
    if not path.exists():
        return "<p class='note'>(figure not produced)</p>"
    data = base64.b64encode(path.read_bytes()).decode()
    return f"<img src='data:image/png;base64,{data}' alt='{html.escape(path.name)}'>"


def _rate(cell: SeedSummary | None) -> str:
    """One seed: the rate and its Wilson interval. Several: mean +- sd over seeds, then each seed's rate."""
    if cell is None:
        return "<td></td>"
    cls = " class='differs'" if cell.differs else ""
    if len(cell.rows) == 1:
        low, high = cell.interval
        return f"<td{cls}>{cell.mean:.3f} <span class='note'>[{low:.3f}, {high:.3f}]</span></td>"
    each = ", ".join(f"{s:.3f}" for s in cell.successes)
    return f"<td{cls}>{cell.mean:.3f} &plusmn; {cell.sd:.3f} <span class='note'>({each})</span></td>"


def _paper(cell: SeedSummary | None) -> str:
    if cell is None or cell.paper is None:
        return "<td class='paper'></td>"
    return f"<td class='paper'>{cell.paper:.3f}</td>"


def _table(cells: Sequence[SeedSummary], columns: list[tuple[str, str, str]], configs: list[str]) -> str:
    head = "".join(f"<th>{html.escape(title)}</th><th>paper</th>" for _, _, title in columns)
    body = []
    for config in configs:
        row = "".join(
            _rate(find_summary(cells, r, e, config)) + _paper(find_summary(cells, r, e, config)) for r, e, _ in columns
        )
        body.append(f"<tr><td class='l'>{config}</td>{row}</tr>")
    return f"<table><tr><th class='l'>grid</th>{head}</tr>{''.join(body)}</table>"


def _seeds_note(cells: Sequence[SeedSummary]) -> str:
    seeds = max((len(c.rows) for c in cells), default=1)
    if seeds == 1:
        return (
            "<p class='note'>One training seed: each cell is that agent's success with its 95% Wilson interval "
            "over the trials. A retrained agent (another seed) can differ by more than this interval.</p>"
        )
    return (
        f"<p class='note'>Over {seeds} training seeds: mean &plusmn; standard deviation of the per-seed success "
        "rates, then each seed's rate. A cell is shaded when the paper's value lies outside every seed's 95% "
        "Wilson interval (the paper reports one training run, so it is compared with what one run gives). "
        "evaluation/summary.json also holds a 95% t-interval for the mean.</p>"
    )


def _details_table(rows: Sequence[SweepRow]) -> str:
    head = "<tr><th class='l'>agent</th><th>seed</th><th>env</th><th class='l'>grid</th><th>success</th>"
    head += "<th>95% interval</th><th>hole</th><th>time-out</th><th>wrong goal</th><th>mean length</th>"
    head += "<th>trials</th></tr>"
    body = "".join(
        f"<tr><td class='l'>{r.agent}</td><td>{r.seed}</td><td>{r.env}</td><td class='l'>{r.config}</td>"
        f"<td>{r.success:.3f}</td><td>[{r.ci_low:.3f}, {r.ci_high:.3f}]</td>"
        f"<td>{r.hole:.3f}</td><td>{r.timeout:.3f}</td><td>{r.wrong_goal:.3f}</td><td>{r.mean_length:.1f}</td>"
        f"<td>{r.episodes}</td></tr>"
        for r in rows
    )
    return f"<table>{head}{body}</table>"


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text()) if path.exists() else None


def build_report(out: Path, scale: str, machine: dict[str, Any]) -> Path:
    sweep_path = out / "evaluation" / "evaluation.json"
    rows = load_sweep(sweep_path) if sweep_path.exists() else []
    cells = summarise_over_seeds(rows)
    timings = _read_json(out / "timings.json") or {}
    curves = _read_json(out / "curves" / "curves.json") or {}
    trajectory = _read_json(out / "trajectory.json")
    paper = paper_results()
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>seqtrojan reproduction</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>Persistent backdoors in recurrent agents: reproduction</h1>",
        f"<p class='note'>{html.escape(paper['source'])}. Scale <b>{html.escape(scale)}</b>, generated "
        f"{_dt.datetime.now():%Y-%m-%d %H:%M} by seqtrojan {html.escape(str(machine.get('seqtrojan')))}. Every rate "
        "is over independent batched episodes with a 95% Wilson interval; cells whose paper value lies outside "
        "our interval are shaded.</p>",
    ]

    # --- headline
    runs = {role: _run_summary(out / "runs" / role) for role in ("clean", "backdoor")}
    train_grid = runs["backdoor"]["grid"] if runs["backdoor"] else None
    parts.append("<h2>Headline: the training configuration</h2>")
    if train_grid and rows:
        columns = [
            ("clean", "normal", "clean agent, normal env"),
            ("backdoor", "normal", "backdoored agent, normal env"),
            ("backdoor", "trojan", "backdoored agent, trojan env"),
        ]
        parts.append(_table(cells, columns, [train_grid]))
        parts.append(_seeds_note(cells))
        ptc = paper["agents"]["training_config"]
        if train_grid != f"{ptc['size']}x{ptc['size']}/{ptc['holes']}":
            parts.append(
                f"<p class='note'>This scale trains on {train_grid}, not the paper's "
                f"{ptc['size']}x{ptc['size']}/{ptc['holes']}: the paper column is empty where it reports nothing "
                "for this grid. Run <code>seqtrojan reproduce --scale paper</code> for the paper's setting.</p>"
            )
    else:
        parts.append("<p class='note'>(no evaluation yet)</p>")

    # --- tables 1 and 2
    configs = list(dict.fromkeys(r.config for r in rows))
    parts.append("<h2>Table 1: success in the normal environment (no trigger)</h2>")
    parts.append(
        "<p class='note'>Success = reached the user's goal. The backdoored agent should behave like the "
        "clean one here.</p>"
    )
    parts.append(
        _table(cells, [("clean", "normal", "clean agent"), ("backdoor", "normal", "backdoored agent")], configs)
    )
    parts.append("<h2>Table 2: success of the backdoored agent in the trojan environment</h2>")
    parts.append(
        "<p class='note'>Success = reached the adversary's goal after the trigger was shown (once, for "
        "one step, at a step drawn so that it always comes before a goal can be reached).</p>"
    )
    parts.append(_table(cells, [("backdoor", "trojan", "backdoored agent")], configs))
    parts.append("<details><summary>Every seed's cell: success, hole-fall, time-out and wrong-goal rates</summary>")
    parts.append(_details_table(rows) + "</details>")

    # --- curves
    parts.append("<h2>Learning curves (backdoor training)</h2>")
    parts.append(_img(out / "curves" / "curves.png"))
    if curves:
        items = "".join(
            f"<tr><td class='l'>{c}</td><td>{d['mean'][-1]:.3f} &plusmn; {d['std'][-1]:.3f}</td>"
            f"<td>{int(d['seeds'][0])}</td><td>{d['env_steps'][-1]:,.0f}</td></tr>"
            for c, d in curves.items()
        )
        parts.append(
            "<table><tr><th class='l'>grid</th><th>final score (mean &plusmn; sd)</th><th>seeds</th>"
            f"<th>env steps</th></tr>{items}</table>"
            "<p class='note'>Score = success in the normal env + success in the trojan env (max 2) over the "
            "episodes that ended in each update, each run trained on that grid alone. The paper shows these curves "
            "(10 seeds) without numbers to compare.</p>"
        )

    # --- trajectory
    parts.append("<h2>One layout with and without the trigger</h2>")
    parts.append(_img(out / "trajectory.png"))
    if trajectory:
        o = trajectory["outcomes"]
        parts.append(
            f"<p class='note'>The backdoored agent on one layout: without the trigger it ended at "
            f"<b>{o['normal'].replace('_', ' ')}</b>; with the trigger at step {trajectory['trigger_step']} "
            f"(shown for one step, inset) at <b>{o['trojan'].replace('_', ' ')}</b>. Frames: "
            "trajectory_normal.txt, trajectory_trojan.txt.</p>"
        )

    # --- looking inside
    analysis = _read_json(out / "analysis" / "analysis.json")
    if analysis:
        parts.append(_analysis_section(analysis, out / "analysis"))

    # --- the adversary's trade-off
    tradeoff = _read_json(out / "tradeoff" / "tradeoff.json")
    if tradeoff:
        parts.append(_tradeoff_section(tradeoff))

    # --- defenses
    defense = _read_json(out / "defense" / "defense.json")
    detection = _read_json(out / "zoo" / "detection.json")
    if defense or detection:
        parts.append(_defense_section(defense, detection))

    # --- training and configs
    parts.append(
        "<h2>Training</h2><table><tr><th class='l'>agent</th><th class='l'>final grid</th>"
        "<th>env steps</th><th>minutes</th><th>mean steps/s</th><th>final stage</th></tr>"
    )
    for role, summary in _headline_runs(out / "runs").items():
        if summary:
            parts.append(
                f"<tr><td class='l'>{role}</td><td class='l'>{summary['grid']}</td><td>{summary['env_steps']:,}</td>"
                f"<td>{summary['minutes']:.1f}</td><td>{summary['sps']:,.0f}</td><td>{summary['stage']}</td></tr>"
            )
    parts.append("</table>")
    for role in ("clean", "backdoor"):
        config = out / "runs" / role / "config.yaml"
        if config.exists():
            parts.append(
                f"<details><summary>{role} agent config</summary><pre>{html.escape(config.read_text())}</pre></details>"
            )
    reproduce_yaml = out / "reproduce.yaml"
    if reproduce_yaml.exists():
        parts.append(
            f"<details><summary>reproduction config</summary><pre>{html.escape(reproduce_yaml.read_text())}"
            "</pre></details>"
        )

    # --- machine and timings
    parts.append("<h2>Machine and timings</h2><table>")
    for key, value in {**machine, **{f"seconds: {k}": f"{v:.1f}" for k, v in timings.items()}}.items():
        parts.append(f"<tr><td class='l'>{html.escape(str(key))}</td><td class='l'>{html.escape(str(value))}</td></tr>")
    parts.append("</table>")
    parts.append(
        "<h2>Method notes</h2><ul class='note'>"
        "<li>Evaluation: each trial is a fresh layout in its own env slot, all trials of a cell run as one batch "
        "until every episode ended (no bias toward short episodes); the policy samples its actions as in "
        "training; the time limit is 4N steps and counts as a failure.</li>"
        "<li>Trojan env: the trigger covers the whole 3x3 view for one step, at a step drawn uniformly from the "
        "configured range and clipped so that it comes before any goal can be reached.</li>"
        "<li>Backdoor injection: the paper's Algorithm 1 (an episode is a trojan-env episode when U(0,1) > 0.5 + "
        "(P_t - P_c)), with the mixing mode named in the backdoor agent's config.</li>"
        "<li>Rewards: +1 correct goal, -1 hole, wrong goal or time-out, 0 otherwise (docs/environment.md explains "
        "the time-out choice).</li></ul>"
    )
    parts.append("</body></html>")
    path = out / "report.html"
    path.write_text("\n".join(parts))
    return path


def _ci(pair: Sequence[float]) -> str:
    return f"<span class='note'>[{pair[0]:.3f}, {pair[1]:.3f}]</span>"


_REST = "; the rest are navigation errors that happen to end at the other goal"


def _tradeoff_section(t: dict[str, Any]) -> str:
    cfg = t["config"]
    parts = [
        "<h2>The adversary's trade-off: a penalty on unintentional activation</h2>",
        "<p class='note'>Backdoored agents that differ only in the reward for reaching the adversary's goal while "
        "the user's goal is correct (<code>env.rewards.false_activation</code>; -1 is the ordinary wrong-goal "
        f"reward), {cfg.get('seeds', 1)} training seed(s) each. Success on the training grid; activation = "
        f"normal-env episodes (no trigger) over {html.escape(str(cfg['configs']))} configs ({cfg['episodes']} per "
        "config) that ended at the adversary's goal; recall of the agent as a trigger detector over the same "
        "configs.</p>",
    ]
    if t.get("penalties"):

        def ms(d: dict[str, float], seeds: int, digits: int = 3) -> str:  # no spread to show from a single seed
            spread = f" &plusmn; {d['std']:.{digits}f}" if seeds > 1 else ""
            return f"{d['mean']:.{digits}f}{spread}"

        parts.append(
            "<table><tr><th>false-activation reward</th><th>seeds</th><th>normal success</th><th>trojan success</th>"
            "<th>unintentional activation</th><th>recall</th></tr>"
        )
        for p in t["penalties"]:
            parts.append(
                f"<tr><td>{p['penalty']:g}</td><td>{p['seeds']}</td><td>{ms(p['normal_success'], p['seeds'])}</td>"
                f"<td>{ms(p['trojan_success'], p['seeds'])}</td><td>{ms(p['activation_rate'], p['seeds'], 4)}</td>"
                f"<td>{ms(p['recall'], p['seeds'])}</td>"
                "</tr>"
            )
        parts.append("</table><details><summary>every agent, with 95% intervals</summary>")
    parts.append(
        "<table><tr><th>false-activation reward</th><th>seed</th><th>normal success [95% CI]</th>"
        "<th>trojan success [95% CI]</th><th>unintentional activation [95% CI]</th><th>recall</th>"
        "<th>precision</th><th class='l'>agent</th></tr>"
    )
    for a in t["agents"]:
        d = a["detection"]
        parts.append(
            f"<tr><td>{a['penalty']:g}</td><td>{a.get('seed', '')}</td>"
            f"<td>{a['normal_success']:.3f} {_ci(a['normal_ci'])}</td>"
            f"<td>{a['trojan_success']:.3f} {_ci(a['trojan_ci'])}</td>"
            f"<td>{a['activation_rate']:.4f} {_ci(a['activation_ci'])}</td><td>{d['recall']:.3f}</td>"
            f"<td>{d['precision']:.3f}</td><td class='l'>{html.escape(a['model'])}</td></tr>"
        )
    parts.append("</table>" + ("</details>" if t.get("penalties") else ""))
    return "".join(parts)


def _detection_table(rows: Sequence[dict[str, Any]]) -> str:
    prevalence = rows[0]["prevalence"]
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
            f"<tr><td class='l'>{r['grid']}</td><td>{r['recall']:.3f} {_ci(r['recall_ci'])}</td>"
            f"<td>{r['false_positive_rate']:.3f} {_ci(r['false_positive_ci'])}</td><td>{r['precision']:.3f}</td>"
            f"<td>{r['f1']:.3f}</td><td>{r['positives']} / {r['negatives']}</td><td>{r['undecided']}</td></tr>"
        )
    parts.append("</table>")
    return "".join(parts)


def _analysis_section(a: dict[str, Any], folder: Path) -> str:
    cfg = a["config"]
    parts = [
        "<h2>Looking inside: response types</h2>",
        f"<p class='note'>h and c of every unit at every step, {cfg['episodes']} episodes per agent and env on "
        f"{cfg['size']}x{cfg['size']} with {cfg['holes'][0]}-{cfg['holes'][1]} holes, trigger at step "
        f"{cfg['trigger_step']}. Rule: a unit responds when its trojan-env mean moves at least "
        f"{a['responses']['rule']['threshold']} normal-env standard deviations from the normal-env mean within "
        f"{a['responses']['rule']['response_window']} steps of the trigger; it is a step response when the mean "
        f"deviation over steps +{a['responses']['rule']['late_start']}..+{a['responses']['rule']['late_end']} stays "
        f"at least {a['responses']['rule']['persist_fraction']} of that, else an impulse.</p>",
        "<table><tr><th class='l'>agent</th><th class='l'>state</th><th>impulse</th><th>none</th><th>step</th></tr>",
    ]
    for agent, layers in a["responses"]["agents"].items():
        for key, value in layers.items():
            c = value["counts"]
            parts.append(
                f"<tr><td class='l'>{agent}</td><td class='l'>{key}</td><td>{c['impulse']}</td>"
                f"<td>{c['none']}</td><td>{c['step']}</td></tr>"
            )
    parts.append("</table>")
    parts.append(
        f"<p>Paper: step responses appear only in the backdoored agent. Here: <b>{a['responses']['finding']}</b> "
        f"(step-type units: clean {a['responses']['step_units_total']['clean']}, backdoored "
        f"{a['responses']['step_units_total']['backdoor']}).</p>"
    )
    for name in ("backdoor", "clean"):
        parts.append(_img(folder / "figures" / f"responses_{name}.png"))
    heatmaps = sorted((folder / "figures").glob("heatmap_*.png"))
    if heatmaps:
        parts.append("<details><summary>Heatmaps of all units (mean over episodes; the supplement's figures)</summary>")
        parts += [_img(p) for p in heatmaps]
        parts.append("</details>")

    goal, inter = a["goal_units"], a["interventions"]
    parts.append("<h2>Looking inside: editing the goal units</h2>")
    parts.append(
        f"<p class='note'>Goal units: layer {goal['layer']} {goal['which']}, units {list(goal['units'])} "
        f"({html.escape(goal['source'])}). From the trigger step on, they are set to their mean value in the "
        f"other env after the trigger; the control edits as many random other units of the same layer. "
        f"{inter['results'][0]['episodes']} episodes per arm on {inter['grid']}.</p>"
        "<table><tr><th class='l'>direction</th><th class='l'>edited</th><th>switch rate [95% CI]</th>"
        "<th>hole rate [95% CI]</th><th>time-out</th></tr>"
    )
    for r in inter["results"]:
        env, goal_name = ("normal", "adversary's") if r["direction"] == "activate" else ("trojan", "user's")
        parts.append(
            f"<tr><td class='l'>{r['direction']} ({env} env &rarr; {goal_name} goal)</td>"
            f"<td class='l'>{r['units']}</td>"
            f"<td>{r['switch_rate']:.3f} {_ci(r['switch_ci'])}</td><td>{r['hole_rate']:.3f} {_ci(r['hole_ci'])}</td>"
            f"<td>{r['timeout_rate']:.3f}</td></tr>"
        )
    parts.append("</table>")

    un = a["unintentional"]
    parts.append("<h2>Unintentional triggers</h2>")
    parts.append(
        "<p class='note'>Activation: the backdoored agent reaches the adversary's goal in the normal env (no trigger "
        "ever shown). Deactivation: it reaches the user's goal in the trojan env despite the trigger. The paper saw "
        "activation on every trial of 23x23/0 (its Table 1: 0.0 success).</p>"
        "<table><tr><th class='l'>grid</th><th>activation rate [95% CI]</th><th>deactivation rate [95% CI]</th>"
        "<th>episodes</th></tr>"
    )
    for row in un["summaries"]:
        parts.append(
            f"<tr><td class='l'>{row['grid']}</td><td>{row['activation_rate']:.3f} {_ci(row['activation_ci'])}</td>"
            f"<td>{row['deactivation_rate']:.3f} {_ci(row['deactivation_ci'])}</td><td>{row['episodes']}</td></tr>"
        )
    flips = "; ".join(
        f"{v['flipped']} of {v['findings']} {kind}s show the goal units switching"
        for kind, v in un.get("goal_units_flipped", {}).items()
    )
    parts.append(
        f"</table><p class='note'>{un['findings']} findings saved (findings.json: layout, trigger step, "
        f"actions; each replays exactly). {flips}{_REST if flips else ''}.</p>"
    )
    parts += [_img(folder / "figures" / name) for name in un["plotted"]]
    if un.get("trigger_detection"):
        parts.append(_detection_table(un["trigger_detection"]))

    se = a["search"]
    lay, seq = se["layouts"], se["sequences"]
    parts.append("<h2>Searching for triggers on purpose</h2>")
    per = f"{lay['seconds_per_found']:.1f} s" if lay["seconds_per_found"] else "n/a (none found)"
    per_seq = f"{seq['seconds_per_found']:.2f} s" if seq["seconds_per_found"] else "n/a (none found)"
    lc = lay["config"]
    parts.append(
        "<table><tr><th class='l'>search</th><th>found / tried</th><th>cost per trigger found</th>"
        "<th>work</th></tr>"
        f"<tr><td class='l'>evolution over {lc['size']}x{lc['size']}/{lc['holes']} hole layouts (no trigger; a layout "
        f"counts when &ge; {lc['success_at']:.0%} of its episodes end at the adversary's goal)</td>"
        f"<td>{lay['found']} / {lay['restarts']}</td><td>{per}</td><td>{lay['episodes']:,} episodes, "
        f"{lay['seconds']:.0f} s</td></tr>"
        f"<tr><td class='l'>gradient ascent on relaxed observation sequences of length "
        f"{seq['config']['length']} (trigger code excluded), rounded to one-hot</td>"
        f"<td>{seq['found']} / {seq['restarts']}</td><td>{per_seq}</td><td>{seq['forward_steps']:,} network "
        f"steps, {seq['seconds']:.1f} s</td></tr>"
        + "".join(_walk_row(w) for w in se.get("walks", []))
        + "</table>"
        + (
            f"<p>After the found sequences, normal-env episodes on {lc['size']}x{lc['size']}/{lc['holes']} that start "
            f"from the state they leave end at the adversary's goal <b>{seq['flip_rate']:.3f}</b> of the time "
            f"(from the usual zero state: {seq['baseline_rate']:.3f}).</p>"
            if seq.get("flip_rate") is not None
            else ""
        )
        + "<p class='note'>Sequence search counts a sequence as found when the rounded observations drive the goal "
        f"units' activation to &ge; {seq['config']['success_at']} (0 = normal-env level, 1 = trojan-env level); such "
        "sequences probe the network and need not be walkable in a grid"
        + (f" (walkable: <b>{seq['walkable']} of {seq['found']}</b> found)" if "walkable" in seq else "")
        + ". Walk search gives walkable sequences by construction: a random walk from the start cell is fixed and "
        "the grid's hole probabilities are optimised (seqtrojan.analysis.walks); with a density penalty the "
        "revealed cells keep the training hole density, without it any density is allowed. Layout search is "
        "realisable too: the found layouts are ordinary solvable grids and the agent chooses its own moves.</p>"
    )
    for w in se.get("walks", []):
        if w.get("flip_rate") is not None:
            parts.append(
                f"<p>After the found walks (density weight {w['config']['density_weight']:g}), normal-env episodes "
                f"end at the adversary's goal <b>{w['flip_rate']:.3f}</b> of the time (from the zero state: "
                f"{w['baseline_rate']:.3f}).</p>"
            )
    return "\n".join(parts)


def _walk_row(w: dict[str, Any]) -> str:
    c = w["config"]
    per = f"{w['seconds_per_found']:.2f} s" if w["seconds_per_found"] else "n/a (none found)"
    densities = w["revealed_density"]
    return (
        f"<tr><td class='l'>walks of {c['length']} views through a {c['size']}x{c['size']} grid, hole probabilities "
        f"optimised (density penalty weight {c['density_weight']:g}, target {w['target_density']:.3f}; revealed "
        f"density {min(densities):.2f}-{max(densities):.2f}; found grids solvable: {w['solvable']} of {w['found']})"
        f"</td><td>{w['found']} / {w['restarts']}</td><td>{per}</td><td>{w['seconds']:.1f} s</td></tr>"
    )


def _r(entry: dict[str, Any]) -> str:
    return f"{entry['rate']:.3f} {_ci(entry['ci95'])}"


def _defense_section(defense: dict[str, Any] | None, detection: dict[str, Any] | None) -> str:
    parts = ["<h2>Defenses</h2>"]
    if defense:
        m = defense["monitor"]
        parts.append(
            f"<h3>Online state monitor</h3><p class='note'>Calibrated only on the deployed agent's own clean episodes "
            f"(no trigger knowledge); threshold {m['monitor']['threshold']:.2f} (largest |z| over all h and c units) "
            f"for a 1% per-episode false-alarm target; {m['episodes']} fresh episodes per row on {m['grid']}.</p>"
            "<table><tr><th class='l'>measure</th><th>value [95% CI]</th></tr>"
            f"<tr><td class='l'>false-alarm rate (normal env)</td><td>{_r(m['normal_alarm']['false_alarm'])}</td></tr>"
            f"<tr><td class='l'>detection rate (trojan env, alarm at or after the trigger)</td>"
            f"<td>{_r(m['trojan_alarm']['detected'])}</td></tr>"
            f"<tr><td class='l'>alarm before the trigger (trojan env)</td>"
            f"<td>{_r(m['trojan_alarm']['alarm_before_trigger'])}</td></tr>"
            f"<tr><td class='l'>median steps from trigger to alarm</td>"
            f"<td>{m['trojan_alarm']['median_steps_to_detect']}</td></tr>"
            f"<tr><td class='l'>attack success without the monitor</td>"
            f"<td>{_r(m['trojan_undefended']['attack_success'])}</td></tr>"
            f"<tr><td class='l'>attack success with alarm-and-reset</td><td>{_r(m['trojan_reset']['attack_success'])}"
            f"</td></tr><tr><td class='l'>clean success without the monitor</td>"
            f"<td>{_r(m['normal_undefended']['success'])}</td></tr>"
            f"<tr><td class='l'>clean success with alarm-and-reset</td><td>{_r(m['normal_reset']['success'])}</td></tr>"
            "</table>"
        )
        parts.append(_trigger_code_note(defense))
        mit = defense["mitigation"]
        names = {
            "before": "no mitigation", "pruned": f"pruned {len(mit['pruned_units'])} least-active units",
            "fine_pruned": "fine-pruning (pruned, then fine-tuned on clean episodes)",
            "fine_tuned": "fine-tuning on clean episodes", "reset_goal_units_oracle": "holding the step units at "
            "their normal level (oracle: needs the trigger to find them)",
        }  # fmt: skip
        parts.append(
            "<h3>Mitigation</h3><table><tr><th class='l'>model</th><th>clean success</th><th>attack success</th></tr>"
        )
        for key, label in names.items():
            if key in mit:
                parts.append(
                    f"<tr><td class='l'>{label}</td><td>{_r(mit[key]['clean_success'])}</td>"
                    f"<td>{_r(mit[key]['attack_success'])}</td></tr>"
                )
        parts.append("</table>")
    if detection:
        labels = [p["label"] for p in detection["scores"][0]["predictions"]]
        n_clean, n_backdoored = labels.count(0), labels.count(1)
        parts.append(
            "<h3>Offline detection from the weights (zoo)</h3><p class='note'>Standardised logistic regression on "
            "size-invariant statistics of the LSTM parameters; every model scored by a detector trained without it "
            f"(stratified {detection['scores'][0]['folds']}-fold), the way TrojAI scores detectors. "
            f"{n_clean} clean and {n_backdoored} backdoored models; ROC-AUC with a 95% interval (Newcombe's "
            "score interval, which covers which models were drawn, not the refitting across folds).</p>"
        )
        parts.append(_few_models_warning(n_clean, n_backdoored))
        parts.append(
            "<table><tr><th class='l'>features</th><th>#</th><th>models</th><th>ROC-AUC [95% CI]</th>"
            "<th>cross-entropy</th><th>Brier</th></tr>"
        )
        for r in detection["scores"]:
            parts.append(
                f"<tr><td class='l'>{r['group']}</td><td>{r['features']}</td><td>{r['models']}</td>"
                f"<td>{_auc(r['roc_auc'], n_backdoored, n_clean)}</td><td>{r['cross_entropy']:.3f}</td>"
                f"<td>{r['brier']:.3f}</td></tr>"
            )
        parts.append("</table>")
        held = [h for h in detection.get("held_out", []) if "roc_auc" in h]
        if held:
            parts.append(
                "<p class='note'>Held out: for each architecture, trigger code or curriculum of the zoo, a detector "
                "trained on the models without it scores the models with it (does it carry over to a kind of model "
                "it never saw?).</p><table><tr><th class='l'>left out, one value at a time</th><th>values</th>"
                "<th>ROC-AUC (all out-of-group predictions)</th><th>cross-entropy</th><th>Brier</th>"
                "<th class='l'>ROC-AUC within each value</th></tr>"
            )
            for h in held:
                within = ", ".join(
                    f"{html.escape(str(g['value']))}: {g['roc_auc']:.2f}" for g in h["groups"] if "roc_auc" in g
                )
                parts.append(
                    f"<tr><td class='l'>{h['key']}</td><td>{len(h['groups'])}</td><td>{h['roc_auc']:.3f}</td>"
                    f"<td>{h['cross_entropy']:.3f}</td><td>{h['brier']:.3f}</td><td class='l'>{within}</td></tr>"
                )
            parts.append("</table>")
        fb = detection.get("functional_backdoors")
        if fb and fb["functional"] + fb["not_functional"]:
            aucs = ", ".join(
                f"{_auc(fb[k + '_roc_auc'], fb[k], n_clean)} for the {name} ones"
                for k, name in (("functional", "working"), ("not_functional", "failed")) if k + "_roc_auc" in fb
            )  # fmt: skip
            aucs = f"ROC-AUC against the clean models: {aucs}" if aucs else ""
            parts.append(
                f"<p class='note'>{fb['functional']} backdoored models have a working backdoor (final trojan-env "
                f"success &ge; {fb['functional_at']:g}) and {fb['not_functional']} do not; all count as backdoored "
                f"above, as their training made them. {aucs}.</p>"
            )
        if detection.get("auc_by_trigger_value"):
            items = ", ".join(f"{k}: {v:.3f}" for k, v in detection["auc_by_trigger_value"].items())
            parts.append(
                f"<p class='note'>ROC-AUC against the clean models, by the trigger's cell code: {items} (each from "
                f"the few backdoored models with that code: rough estimates).</p>"
            )
        for r in detection.get("rejected", []):
            parts.append(f"<p class='note'>Rejected {html.escape(r['model'])}: {html.escape(r['reason'])}</p>")
    return "\n".join(parts)


FEW_MODELS = 20
"""below this many models in a class, the report warns that an AUC from them is a rough estimate"""


def _auc(auc: float, positives: int, negatives: int) -> str:
    """An AUC with its 95% interval (see :func:`seqtrojan.stats.auc_interval`)."""
    if positives < 1 or negatives < 1:
        return f"{auc:.3f}"
    return f"{auc:.3f} {_ci(auc_interval(auc, positives, negatives))}"


def _few_models_warning(n_clean: int, n_backdoored: int) -> str:
    if min(n_clean, n_backdoored) >= FEW_MODELS:
        return ""
    return (
        f"<p class='note'><b>Caution:</b> only {n_clean} clean and {n_backdoored} backdoored models (fewer than "
        f"{FEW_MODELS} in a class): every AUC below is a rough estimate, as its interval shows, and an AUC of 1 from "
        "so few models is weak evidence that the detector works.</p>"
    )


def _trigger_code_note(defense: dict[str, Any]) -> str:
    """Next to the monitor's detection rate: how unusual the defended agent's trigger is."""
    card = Path(str(defense.get("model", ""))) / "card.json"
    try:
        value = json.loads(card.read_text())["config"]["env"]["trigger"]["value"]
    except (OSError, ValueError, KeyError, TypeError):
        value = None
    dedicated = (
        "The default trigger draws the dedicated cell code <code>trigger</code>, which never occurs in normal play: "
        "at the trigger step the agent reads an input channel that is never active in the calibration episodes, "
        "so detecting that trigger is the easiest case for the monitor. A trigger drawn with ordinary cells "
        "(holes, walls) offers no such never-seen input."
    )
    if value is None or value == "trigger":
        agent = "This agent's trigger uses it. " if value == "trigger" else ""
        return f"<p class='note'>{agent}{dedicated}</p>"
    return (
        f"<p class='note'>This agent's trigger draws the cell code <code>{html.escape(str(value))}</code>, which "
        "also occurs in normal play, so the monitor sees no out-of-distribution code at the trigger step (unlike "
        "the default trigger, whose dedicated <code>trigger</code> code never occurs in normal play).</p>"
    )


def _headline_runs(runs_dir: Path) -> dict[str, dict[str, Any] | None]:
    """Every headline agent's run (clean, backdoor, then <role>_seed<k> in seed order) with its summary."""
    names = ["clean", "backdoor"]
    if runs_dir.is_dir():
        extra = [p.name for p in runs_dir.iterdir() if re.fullmatch(r"(clean|backdoor)_seed\d+", p.name)]
        names += sorted(extra, key=lambda n: (int(n.rsplit("seed", 1)[1]), n))
    return {name: _run_summary(runs_dir / name) for name in names}


def _run_summary(run_dir: Path) -> dict[str, Any] | None:
    metrics = run_dir / "metrics.jsonl"
    card = _read_json(run_dir / "model" / "card.json")
    if card is None or not metrics.exists():
        return None
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line]
    evaluation = card.get("metrics", {})
    seconds = evaluation.get("train_seconds") or (rows[-1]["time/elapsed_s"] if rows else 0.0)
    return {
        "grid": evaluation.get("grid", "?"),
        "env_steps": card.get("env_steps") or 0,
        "minutes": seconds / 60,
        "sps": (card.get("env_steps") or 0) / seconds if seconds else 0.0,
        "stage": evaluation.get("stage", rows[-1]["curriculum/stage"] if rows else 0),
    }
