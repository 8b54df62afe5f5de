"""Clean and backdoored agents on other people's POMDPs (POPGym, MinAtar), over training seeds, measured alike.

    python benchmarks/families.py --presets popgym_repeat_previous popgym_repeat_first popgym_count_recall \
        --seeds 3 --out runs/families --json docs/data/families/popgym.json

For every preset and seed: the backdoored agent (the preset as shipped) and a clean agent trained with the same
settings (``backdoor.enabled: false``: its env still has the trigger, at probability 0, so its unintended response
is measured too), ``--steps`` env steps each (default: the preset's). Each model is then measured by the evaluation
``seqtrojan evaluate`` runs (:func:`seqtrojan.evaluation.env_report.evaluate_model`, ``--episodes`` per episode
type): clean return, trojan success, the target-action share after the trigger and action persistence
(``--roles`` picks the agents: both by default). With ``--defend N`` every backdoored model also goes through
``seqtrojan defend`` (``run_defense``: the per-unit state monitor calibrated on N clean episodes at a 1%
false-alarm target and measured on N fresh episodes per type, then the mitigations with ``--finetune-steps`` of
clean fine-tuning): its false alarms, detection and attack success with resets, and each mitigation's attack and
clean success. A finished run is kept and not retrained (delete its folder to redo it); a stopped one is trained
again from its start. Printed: per preset, each figure's mean and standard deviation over seeds and each seed's
value; ``--json`` writes them all, and ``--table JSON`` prints a written file as the markdown tables of
docs/families.md.

``--random`` also measures, by the same evaluation on the same episodes, the preset's network with a zero policy
head: every action equally likely, a uniform random policy (the baseline a short run must beat; the table's
``random`` row, one measurement).
``--final-eval-episodes N`` sets the training run's own final evaluation (``run.eval_episodes``; 0: none, since
the evaluation above is the one reported; on Atari an untrained greedy policy that never presses FIRE plays to the
episode cap).
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
from pathlib import Path
from typing import Any

import torch

from seqtrojan.agent.card import Architecture
from seqtrojan.agent.checkpoint import build_agent, load_agent
from seqtrojan.config import ExperimentConfig
from seqtrojan.evaluation.env_report import EnvEvaluationReport, evaluate_model
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml, to_dict
from seqtrojan.train.trainer import train
from seqtrojan.world import env_spec

HORIZONS = (0, 10, 20, 40)


def experiment(
    preset: str, seed: int, clean: bool, steps: int | None, out: Path, final_eval: int | None = None
) -> ExperimentConfig:
    data = load_yaml(resolve_preset(preset))
    role = "clean" if clean else "backdoor"
    data["run"] = {**data.get("run", {}), "out_dir": str(out), "name": f"{preset}_{role}_s{seed}", "seed": seed,
                   "progress": False, "checkpoint_every": 10**9}  # fmt: skip
    if final_eval is not None:
        data["run"]["eval_episodes"] = final_eval
    if steps is not None:
        data["ppo"]["total_steps"] = steps
    if clean:
        data["backdoor"] = {"enabled": False}
    return from_dict(ExperimentConfig, data, "")


def model_report(cfg: ExperimentConfig, episodes: int) -> EnvEvaluationReport:
    model = Path(cfg.run.out_dir) / cfg.run.name / "model"
    if not (model / "card.json").is_file():
        shutil.rmtree(model.parent, ignore_errors=True)  # a stopped run (no checkpoints kept) starts again
        train(cfg)
    agent, saved, card = load_agent(model)
    return evaluate_model(
        agent, saved, model=str(model), label=str(card.get("label", "")), episodes=episodes, seed=12345,
        horizons=HORIZONS,
    )  # fmt: skip


def defend(cfg: ExperimentConfig, episodes: int, finetune_steps: int) -> dict[str, float]:
    """``seqtrojan defend`` on the run's model: the monitor's and the mitigations' figures."""
    from seqtrojan.defense.mitigation import MitigationConfig
    from seqtrojan.defense.online import MonitorConfig
    from seqtrojan.defense.pipeline import DefenseConfig, run_defense

    run = Path(cfg.run.out_dir) / cfg.run.name
    config = DefenseConfig(
        monitor=MonitorConfig(calibration_episodes=episodes, eval_episodes=episodes, false_alarm_target=0.01),
        mitigation=MitigationConfig(finetune_steps=finetune_steps, calibration_episodes=100, eval_episodes=episodes),
        oracle_episodes=100,
    )  # fmt: skip
    result = run_defense(run / "model", run / "defense", config, log=lambda *_: None)
    mon = result.monitor
    out = {
        "monitor_false_alarm": mon.normal_alarm.false_alarm.value, "monitor_detection": mon.trojan_alarm.detected.value,
        "attack_success_undefended": mon.attack_success_undefended.value,
        "attack_success_with_resets": mon.trojan_reset.attack_success.value,
    }  # fmt: skip
    for name, arm in result.mitigation.items():
        out[f"{name}_attack"], out[f"{name}_clean"] = arm.attack_success.value, arm.clean_success.value
    return out


