"""Print how well the behaviour detector separates each attack's agents from clean agents, beside each attack's
success, over training seeds, and write the figures to a JSON file: the attacker who knows the detector's search
(``search_decoys``, at several decoy shares) against the attacks it was not built for.

    python benchmarks/behaviour_evasion.py --out /tmp/be --json /tmp/be/behaviour_evasion.json
    python benchmarks/behaviour_evasion.py --attacks sequence,search_decoys/0.6 --seeds 5 --out /tmp/be
    python benchmarks/behaviour_evasion.py --table docs/data/defenses/behaviour_evasion_2026-12-03.json

Agents: as ``benchmarks/state_bounds.py`` trains them (the matrix smoke preset: 7x7/3, LSTM 64-32, curriculum,
1M env steps unless ``--steps``; each attack's recipe from ``ATTACKS``, ``recipe/value`` its knob at that value;
training seeds ``0..seeds-1``; one torch thread), and the preset's clean agents of the same seeds. A finished agent
in ``--out`` is reused.

Per agent: the registered ``behaviour_detector``'s score (its default settings: 200 normal episodes per candidate,
6 whole-view and 24 random one-step patches; the largest rise of adversary-goal episodes over no patch), clean
success and attack success on ``--episodes`` fresh episodes. Per attack: the ROC-AUC of its agents' scores against
the clean agents' with its 95% interval, and the rates as mean +- sd over seeds [pooled 95% Wilson interval].
"""

from __future__ import annotations

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
import argparse
import datetime
import sys
from dataclasses import dataclass
from pathlib import Path

from goal_switch import cell
from state_bounds import rates, train_agent, train_clean

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.defense.behaviour import BehaviourConfig, behaviour_score, scores_auc
from seqtrojan.serde import load_json, save_json
from seqtrojan.stats import OverSeeds, Rate


@dataclass(frozen=True)
class Row:
    """One agent: its behaviour score and its rates (``attack`` is ``clean`` for a clean agent)."""

    attack: str
    seed: int
    score: float
    """the detector's score: the largest rise of adversary-goal episodes over the no-patch baseline"""
    best: str
    """the candidate patch with that rise"""
    clean_success: Rate
    attack_success: Rate
    """trojan env, the adversary's goal (a clean agent's: how often it goes there anyway)"""


@dataclass(frozen=True)
class Bench:
    command: str
    date: str
    episodes: int
    detector_episodes: int
    rows: tuple[Row, ...]


def measure(attack: str, seed: int, args: argparse.Namespace) -> Row:
    if attack == "clean":
        agent, cfg, _ = load_agent(train_clean(seed, Path(args.out), args.steps))
        agent = agent.eval()
    else:
        agent, cfg = train_agent(attack, seed, Path(args.out), args.steps)
    grid = cfg.grids[-1]
    result = behaviour_score(agent, cfg.grid_env, grid, BehaviourConfig(episodes=args.detector_episodes))
    clean, attacked = rates(agent, cfg, args.episodes, None)
    print(f"  {attack} s{seed}: score {result.score:+.3f} ({result.best})  clean {clean.text()}  attack "
          f"{attacked.text()}", flush=True)  # fmt: skip
    return Row(attack, seed, result.score, result.best, clean, attacked)


def table(bench: Bench) -> str:
    """The docs' table: per attack, the detector's AUC against the clean agents and the rates over seeds."""
    clean = [r for r in bench.rows if r.attack == "clean"]
    lines = [
        "| attack | agents | behaviour score (mean ± sd) | ROC-AUC vs clean [95%] | attack success | clean success |",
        "|---|---|---|---|---|---|",
    ]
    for attack in dict.fromkeys(r.attack for r in bench.rows):
        mine = [r for r in bench.rows if r.attack == attack]
        scores = OverSeeds(tuple(r.score for r in mine)).text()
        if attack == "clean":
            auc = "—"
        else:
            a = scores_auc([r.score for r in mine + clean], [1] * len(mine) + [0] * len(clean))
            auc = f"{a.auc:.3f} [{a.interval[0]:.3f}, {a.interval[1]:.3f}]"
        lines.append(f"| {attack} | {len(mine)} | {scores} | {auc} | {cell([r.attack_success for r in mine])} | "
                     f"{cell([r.clean_success for r in mine])} |")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--attacks", default="sequence,search_decoys/0.1,search_decoys/0.3,search_decoys/0.6")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=None, help="env steps per agent (default: the preset's 1M)")
    parser.add_argument("--episodes", type=int, default=500, help="fresh episodes per env for the success rates")
    parser.add_argument("--detector-episodes", type=int, default=200, help="normal episodes per candidate patch")
    parser.add_argument("--out", help="folder of the trained agents (reused when finished)")
    parser.add_argument("--json", help="write every row here")
    parser.add_argument("--table", metavar="JSON", help="only print the table of a written JSON file")
    args = parser.parse_args()
    if args.table:
        print(table(load_json(Bench, args.table)))
        return
    if not args.out:
        parser.error("--out is required (unless --table)")
    torch.set_num_threads(1)
    rows = [measure(attack, seed, args) for attack in ["clean", *args.attacks.split(",")] for seed in range(args.seeds)]
    bench = Bench(" ".join(["python", *sys.argv]), datetime.date.today().isoformat(), args.episodes,
                  args.detector_episodes, tuple(rows))  # fmt: skip
    if args.json:
        save_json(bench, args.json)
    print()
    print(table(bench))


if __name__ == "__main__":
    main()
