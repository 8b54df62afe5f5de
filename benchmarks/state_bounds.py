"""Print what the ``state_bounds`` mitigation does to attack success and clean success, over training seeds.

    python benchmarks/state_bounds.py --out /tmp/sb                     # in_distribution_patch, 3 seeds, smoke scale
    python benchmarks/state_bounds.py --attacks in_distribution_patch,sequence,dedicated_code --out /tmp/sb
    python benchmarks/state_bounds.py --steps 500000 --settings 0,0.01,0.05,0.01/0/c --out /tmp/sb
    python benchmarks/state_bounds.py --attacks state_camouflage/1.0,state_camouflage/0.5 --out /tmp/sb  # adaptive

Agents: the matrix smoke preset's backdoor settings (7x7/3, LSTM 64-32, curriculum 5x5/0 -> 5x5/1 -> 7x7/3, running
mixing, 1M env steps unless ``--steps``), each attack's recipe from ``ATTACKS``, training seeds ``0..seeds-1``
(added to the preset's seed, as the matrix does), one torch thread. A finished agent in ``--out`` is reused.

Per agent: bounds fitted on ``--calibration`` clean (normal-env) episodes (seed 0), then ``--episodes`` fresh
episodes (seed 1000003) per env without a defense and with each setting; the same episodes for every arm. A setting
is ``quantile[/margin[/parts]]`` (parts: ``hc``, ``h`` or ``c``). An attack ``state_camouflage/M`` is the
registered monitor-aware recipe (weight 5) with the |z| margin ``M`` instead of 2.5: the attacker who knows the
bounds keeps the trojan states within M clean sd of the clean mean (about the central 68% of a unit's clean range
at M = 1, where ``state_bounds`` keeps the central 90% at its default q = 0.05). ``mahalanobis_camouflage/W`` is that
recipe with weight ``W``: any adaptive recipe written ``recipe/value`` is trained with its registered knob
(``Attack.knob``, ``seqtrojan attacks``) at that value (``finetune_resistant/W``, ``ewc/W``, ``search_decoys/P``);
``in_distribution_patch+mahalanobis_camouflage/W`` the same with the first recipe's
trigger (an adaptive recipe changes only the training terms). A recipe that starts from a clean agent
(``from_clean``, ``switch_camouflage``, ``ewc``) starts from the smoke preset's clean agent of the same training seed,
trained first into ``--out`` (``clean_s<seed>``), as the matrix does. Printed: each seed's rates, then
per attack and arm the mean +- sd over seeds and the pooled rate with its 95% Wilson interval.
"""

from __future__ import annotations

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import torch

# isort: on
import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.state import Intervention
from seqtrojan.config import ExperimentConfig
from seqtrojan.defense.state_bounds import StateBoundsConfig, clean_trace, fit_trace
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.experiments.attacks import ATTACKS, KnobbedAttack, resolve_attack
from seqtrojan.experiments.matrix import load_matrix_config
from seqtrojan.experiments.specs import experiment_from_spec
from seqtrojan.stats import OverSeeds, Rate, pooled
from seqtrojan.train.trainer import train_or_resume

EVAL_SEED = 1_000_003


@dataclass(frozen=True)
class Arm:
    """One agent under one arm (no defense, or one state-bounds setting)."""

    attack: str
    seed: int
    arm: str
    clean_success: Rate
    attack_success: Rate


def parse_setting(text: str) -> StateBoundsConfig:
    given = text.split("/")
    quantile, margin, parts = given + ["0", "hc"][len(given) - 1 :]
    return StateBoundsConfig(quantile=float(quantile), margin=float(margin), parts=tuple(parts))


def setting_name(cfg: StateBoundsConfig) -> str:
    return f"q={cfg.quantile:g} m={cfg.margin:g} {''.join(cfg.parts)}"


def train_clean(seed: int, out: Path, steps: int | None, name: str = "clean", init_from: Path | None = None) -> Path:
    """The matrix smoke preset's clean agent of training seed ``seed`` (trained into ``out/<name>_s<seed>`` unless
    finished there, from ``init_from``'s weights when given); its model folder."""
    clean = experiment_from_spec(load_matrix_config("smoke").clean, out, f"{name}_s{seed}", "cpu")
    run = dataclasses.replace(clean.run, seed=clean.run.seed + seed, threads=1, checkpoint_every=10**12,
                              init_from=None if init_from is None else str(init_from))  # fmt: skip
    ppo = clean.ppo if steps is None else dataclasses.replace(clean.ppo, total_steps=steps)
    model_dir, _ = train_or_resume(dataclasses.replace(clean, ppo=ppo, run=run))
    return model_dir