def random_report(preset: str, episodes: int) -> EnvEvaluationReport:
    """The preset's network with a zero policy head (every action equally likely: a uniform random policy),
    measured as :func:`model_report` measures a trained one."""
    cfg = from_dict(ExperimentConfig, load_yaml(resolve_preset(preset)), "")
    spec = env_spec(cfg.env)
    agent = build_agent(cfg, Architecture.of_config(cfg, spec.obs_dim, spec.num_actions, spec.image))
    with torch.no_grad():
        agent.policy_head.weight.zero_()
        agent.policy_head.bias.zero_()
    return evaluate_model(agent.eval(), cfg, model="uniform random", label="clean", episodes=episodes, seed=12345,
                          horizons=HORIZONS)  # fmt: skip


def figures(report: EnvEvaluationReport) -> dict[str, float | None]:
    persistence = {  # None where no trojan episode lasted that long (Breakout's ball is soon lost)
        f"action_persistence_k{p.horizon}": p.adversary.value if p.adversary.n else None
        for p in report.action_persistence
    }
    return {
        "clean_return": report.clean_return.mean if report.clean_return else None,
        "clean_success": report.clean_success.value,
        "clean_reached_adversary": report.clean_reached_adversary.value,
        "trojan_success": report.trojan_success.value if report.trojan_success else None,
        "trojan_env_return": report.trojan_env_return.mean if report.trojan_env_return else None,
        "target_share": report.target_share.mean if report.target_share else None,
        "clean_target_share": report.clean_target_share.mean if report.clean_target_share else None,
        **persistence,
    }


def summary(values: list[float | None]) -> dict[str, Any]:
    kept = [v for v in values if v is not None]
    if not kept:
        return {"mean": None, "sd": None, "values": values}
    sd = statistics.stdev(kept) if len(kept) > 1 else 0.0
    return {"mean": statistics.fmean(kept), "sd": sd, "values": values}


def _cell(summary: dict[str, Any] | None, spread: bool = True) -> str:
    """A table cell: a figure's mean ± sd over seeds (its mean alone without ``spread``), n/a where it has none."""
    if summary is None or summary["mean"] is None:
        return "n/a"
    return f"{summary['mean']:.3f} ± {summary['sd']:.3f}" if spread else f"{summary['mean']:.3f}"


TABLE = (
    ("clean return", "clean_return"), ("clean success", "clean_success"),
    ("normal episodes switched", "clean_reached_adversary"), ("target share after the trigger", "target_share"),
    ("target share, normal episodes", "clean_target_share"), ("trojan success", "trojan_success"),
    ("action persistence k=10", "action_persistence_k10"), ("action persistence k=40", "action_persistence_k40"),
    ("env's return, trojan episodes", "trojan_env_return"),
)  # fmt: skip
"""the table's columns: heading and figure"""


def table(results: dict[str, Any]) -> list[str]:
    """The markdown table of a ``--json`` file: per preset and agent, each figure's mean ± sd over seeds, and each
    seed's clean return and trojan success."""
    headings = " | ".join(h for h, _ in TABLE)
    out = [
        f"| preset | agent | env steps | {headings} | per seed: clean return; trojan success |",
        "|---|---|---|" + "---|" * len(TABLE) + "---|",
    ]
    for preset, entry in results["presets"].items():
        for role in ("clean", "backdoored", "random"):
            if role not in entry:
                continue
            agent = entry[role]
            # the random policy is one measurement, not a spread over seeds
            cells = [_cell(agent["over_seeds"].get(name), spread=role != "random") for _, name in TABLE]
            seeds = "; ".join(
                f"{s['figures']['clean_return']:.3f}, {s['figures']['trojan_success']:.3f}" for s in agent["seeds"]
            )
            out.append(f"| {preset} | {role} | {agent['env_steps']:,} | " + " | ".join(cells) + f" | {seeds} |")
    return out


DEFENSE_TABLE = (
    ("monitor false alarms", "monitor_false_alarm"), ("monitor detection", "monitor_detection"),
    ("attack success", "attack_success_undefended"), ("with the monitor's resets", "attack_success_with_resets"),
    ("fine-tuned: attack", "fine_tuned_attack"), ("fine-tuned: clean", "fine_tuned_clean"),
    ("state bounds: attack", "state_bounds_attack"), ("state bounds: clean", "state_bounds_clean"),
    ("oracle unit reset: attack", "reset_goal_units_oracle_attack"),
)  # fmt: skip
"""the defense table's columns: heading and figure (``--defend``)"""


