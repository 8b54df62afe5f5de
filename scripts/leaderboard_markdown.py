"""Print a benchmark leaderboard (``seqtrojan zoo detect --out S``: ``S/leaderboard.json``) as a markdown table: per
detector and split, the models (poisoned), ROC-AUC with Newcombe's interval, cross-entropy and Brier score with
their bootstrap intervals. docs/benchmark.md's tables are this script's output; tests/test_docs_data.py checks it.

    python scripts/leaderboard_markdown.py docs/data/benchmark/leaderboard_smoke_300k.json
    python scripts/leaderboard_markdown.py docs/data/benchmark/leaderboard_minigrid_memory_attacks.json --by attack

``--by FACTOR``: the breakdown by one factor instead (``by_factor`` in the data; for ``attack``, each attack's
poisoned models against the split's clean ones), one row per detector, split and value, with ROC-AUC and
cross-entropy.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any


def short(metric: dict[str, Any]) -> str:
    if metric["value"] is None:
        return "n/a"
    if metric["low"] is None:
        return f"{metric['value']:.3f}"
    return f"{metric['value']:.3f} [{metric['low']:.2f}, {metric['high']:.2f}]"


def rows(board: dict[str, Any]) -> list[str]:
    out = [
        "| detector | split | models (poisoned) | ROC-AUC [Newcombe] | cross-entropy [bootstrap] | Brier [bootstrap] |",
        "|---|---|---|---|---|---|",
    ]
    for detector in board["detectors"]:
        for split in detector["splits"]:
            s = split["scores"]
            out.append(
                f"| {detector['detector']} | {split['split']} | {s['models']} ({s['poisoned']}) | "
                f"{short(s['roc_auc_newcombe'])} | {short(s['cross_entropy'])} | {short(s['brier'])} |"
            )
    return out


def factor_rows(board: dict[str, Any], factor: str) -> list[str]:
    out = [
        f"| detector | split | {factor} | models (poisoned) | ROC-AUC [Newcombe] | cross-entropy [bootstrap] |",
        "|---|---|---|---|---|---|",
    ]
    for detector in board["detectors"]:
        for split in detector["splits"]:
            for value, s in split.get("by_factor", {}).get(factor, {}).items():
                out.append(
                    f"| {detector['detector']} | {split['split']} | {value} | {s['models']} ({s['poisoned']}) | "
                    f"{short(s['roc_auc_newcombe'])} | {short(s['cross_entropy'])} |"
                )
    return out


def main() -> None:
    board = json.loads(Path(sys.argv[1]).read_text())
    if len(sys.argv) == 4 and sys.argv[2] == "--by":
        print("\n".join(factor_rows(board, sys.argv[3])))
        return
    print("\n".join(rows(board)))


if __name__ == "__main__":
    main()
