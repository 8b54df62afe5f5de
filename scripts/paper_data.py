"""Keep a paper-scale reproduction's small results under docs/data, and print docs/results.md's tables from them.

    python scripts/paper_data.py save results/paper_v5 docs/data/paper     # after `seqtrojan reproduce --scale paper`
    python scripts/paper_data.py print docs/data/paper                      # the tables of docs/results.md

``save`` copies what the tables read (a few hundred KB): ``evaluation/summary.json`` (Tables 1 and 2 over seeds),
``zoo/detection.json``, ``tradeoff/tradeoff.json``, ``defense/defense.json``, ``curves/curves.csv`` (each learning-curve
run's score per update), ``analysis/analysis.json`` and ``timings.json``, and writes ``training.json``: each headline
agent's end-of-training success (its model card's metrics). ``print`` prints the training table, Tables 1 and 2
(``scripts/tables_markdown.py``'s format), the trade-off table, the monitor table, the learning curves' table and the
looking-inside tables (response types, interventions, unintentional triggers); ``tests/test_docs_data.py`` checks that
docs/results.md holds them as printed.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

from seqtrojan.analysis.results import AnalysisResult
from seqtrojan.serde import load_json
from seqtrojan.stats import OverSeeds

LEARNED = 1.9
"""a learning-curve run has learned its grid once an update's score (normal + trojan success, max 2) reaches this"""

KEPT = (
    "evaluation/summary.json", "tradeoff/tradeoff.json", "defense/defense.json", "zoo/detection.json", "timings.json",
    "curves/curves.csv", "analysis/analysis.json",
)  # fmt: skip
"""a reproduction's files the docs' tables read, copied under the same relative paths"""

AGENT = re.compile(r"^(clean|backdoor)(?:_seed(\d+))?$")
"""the headline agents' run folders: ``clean``, ``backdoor`` (seed 0) and ``<kind>_seed<k>``"""


def save(results: Path, out: Path) -> None:
    for name in KEPT:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(results / name, out / name)
    agents = []
    for run in sorted((results / "runs").iterdir()):
        m = AGENT.match(run.name)
        if not m:
            continue
        metrics = json.loads((run / "model" / "card.json").read_text())["metrics"]
        agents.append({"agent": m.group(1), "seed": int(m.group(2) or 0), "normal_success": metrics["normal_success"],
                       "trojan_success": metrics.get("trojan_success")})  # fmt: skip
    (out / "training.json").write_text(json.dumps({"agents": agents}, indent=1) + "\n")
    print(f"kept {len(KEPT)} files and {len(agents)} agents' training figures in {out}")


def _rate(r: dict) -> str:
    low, high = r["ci95"]
    return f"{r['rate']:.3f} [{low:.3f}, {high:.3f}]"


def training_table(data: Path) -> str:
    agents = json.loads((data / "training.json").read_text())["agents"]
    rows = (("clean, normal env", "clean", "normal_success"), ("backdoored, normal env", "backdoor", "normal_success"),
            ("backdoored, trojan env", "backdoor", "trojan_success"))  # fmt: skip
    seeds = sorted({a["seed"] for a in agents})
    lines = ["| agent | " + " | ".join(f"seed {s}" for s in seeds) + " | mean ± sd |", "|---" * (len(seeds) + 2) + "|"]
    for title, kind, key in rows:
        values = [next(a[key] for a in agents if a["agent"] == kind and a["seed"] == s) for s in seeds]
        per_seed = " | ".join(f"{v:.3f}" for v in values)
        lines.append(f"| {title} | {per_seed} | {OverSeeds(tuple(values)).text()} |")
    return "\n".join(lines)


def tradeoff_table(data: Path) -> str:
    agents = json.loads((data / "tradeoff" / "tradeoff.json").read_text())["agents"]
    lines = [
        "| false-activation reward | seeds | normal success | trojan success | unintentional activation | recall |",
        "|---|---|---|---|---|---|",
    ]
    for penalty in dict.fromkeys(a["penalty"] for a in agents):
        mine = [a for a in agents if a["penalty"] == penalty]

        def over(get, digits=3, mine=mine):
            return OverSeeds(tuple(get(a) for a in mine)).text(digits)

        lines.append(f"| {penalty:g} | {len(mine)} | {over(lambda a: a['normal_success']['rate'])} | "
                     f"{over(lambda a: a['trojan_success']['rate'])} | {over(lambda a: a['activation']['rate'], 4)} | "
                     f"{over(lambda a: a['detection']['recall']['rate'])} |")  # fmt: skip
    return "\n".join(lines)


def monitor_table(data: Path) -> str:
    m = json.loads((data / "defense" / "defense.json").read_text())["monitor"]
    rows = (
        ("false-alarm rate (normal env)", m["normal_alarm"]["false_alarm"]),
        ("detection rate (trojan env, alarm at or after the trigger)", m["trojan_alarm"]["detected"]),
        ("alarm before the trigger", m["trojan_alarm"]["alarm_before_trigger"]),
        ("attack success, no monitor", m["trojan_alarm"]["attack_success"]),
        ("attack success, monitor resets the state", m["trojan_reset"]["attack_success"]),
        ("clean success, monitor resets the state", m["normal_reset"]["success"]),
    )
    return "\n".join(["| measure | value [95% CI] |", "|---|---|", *(f"| {name} | {_rate(r)} |" for name, r in rows)])