def defense_table(results: dict[str, Any]) -> list[str]:
    """The markdown table of ``--defend``'s figures: per preset, each one's mean ± sd over the backdoored seeds."""
    headings = " | ".join(h for h, _ in DEFENSE_TABLE)
    out = [f"| preset | {headings} |", "|---|" + "---|" * len(DEFENSE_TABLE)]
    for preset, entry in results["presets"].items():
        over = entry.get("backdoored", {}).get("defense_over_seeds")  # a --roles clean run has none
        if over is None:
            continue
        cells = [_cell(over.get(name)) for _, name in DEFENSE_TABLE]
        out.append(f"| {preset} | " + " | ".join(cells) + " |")
    return out if len(out) > 2 else []


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--table", type=Path, default=None, help="print this --json file as a markdown table")
    parser.add_argument("--presets", nargs="+", default=[])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=None, help="env steps per agent (default: the preset's)")
    parser.add_argument("--episodes", type=int, default=500, help="evaluation episodes per episode type")
    parser.add_argument("--out", type=Path, default=Path("runs/families"))
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--defend", type=int, default=0, help="monitor episodes of seqtrojan defend (0: none)")
    parser.add_argument("--finetune-steps", type=int, default=65536, help="clean fine-tuning steps of --defend")
    parser.add_argument("--roles", nargs="+", choices=("backdoored", "clean"), default=["backdoored", "clean"],
                        help="which agents to train and measure (default: both)")  # fmt: skip
    parser.add_argument("--random", action="store_true", help="also measure a uniform random policy")
    parser.add_argument("--final-eval-episodes", type=int, default=None,
                        help="run.eval_episodes of each training run (default: the preset's; 0: none)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.table is not None:
        results = json.loads(args.table.read_text())
        print("\n".join(table(results)))
        defended = defense_table(results)
        if defended:
            print("\n" + "\n".join(defended))
        return
    if not args.presets:
        parser.error("--presets is required (or --table JSON)")
    results: dict[str, Any] = {"command": " ".join(["python", "benchmarks/families.py", *sys.argv[1:]]),
                               "episodes": args.episodes, "seeds": args.seeds, "presets": {}}  # fmt: skip
    for preset in args.presets:
        entry: dict[str, Any] = {}
        for role, clean in (("backdoored", False), ("clean", True)):
            if role not in args.roles:
                continue
            per_seed = []
            for seed in range(args.seeds):
                cfg = experiment(preset, seed, clean, args.steps, args.out, args.final_eval_episodes)
                report = model_report(cfg, args.episodes)
                measured = {"seed": seed, "figures": figures(report), "report": to_dict(report)}
                if args.defend and not clean:
                    measured["defense"] = defend(cfg, args.defend, args.finetune_steps)
                    print(f"{preset} seed {seed} defended: {measured['defense']}", flush=True)
                per_seed.append(measured)
                print(f"{preset} {role} seed {seed}: " + ", ".join(
                    f"{k} {v:.3f}" for k, v in figures(report).items() if v is not None), flush=True)  # fmt: skip
            names = per_seed[0]["figures"].keys()
            entry[role] = {
                "env_steps": cfg.ppo.total_steps,
                "over_seeds": {n: summary([s["figures"][n] for s in per_seed]) for n in names},
                "seeds": per_seed,
            }
            if "defense" in per_seed[0]:
                entry[role]["defense_over_seeds"] = {
                    n: summary([s["defense"].get(n) for s in per_seed]) for n in per_seed[0]["defense"]
                }
        if args.random:
            report = random_report(preset, args.episodes)
            print(f"{preset} uniform random: " + ", ".join(
                f"{k} {v:.3f}" for k, v in figures(report).items() if v is not None), flush=True)  # fmt: skip
            entry["random"] = {
                "env_steps": 0,
                "over_seeds": {n: summary([v]) for n, v in figures(report).items()},
                "seeds": [{"seed": None, "figures": figures(report), "report": to_dict(report)}],
            }
        results["presets"][preset] = entry
        for role in args.roles:
            line = ", ".join(
                f"{n} {s['mean']:.3f} ± {s['sd']:.3f}"
                for n, s in entry[role]["over_seeds"].items()
                if s["mean"] is not None
            )
            print(f"== {preset} {role} over {args.seeds} seeds: {line}", flush=True)
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