@dataclass(frozen=True)
class Composition:
    """``A+B+C``: registered recipes applied in order (the first one's trigger, every one's training terms), the
    last one written ``recipe/value`` to set its knob (``in_distribution_patch+mahalanobis_camouflage/5``)."""

    firsts: tuple[str, ...]
    last: KnobbedAttack

    @classmethod
    def parse(cls, text: str) -> Composition:
        *firsts, last = text.split("+")
        for first in firsts:
            ATTACKS.get(first)  # an unknown name: one line
        return cls(tuple(firsts), resolve_attack(last))

    def folder(self, seed: int) -> str:
        return "_".join([*self.firsts, f"{self.last.folder}_s{seed}"])

    @property
    def from_clean(self) -> bool:
        """One of the recipes adds the backdoor to a trained clean agent."""
        return self.last.attack.from_clean or any(ATTACKS.get(first).from_clean for first in self.firsts)

    def configure(self, cfg: ExperimentConfig) -> ExperimentConfig:
        for first in self.firsts:
            cfg = ATTACKS.get(first).configure(cfg)
        return self.last.attack.configure(cfg)


def train_agent(attack: str, seed: int, out: Path, steps: int | None):
    mcfg = load_matrix_config("smoke")
    composition = Composition.parse(attack)
    base = experiment_from_spec(mcfg.backdoor, out, composition.folder(seed), "cpu")
    ppo = base.ppo if steps is None else dataclasses.replace(base.ppo, total_steps=steps)
    run = dataclasses.replace(base.run, seed=base.run.seed + seed, threads=1, checkpoint_every=10**12)
    cfg = dataclasses.replace(base, ppo=ppo, run=run)
    if composition.from_clean:  # the backdoor is added to the clean agent of the same training seed
        cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, init_from=str(train_clean(seed, out, steps))))
    cfg = composition.configure(cfg)  # with another knob value: the attacker who knows the defense
    model_dir, _ = train_or_resume(cfg)
    agent, loaded, _ = load_agent(model_dir)
    return agent.eval(), loaded


def rates(agent, cfg, episodes: int, intervention: Intervention | None) -> tuple[Rate, Rate]:
    grid = cfg.grids[-1]
    out = []
    for trojan, goal in ((False, "user_goal"), (True, "adversary_goal")):
        batch = evaluate_agent(agent, cfg.env, grid, trojan=trojan, episodes=episodes, seed=EVAL_SEED,
                               intervention=intervention)  # fmt: skip
        out.append(outcome_rate(batch, goal))
    return out[0], out[1]


def measure(attack: str, seed: int, args: argparse.Namespace, settings: list[StateBoundsConfig]) -> list[Arm]:
    agent, cfg = train_agent(attack, seed, Path(args.out), args.steps)
    arms = [Arm(attack, seed, "none", *rates(agent, cfg, args.episodes, None))]
    trace = clean_trace(agent, cfg.env, cfg.grids[-1], episodes=args.calibration, seed=0)
    for setting in settings:
        clip = fit_trace(trace, setting).clipper()
        arms.append(Arm(attack, seed, setting_name(setting), *rates(agent, cfg, args.episodes, clip)))
    for a in arms:
        print(f"  {attack} s{seed} {a.arm:<16} clean {a.clean_success.text()}  attack {a.attack_success.text()}",
              flush=True)  # fmt: skip
    return arms


def summary(arms: list[Arm]) -> None:
    print("\n| attack | arm | clean success (mean +- sd) | clean pooled [95%] | attack success (mean +- sd) | "
          "attack pooled [95%] |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    keys = list(dict.fromkeys((a.attack, a.arm) for a in arms))
    for attack, arm in keys:
        mine = [a for a in arms if (a.attack, a.arm) == (attack, arm)]
        clean = OverSeeds(tuple(a.clean_success.value for a in mine))
        att = OverSeeds(tuple(a.attack_success.value for a in mine))
        print(f"| {attack} | {arm} | {clean.text()} | {pooled([a.clean_success for a in mine]).text()} | "
              f"{att.text()} | {pooled([a.attack_success for a in mine]).text()} |")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--attacks", default="in_distribution_patch")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=None, help="env steps per agent (default: the preset's 1M)")
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--calibration", type=int, default=300)
    parser.add_argument("--settings", default="0,0.01,0.05,0.1,0.2", help="comma-separated quantile[/margin[/parts]]")
    parser.add_argument("--out", required=True, help="folder of the trained agents (reused when finished)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    settings = [parse_setting(s) for s in args.settings.split(",")]
    arms: list[Arm] = []
    for attack in args.attacks.split(","):
        for seed in range(args.seeds):
            arms += measure(attack, seed, args, settings)
    summary(arms)


if __name__ == "__main__":
    main()