def _steps(n: float) -> str:
    return f"{n / 1e6:g}M" if n >= 1e6 else f"{n / 1e3:.0f}k"


def curves_table(data: Path) -> str:
    """Per grid: the env steps per run, the last update's score over the seeds (and each seed's), and the seeds whose
    score reached ``LEARNED`` at some update, with the range of the env steps where each first did."""
    runs: dict[str, dict[int, list[tuple[int, float]]]] = {}
    with (data / "curves" / "curves.csv").open() as fh:
        for row in csv.DictReader(fh):
            runs.setdefault(row["config"], {}).setdefault(int(row["seed"]), []).append(
                (int(row["env_steps"]), float(row["score"]))
            )
    lines = [f"| grid | env steps per run | final score (mean ± sd) | seeds at score ≥ {LEARNED}, and when |",
             "|---|---|---|---|"]  # fmt: skip
    for grid, by_seed in runs.items():
        seeds = [points for _, points in sorted(by_seed.items())]
        final = OverSeeds(tuple(points[-1][1] for points in seeds))
        first = [next((s for s, score in points if score >= LEARNED), None) for points in seeds]
        reached = sorted(s for s in first if s is not None)
        steps = max(points[-1][0] for points in seeds)
        when = f"{len(reached)} of {len(first)}"
        if reached:
            when += f", at {_steps(reached[0])}-{_steps(reached[-1])} steps"
        if len(reached) < len(first):
            when += f"; {len(first) - len(reached)} not within {_steps(steps)}"
        per_seed = ", ".join(f"{v:.2f}" for v in final.values)
        lines.append(f"| {grid} | {_steps(steps)} | {final.text()} (per seed {per_seed}) | {when} |")
    return "\n".join(lines)


def response_table(analysis: AnalysisResult) -> str:
    """Each agent's units by response type (impulse / none / step), per layer's h and c."""
    agents = analysis.responses.agents
    first = next(iter(agents.values()))
    keys = list(first)
    widths = {k: first[k].counts.impulse + first[k].counts.none + first[k].counts.step for k in keys}
    head = " | ".join(f"layer {k.removeprefix('layer').replace('.', ' ')} ({widths[k]})" for k in keys)
    lines = [f"| agent | {head} |", "|---" * (len(keys) + 1) + "|"]
    for agent, layers in agents.items():
        cells = " | ".join(f"{c.impulse} / {c.none} / {c.step}" for c in (layers[k].counts for k in keys))
        lines.append(f"| {agent}: impulse / none / step | {cells} |")
    return "\n".join(lines)


def intervention_table(analysis: AnalysisResult) -> str:
    lines = ["| direction | units edited | goal switched [95% CI] | hole | time-out |", "|---|---|---|---|---|"]
    for r in analysis.interventions.results:
        lines.append(f"| {r.direction} | {r.units} | {r.switch.text()} | {r.hole.value:.3f} | {r.timeout.value:.3f} |")
    return "\n".join(lines)


def unintentional_table(analysis: AnalysisResult) -> str:
    """The sweep's grids with any activation or deactivation, then the agent as a trigger detector over all grids."""
    u = analysis.unintentional
    lines = ["| grid | activation (normal env) [95% CI] | deactivation (trojan env) [95% CI] |", "|---|---|---|"]
    for row in u.summaries:
        if row.activation.k or row.deactivation.k:
            lines.append(f"| {row.grid} | {row.activation.text()} | {row.deactivation.text()} |")
    for d in u.trigger_detection:
        if d.grid == "all":
            lines.append(f"| all {len(u.summaries)} grids, as a trigger detector | recall {d.recall.text()} | "
                         f"false-positive rate {d.false_positive_rate.text()} |")  # fmt: skip
    return "\n".join(lines)


def print_tables(data: Path) -> None:
    script = str(Path(__file__).parent / "tables_markdown.py")
    summary = str(data / "evaluation" / "summary.json")
    tables = subprocess.run([sys.executable, script, summary], capture_output=True, text=True, check=True)
    analysis = load_json(AnalysisResult, data / "analysis" / "analysis.json")
    for title, text in (("Training", training_table(data)), ("Tables 1 and 2", tables.stdout.rstrip("\n")),
                        ("Trade-off", tradeoff_table(data)), ("Monitor", monitor_table(data)),
                        ("Learning curves", curves_table(data)), ("Response types", response_table(analysis)),
                        ("Interventions", intervention_table(analysis)),
                        ("Unintentional triggers", unintentional_table(analysis))):  # fmt: skip
        print(f"{title}:\n\n{text}\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    s = sub.add_parser("save", help="copy a reproduction's small results")
    s.add_argument("results", type=Path)
    s.add_argument("out", type=Path)
    p = sub.add_parser("print", help="print the docs' tables from kept results")
    p.add_argument("data", type=Path)
    args = parser.parse_args()
    if args.command == "save":
        save(args.results, args.out)
    else:
        print_tables(args.data)


if __name__ == "__main__":
    main()
