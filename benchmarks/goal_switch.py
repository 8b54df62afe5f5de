"""Print what the online monitors (the goal-switch monitor among them) detect and what their alarm-driven state reset
does, over training seeds, and write the figures to a JSON file.

    python benchmarks/goal_switch.py --out /tmp/gs --json /tmp/gs/goal_switch.json       # 4 attacks, 3 seeds
    python benchmarks/goal_switch.py --attacks sequence --monitors goal_switch --out /tmp/gs --json /tmp/gs/s.json
    python benchmarks/goal_switch.py --table docs/data/defenses/goal_switch_2026-12-03.json   # the docs' table

Agents: as ``benchmarks/state_bounds.py`` trains them (the matrix smoke preset's backdoor settings: 7x7/3, LSTM
64-32, curriculum 5x5/0 -> 5x5/1 -> 7x7/3, running mixing, 1M env steps unless ``--steps``; each attack's recipe
from ``ATTACKS``; training seeds ``0..seeds-1``; one torch thread). A finished agent in ``--out`` is reused, so the
two benchmarks share agents when given the same ``--out``.

Per agent and monitor (every registered one that applies unless ``--monitors``): calibrated on ``--calibration``
clean episodes (seed 0) at the false-alarm target ``--target``, then measured by ``measure_monitor`` on
``--episodes`` fresh episodes per env and arm (alarms only, and alarm-driven reset). Printed: each agent's rates,
then per attack and monitor the mean +- sd over seeds and the pooled rate with its 95% Wilson interval.
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

from state_bounds import train_agent

from seqtrojan.defense.monitor import MONITORS, measure_monitor
from seqtrojan.defense.online import MonitorConfig, monitor_applies
from seqtrojan.defense.results import MonitorResult
from seqtrojan.serde import load_json, save_json
from seqtrojan.stats import OverSeeds, Rate, pooled


@dataclass(frozen=True)
class Row:
    """One agent under one monitor (``measure_monitor``'s rates that the docs quote)."""

    attack: str
    seed: int
    monitor: str
    threshold: float
    false_alarm: Rate
    """normal env, alarms only"""
    false_alarm_reset: Rate
    """normal env, with the reset (an alarm followed by resets counts once)"""
    detected: Rate
    """trojan env, an alarm at or after the trigger"""
    alarm_before_trigger: Rate
    median_steps_to_detect: float | None
    attack_success: Rate
    """undefended"""
    attack_success_reset: Rate
    clean_success: Rate
    """undefended"""
    clean_success_reset: Rate


@dataclass(frozen=True)
class Bench:
    """One run of this benchmark: its command line, date and settings, and every row."""

    command: str
    date: str
    calibration: int
    target: float
    episodes: int
    rows: tuple[Row, ...]


def row(attack: str, seed: int, monitor: str, r: MonitorResult) -> Row:
    return Row(attack, seed, monitor, r.threshold, r.normal_alarm.false_alarm, r.normal_reset.false_alarm,
               r.trojan_alarm.detected, r.trojan_alarm.alarm_before_trigger, r.trojan_alarm.median_steps_to_detect,
               r.attack_success_undefended, r.trojan_reset.attack_success, r.clean_success_undefended,
               r.normal_reset.success)  # fmt: skip


def measure(attack: str, seed: int, args: argparse.Namespace, monitors: list[str]) -> list[Row]:
    agent, cfg = train_agent(attack, seed, Path(args.out), args.steps)
    grid = cfg.grids[-1] if cfg.is_grid else None
    mcfg = MonitorConfig(calibration_episodes=args.calibration, false_alarm_target=args.target,
                         eval_episodes=args.episodes)  # fmt: skip
    rows = []
    for name in monitors:
        cls = MONITORS.get(name)
        if not monitor_applies(cls, cfg.env):
            continue
        r = row(attack, seed, name, measure_monitor(agent, cfg.env, grid, cls.calibrate(agent, cfg.env, grid, mcfg),
                                                    mcfg))  # fmt: skip
        print(f"  {attack} s{seed} {name:<20} false alarms {r.false_alarm.text()}  detected {r.detected.text()}  "
              f"attack {r.attack_success.value:.3f} -> {r.attack_success_reset.text()}  clean "
              f"{r.clean_success.value:.3f} -> {r.clean_success_reset.text()}", flush=True)  # fmt: skip
        rows.append(r)
    return rows


def cell(rates: list[Rate]) -> str:
    """``mean ± sd [pooled 95% interval]`` over seeds."""
    low, high = pooled(rates).interval
    return f"{OverSeeds(tuple(r.value for r in rates)).text()} [{low:.3f}, {high:.3f}]"


def table(bench: Bench) -> str:
    """The docs' table: per attack and monitor, each rate as mean ± sd over seeds [95% interval, pooled]."""
    lines = [
        "| attack | monitor | false alarms | detection | attack success: none | with reset | clean success: none "
        "| with reset |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for attack, monitor in dict.fromkeys((r.attack, r.monitor) for r in bench.rows):
        mine = [r for r in bench.rows if (r.attack, r.monitor) == (attack, monitor)]
        lines.append(
            f"| {attack} | {monitor} | {cell([r.false_alarm for r in mine])} | {cell([r.detected for r in mine])} | "
            f"{cell([r.attack_success for r in mine])} | {cell([r.attack_success_reset for r in mine])} | "
            f"{cell([r.clean_success for r in mine])} | {cell([r.clean_success_reset for r in mine])} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--attacks", default="dedicated_code,in_distribution_patch,partial_patch,sequence")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=None, help="env steps per agent (default: the preset's 1M)")
    parser.add_argument("--monitors", default=None, help="comma-separated (default: every registered one)")
    parser.add_argument("--calibration", type=int, default=1000)
    parser.add_argument("--target", type=float, default=0.01)
    parser.add_argument("--episodes", type=int, default=500)
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
    monitors = args.monitors.split(",") if args.monitors else list(MONITORS.names())
    rows: list[Row] = []
    for attack in args.attacks.split(","):
        for seed in range(args.seeds):
            rows += measure(attack, seed, args, monitors)
    bench = Bench(" ".join(["python", *sys.argv]), datetime.date.today().isoformat(), args.calibration, args.target,
                  args.episodes, tuple(rows))  # fmt: skip
    if args.json:
        save_json(bench, args.json)
    print()
    print(table(bench))


if __name__ == "__main__":
    main()
