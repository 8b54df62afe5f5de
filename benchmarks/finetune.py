"""Print what clean fine-tuning and fine-pruning do to attack success and clean success, over training seeds, for
attackers who know fine-tuning, and write the figures to a JSON file.

    python benchmarks/finetune.py --out /tmp/ft --json /tmp/ft/finetune.json      # sequence vs finetune_resistant
    python benchmarks/finetune.py --attacks ewc/1,ewc/10 --out /tmp/ft --json /tmp/ft/ewc.json
    python benchmarks/finetune.py --table docs/data/defenses/finetune_2026-12-03.json     # the docs' table

Agents: as ``benchmarks/state_bounds.py`` trains them (the matrix smoke preset's backdoor settings: 7x7/3, LSTM
64-32, curriculum 5x5/0 -> 5x5/1 -> 7x7/3, running mixing, 1M env steps unless ``--steps``; each attack's recipe
from ``ATTACKS``; training seeds ``0..seeds-1``; one torch thread). ``finetune_resistant/W`` is that recipe with
``attack.finetune_resistance.weight`` W, ``ewc/W`` the EWC recipe with weight W (from the clean agent of the same
seed, trained first into ``--out``). A finished agent in ``--out`` is reused, and so is a finished fine-tune, so the
benchmarks share agents when given the same ``--out``.

Per agent: the registered ``fine_tuning`` and ``fine_pruning`` mitigations (``MITIGATIONS``, as the matrix runs
them) with the matrix smoke preset's ``mitigation:`` settings (100k clean fine-tuning env steps, 100 calibration
episodes for fine-pruning's ranking, 300 fresh episodes per env and arm, the same episodes for every arm; seed 0);
``--finetune-steps`` and ``--episodes`` change them. Each arm's attack success (adversary's goal, trojan env) and
clean success (user's goal, normal env) is a ``Rate`` with its 95% Wilson interval; the table gives per attack and
arm the mean ± sd over seeds [the pooled rate's 95% interval].
"""

from __future__ import annotations

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
import argparse
import dataclasses
import datetime
import sys
from dataclasses import dataclass
from pathlib import Path

from goal_switch import cell
from state_bounds import train_agent

from seqtrojan.defense.mitigation import MITIGATIONS, MitigationConfig, MitigationContext
from seqtrojan.experiments.matrix import load_matrix_config
from seqtrojan.serde import load_json, save_json
from seqtrojan.stats import Rate

ARMS = ("none", "fine_tuning", "fine_pruning")
"""no mitigation, then each registered mitigation measured (its last row: fine-pruning's pruned and fine-tuned agent)"""


@dataclass(frozen=True)
class Row:
    """One agent under one arm."""

    attack: str
    seed: int
    arm: str
    attack_success: Rate
    clean_success: Rate


@dataclass(frozen=True)
class Bench:
    """One run of this benchmark: its command line, date and settings, and every row."""

    command: str
    date: str
    finetune_steps: int
    episodes: int
    rows: tuple[Row, ...]


def measure(attack: str, seed: int, args: argparse.Namespace, mcfg: MitigationConfig) -> list[Row]:
    agent, cfg = train_agent(attack, seed, Path(args.out), args.steps)
    # a finished fine-tune is reused by its folder alone (train_or_resume): the folder names its length
    work = Path(args.out) / "mitigation" / f"ft{mcfg.finetune_steps}" / cfg.run.name
    ctx = MitigationContext(agent, cfg, cfg.grids[-1], mcfg, work)
    before = ctx.measure(agent, "no mitigation")
    rows = [Row(attack, seed, "none", before.attack_success, before.clean_success)]
    for name in ARMS[1:]:
        arms = MITIGATIONS.get(name)(ctx)
        last = list(arms.values())[-1]  # the whole mitigation, as the matrix keeps it
        rows.append(Row(attack, seed, name, last.attack_success, last.clean_success))
    for r in rows:
        print(f"  {attack} s{seed} {r.arm:<13} attack {r.attack_success.text()}  clean {r.clean_success.text()}",
              flush=True)  # fmt: skip
    return rows


def table(bench: Bench) -> str:
    """The docs' table: per attack, attack and clean success with no mitigation and after each, as mean ± sd over
    seeds [95% interval, pooled]."""
    lines = [
        "| attack | seeds | attack success: none | fine-tuned | fine-pruned | clean success: none | fine-tuned "
        "| fine-pruned |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for attack in dict.fromkeys(r.attack for r in bench.rows):
        by_arm = {arm: [r for r in bench.rows if (r.attack, r.arm) == (attack, arm)] for arm in ARMS}
        seeds = len(by_arm["none"])
        attack_cells = " | ".join(cell([r.attack_success for r in by_arm[arm]]) for arm in ARMS)
        clean_cells = " | ".join(cell([r.clean_success for r in by_arm[arm]]) for arm in ARMS)
        lines.append(f"| {attack} | {seeds} | {attack_cells} | {clean_cells} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--attacks", default="sequence,finetune_resistant/0.3,finetune_resistant/1,"
                        "finetune_resistant/3")  # fmt: skip
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=None, help="env steps per agent (default: the preset's 1M)")
    parser.add_argument("--finetune-steps", type=int, default=None, help="default: the matrix smoke preset's")
    parser.add_argument("--episodes", type=int, default=None, help="per env and arm (default: the preset's)")
    parser.add_argument("--out", help="folder of the trained agents and fine-tunes (reused when finished)")
    parser.add_argument("--json", help="write every row here")
    parser.add_argument("--table", metavar="JSON", help="only print the table of a written JSON file")
    args = parser.parse_args()
    if args.table:
        print(table(load_json(Bench, args.table)))
        return
    if not args.out:
        parser.error("--out is required (unless --table)")
    torch.set_num_threads(1)
    mcfg = load_matrix_config("smoke").mitigation
    changes = {"finetune_steps": args.finetune_steps, "eval_episodes": args.episodes}
    mcfg = dataclasses.replace(mcfg, **{k: v for k, v in changes.items() if v is not None})
    rows: list[Row] = []
    for attack in args.attacks.split(","):
        for seed in range(args.seeds):
            rows += measure(attack, seed, args, mcfg)
    bench = Bench(" ".join(["python", *sys.argv]), datetime.date.today().isoformat(), mcfg.finetune_steps,
                  mcfg.eval_episodes, tuple(rows))  # fmt: skip
    if args.json:
        save_json(bench, args.json)
    print()
    print(table(bench))


if __name__ == "__main__":
    main()
