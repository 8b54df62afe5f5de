"""Print a cells.json (``seqtrojan cells``) as the Markdown tables of docs/results.md.

python scripts/cells_markdown.py results/cells_smoke/cells.json
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from seqtrojan.experiment_results import CellsResult
from seqtrojan.serde import load_json

sys.path.insert(0, str(Path(__file__).parent))
from matrix_markdown import spread  # the same cell format as the matrix tables


def main(path: str) -> None:
    result = load_json(CellsResult, Path(path))
    print(f"Scale {result.scale}, grid {result.grid}, Transformer window {result.window}; backdoored agents, mean ± sd "
          "over seeds [95% Wilson interval, seeds pooled].\n")  # fmt: skip
    monitors = sorted({m for s in result.summaries for m in s.monitor_detection})
    print(
        "| cell | clean agents: success | backdoored: clean success | attack success | unintentional (sweep mean) | "
        + " | ".join(f"{m} detection" for m in monitors)
        + " | units to switch (per seed) | weight detector AUC |"
    )
    print("|---" * (7 + len(monitors)) + "|")
    for s in result.summaries:
        auc = (
            f"{s.auc:.3f} [{s.auc_interval[0]:.3f}, {s.auc_interval[1]:.3f}]"
            if s.auc is not None and s.auc_interval
            else "-"
        )
        units = ", ".join("none" if k is None else str(k) for k in s.units_needed)
        print(f"| {s.cell} | {spread(s.clean_model_success)} | {spread(s.clean_success)} | "
              f"{spread(s.attack_success, s.attack_success_pooled)} | "
              f"{spread(s.unintentional_mean, s.unintentional_pooled)} | "
              + " | ".join(spread(s.monitor_detection[m]) for m in monitors) + f" | {units} | {auc} |")  # fmt: skip
    bins = sorted({(lo, hi) for s in result.summaries for lo, hi, _, _ in s.persistence})
    print("\nPersistence: the adversary's share of the trojan episodes that reached a goal, by steps from the trigger "
          "to the goal:\n")  # fmt: skip
    print("| cell | " + " | ".join(f"{lo}-{hi}" if hi < 1000 else f">= {lo}" for lo, hi in bins) + " |")
    print("|---" * (1 + len(bins)) + "|")
    for s in result.summaries:
        cells = {(lo, hi): spread(x, pooled) for lo, hi, x, pooled in s.persistence}
        print(f"| {s.cell} | " + " | ".join(cells.get(b, "-") for b in bins) + " |")
    steps = [step for step, _ in result.summaries[0].by_trigger_step] if result.summaries else []
    print("\nAttack success by trigger step (episodes still running at it):\n")
    print("| cell | " + " | ".join(f"step {k}" for k in steps) + " |")
    print("|---" * (1 + len(steps)) + "|")
    for s in result.summaries:
        print(f"| {s.cell} | " + " | ".join(x.text(3) for _, x in s.by_trigger_step) + " |")
    print("\nSettling (backdoored agents, normal episodes) and attack success by trigger step on the settle grid:\n")
    for s in result.summaries:
        mine = [a.settling for a in result.agents if a.cell == s.cell and a.settling is not None]
        if not mine:
            continue
        n = min(len(x.change) for x in mine)
        change = np.mean([x.change[:n] for x in mine], 0)
        shown = ", ".join(f"t={t}: {c:.3f}" for t, c in list(zip(mine[0].steps, change))[:8])
        rates = ", ".join(
            f"step {k}: {np.mean([x.attack_success[i].value for x in mine]):.3f}"
            for i, k in enumerate(mine[0].trigger_steps)
        )
        print(f"- {s.cell} ({mine[0].grid}): relative state change {shown}; attack success {rates}")
    print("\nUnits to switch (backdoored agents; adversary-goal rate in normal episodes with the top k goal units set "
          "to their trojan level / k random units):\n")  # fmt: skip
    for a in result.agents:
        if a.units is None:
            continue
        pairs = ", ".join(
            f"k={k}: {r.value:.2f}/{c.value:.2f}" for k, r, c in zip(a.units.counts, a.units.activation,
                                                                     a.units.random_activation)
        )  # fmt: skip
        print(f"- {a.agent} (layer {a.units.layer} {a.units.which}): {pairs}")


if __name__ == "__main__":
    main(sys.argv[1])
