"""Print Tables 1 and 2 over training seeds as the markdown table of docs/results.md.

    python scripts/tables_markdown.py results/paper/evaluation/summary.json

Each cell: mean ± sd over seeds (each seed's rate); ↑ when the paper's value lies below every seed's 95% interval,
↓ when above every one (``paper_outside_every_seed_interval`` in summary.json).
"""

from __future__ import annotations

import argparse
import json

COLUMNS = (("clean", "normal"), ("backdoor", "normal"), ("backdoor", "trojan"))
TITLES = ("clean, normal env", "backdoored, normal env", "backdoored, trojan env")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("summary", help="evaluation/summary.json of a reproduction")
    path = parser.parse_args().summary
    try:
        with open(path) as f:
            rows = json.load(f)
        cells = {(r["agent"], r["env"], r["config"]): r for r in rows}
    except (OSError, ValueError, TypeError, KeyError) as err:
        parser.error(f"cannot read {path!r} as a reproduction's evaluation/summary.json: {err}")
    configs = list(dict.fromkeys(r["config"] for r in rows))
    print("| grid | " + " | ".join(f"{t} | paper" for t in TITLES) + " |")
    print("|---|" + "---|---|" * len(COLUMNS))
    for config in configs:
        parts = []
        for agent, env in COLUMNS:
            r = cells.get((agent, env, config))
            if r is None:
                parts += ["", ""]
                continue
            arrow = ""
            if r["paper"] is not None and r["paper_outside_every_seed_interval"]:
                arrow = " ↑" if r["mean"] > r["paper"] else " ↓"
            seeds = ", ".join(f"{v:.3f}" for v in r["success"])
            paper = "" if r["paper"] is None else f"{r['paper']:.3f}"
            parts += [f"{r['mean']:.3f} ± {r['sd']:.3f} ({seeds}){arrow}", paper]
        print(f"| {config} | " + " | ".join(parts) + " |")


if __name__ == "__main__":
    main()
