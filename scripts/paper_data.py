"""Keep a paper-scale reproduction's small results under docs/data, and print docs/results.md's tables from them.

    python scripts/paper_data.py save results/paper_v4 docs/data/paper     # after `seqtrojan reproduce --scale paper`
    python scripts/paper_data.py print docs/data/paper                      # the tables of docs/results.md

``save`` copies what the tables read (a few hundred KB): ``evaluation/summary.json`` (Tables 1 and 2 over seeds),
``zoo/detection.json``, ``tradeoff/tradeoff.json``, ``defense/defense.json`` and ``timings.json``, and writes
``training.json``: each headline agent's end-of-training success (its model card's metrics). ``print`` prints the
training table, Tables 1 and 2 (``scripts/tables_markdown.py``'s format), the trade-off table and the monitor table;
``tests/test_docs_data.py`` checks that docs/results.md holds them as printed.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

from seqtrojan.stats import OverSeeds

KEPT = (
    "evaluation/summary.json", "tradeoff/tradeoff.json", "defense/defense.json", "zoo/detection.json", "timings.json",
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


def print_tables(data: Path) -> None:
    script = str(Path(__file__).parent / "tables_markdown.py")
    summary = str(data / "evaluation" / "summary.json")
    tables = subprocess.run([sys.executable, script, summary], capture_output=True, text=True, check=True)
    for title, text in (("Training", training_table(data)), ("Tables 1 and 2", tables.stdout.rstrip("\n")),
                        ("Trade-off", tradeoff_table(data)), ("Monitor", monitor_table(data))):  # fmt: skip
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
