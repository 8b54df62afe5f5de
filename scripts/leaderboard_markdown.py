"""Print a benchmark leaderboard (``seqtrojan zoo detect --out S``: ``S/leaderboard.json``) as a markdown table: per
detector and split, the models (poisoned), ROC-AUC with Newcombe's interval, cross-entropy and Brier score with
their bootstrap intervals. docs/benchmark.md's tables are this script's output; tests/test_docs_data.py checks it.

    python scripts/leaderboard_markdown.py docs/data/benchmark/leaderboard_smoke_300k.json
    python scripts/leaderboard_markdown.py docs/data/benchmark/leaderboard_minigrid_memory_attacks.json --by attack \
        --detectors state_probe,trigger_reconstruction

``--by FACTOR``: the breakdown by one factor instead (``by_factor`` in the data; for ``attack``, each attack's
poisoned models against the split's clean ones), one row per detector, split and value, with ROC-AUC and
cross-entropy. ``--detectors A,B``: only those detectors' rows.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def short(metric: dict[str, Any]) -> str:
    if metric["value"] is None:
        return "n/a"
    if metric["low"] is None:
        return f"{metric['value']:.3f}"
    return f"{metric['value']:.3f} [{metric['low']:.2f}, {metric['high']:.2f}]"


def rows(detectors: list[dict[str, Any]]) -> list[str]:
    out = [
        "| detector | split | models (poisoned) | ROC-AUC [Newcombe] | cross-entropy [bootstrap] | Brier [bootstrap] |",
        "|---|---|---|---|---|---|",
    ]
    for detector in detectors:
        for split in detector["splits"]:
            s = split["scores"]
            out.append(
                f"| {detector['detector']} | {split['split']} | {s['models']} ({s['poisoned']}) | "
                f"{short(s['roc_auc_newcombe'])} | {short(s['cross_entropy'])} | {short(s['brier'])} |"
            )
    return out


def factor_rows(detectors: list[dict[str, Any]], factor: str) -> list[str]:
    out = [
        f"| detector | split | {factor} | models (poisoned) | ROC-AUC [Newcombe] | cross-entropy [bootstrap] |",
        "|---|---|---|---|---|---|",
    ]
    for detector in detectors:
        for split in detector["splits"]:
            for value, s in split.get("by_factor", {}).get(factor, {}).items():
                out.append(
                    f"| {detector['detector']} | {split['split']} | {value} | {s['models']} ({s['poisoned']}) | "
                    f"{short(s['roc_auc_newcombe'])} | {short(s['cross_entropy'])} |"
                )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("leaderboard", type=Path, help="a leaderboard.json written by seqtrojan zoo detect --out")
    parser.add_argument("--by", metavar="FACTOR", help="the breakdown by one factor (env, cell, attack, ...)")
    parser.add_argument("--detectors", metavar="A,B", help="only these detectors' rows (default: all)")
    args = parser.parse_args()
    detectors = json.loads(args.leaderboard.read_text())["detectors"]
    if args.detectors:
        wanted = args.detectors.split(",")
        unknown = sorted(set(wanted) - {d["detector"] for d in detectors})
        if unknown:
            raise SystemExit(f"{args.leaderboard} has no detector {unknown[0]!r}")
        detectors = [d for d in detectors if d["detector"] in wanted]
    if args.by:
        factors = {f for d in detectors for split in d["splits"] for f in split.get("by_factor", {})}
        if args.by not in factors:
            known = ", ".join(sorted(factors))
            raise SystemExit(f"{args.leaderboard} has no breakdown by {args.by!r}; it has: {known}")
    print("\n".join(factor_rows(detectors, args.by) if args.by else rows(detectors)))


if __name__ == "__main__":
    main()
