"""Print what the recurrent-state probe sees of agents trained against it, beside the same trigger without the
attacker's penalty and beside clean agents, over training seeds.

    python benchmarks/probe_camouflage.py --out /tmp/pc --json docs/data/defenses/probe_camouflage_2026-12-04.json
    python benchmarks/probe_camouflage.py --attacks in_distribution_patch,probe_camouflage/3 --out /tmp/pc
    python benchmarks/probe_camouflage.py --attacks in_distribution_patch,probe_camouflage,probe_mimicry/0.1 \
        --seeds 5 --out /tmp/pc

Agents: the matrix smoke preset's (7x7/3, LSTM 64-32, curriculum 5x5/0 -> 5x5/1 -> 7x7/3, running mixing, 1M env
steps unless ``--steps``), trained as ``benchmarks/state_bounds.py`` trains them (training seeds ``0..seeds-1``, one
torch thread, a finished agent in ``--out`` reused): the preset's clean agents, and per attack (default: the
in-distribution patch, then ``probe_camouflage``, which trains that same trigger with the penalty) one agent per
seed. ``recipe/value`` sets an adaptive recipe's knob (of the last recipe named); ``A+B`` trains A's trigger with
B's terms, ``A+B+C`` with B's and C's (from the clean agent when one of them starts from one); ``clean_longer`` is a
control row, the clean agents trained on, clean, for as many steps again (as long as a from-clean recipe's agents
train in all).

Per agent: clean success and attack success on ``--episodes`` episodes per env (seed 1000003), with Wilson 95%
intervals; and the state probe's features (:func:`seqtrojan.benchmark.state_probe.probe_features`, its default
settings: 48 clean episodes, a candidate at step 1, the state read 4 steps on), computed from the model and the
clean env only, as the benchmark's detector computes them. Printed: each agent's figures; per attack the mean +- sd
over seeds of each figure; per attack and feature the ROC-AUC of that feature alone, the clean agents against the
attack's (the larger the feature, the more suspect), with Newcombe's 95% interval; and registered benchmark detectors
(``--detectors``; default the probe read one-sided, ``state_probe``, and on both sides, ``state_probe_deviation``)
fitted as the benchmark fits them, on the clean agents and the first attack's (the plain backdoor): each agent's
P(poisoned) out of sample (an agent of that train set scored by a fit without its training seed's clean and plain
agents) and per attack the ROC-AUC against the clean agents.
"""

from __future__ import annotations

# isort: off
import seqtrojan  # noqa: F401  (first: it sets the OpenMP wait policy before torch loads its runtime)
import numpy as np
import torch

# isort: on
import argparse
import dataclasses
import datetime
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.benchmark.detectors import DETECTORS
from seqtrojan.benchmark.scoring import roc_auc
from seqtrojan.benchmark.state_probe import ProbeSettings, probe_features
from seqtrojan.benchmark.suspect import ModelFacts, Suspect, clean_env
from seqtrojan.stats import OverSeeds, Rate, auc_interval

sys.path.insert(0, str(Path(__file__).resolve().parent))
from state_bounds import rates, train_agent, train_clean  # a sibling benchmark's training

FEATURES = ("divergence_max", "divergence_mean", "persistence_max")


@dataclass(frozen=True)
class Measured:
    attack: str
    """``clean`` for the clean agents"""
    seed: int
    clean_success: float
    attack_success: float
    features: dict[str, float]


CLEAN_LONGER = "clean_longer"
"""a control row, not an attack: the clean agent of each seed trained on, clean, for as many steps again, as long
as a from-clean recipe's agent has trained in all (a detector that ranks it above the clean agents reads training
length, not a backdoor)"""


def train_clean_longer(seed: int, out: Path, steps: int | None):
    model_dir = train_clean(seed, out, steps, name=CLEAN_LONGER, init_from=train_clean(seed, out, steps))
    agent, loaded, _ = load_agent(model_dir)
    return agent.eval(), loaded


def suspect_of(agent, cfg, name: str) -> Suspect:
    facts = ModelFacts(agent.obs_dim, agent.num_actions, agent.cell, tuple(agent.lstm_sizes),
                       sum(p.numel() for p in agent.parameters()))  # fmt: skip
    return Suspect(name, agent, clean_env(cfg.env), facts)


def measure(attack: str, seed: int, args: argparse.Namespace) -> tuple[Measured, tuple[Rate, Rate], Suspect]:
    if attack == "clean":
        agent, cfg, _ = load_agent(train_clean(seed, Path(args.out), args.steps))
        agent = agent.eval()
    elif attack == CLEAN_LONGER:
        agent, cfg = train_clean_longer(seed, Path(args.out), args.steps)
    else:
        agent, cfg = train_agent(attack, seed, Path(args.out), args.steps)
    clean, att = rates(agent, cfg, args.episodes, None)
    suspect = suspect_of(agent, cfg, f"{attack}_s{seed}")
    features = probe_features(suspect, ProbeSettings())
    row = Measured(attack, seed, clean.value, att.value, features)
    shown = "  ".join(f"{k} {features[k]:.4f}" for k in FEATURES)
    print(f"  {attack} s{seed}: clean {clean.text()}  attack {att.text()}  {shown}", flush=True)
    return row, (clean, att), suspect


def summary(rows: list[Measured], fitted: dict) -> dict:
    out: dict = {"attacks": {}, "auc": {}}
    clean_rows = [r for r in rows if r.attack == "clean"]
    print("\n| agents | clean success | attack success | " + " | ".join(FEATURES) + " |")
    print("|---|---|---|" + "---|" * len(FEATURES))
    for attack in dict.fromkeys(r.attack for r in rows):
        mine = [r for r in rows if r.attack == attack]
        figures = {"clean_success": OverSeeds(tuple(r.clean_success for r in mine)),
                   "attack_success": OverSeeds(tuple(r.attack_success for r in mine)),
                   **{k: OverSeeds(tuple(r.features[k] for r in mine)) for k in FEATURES}}  # fmt: skip
        out["attacks"][attack] = {
            k: {"mean": v.mean, "sd": v.sd, "per_seed": list(v.values)} for k, v in figures.items()
        }
        print(f"| {attack} | " + " | ".join(v.text() for v in figures.values()) + " |")
    print("\n| attack | feature | ROC-AUC, clean agents vs the attack's [95%] |")
    print("|---|---|---|")
    for attack in dict.fromkeys(r.attack for r in rows if r.attack != "clean"):
        mine = [r for r in rows if r.attack == attack]
        for k in FEATURES:
            labels = torch.tensor([0] * len(clean_rows) + [1] * len(mine)).numpy()
            scores = torch.tensor([r.features[k] for r in clean_rows + mine], dtype=torch.float64).numpy()
            auc = roc_auc(labels, scores)
            low, high = auc_interval(auc, len(mine), len(clean_rows))
            out["auc"].setdefault(attack, {})[k] = {"auc": auc, "ci95": [low, high]}
            print(f"| {attack} | {k} | {auc:.3f} [{low:.3f}, {high:.3f}] |")
    if fitted:
        print(f"\n| attack | detector, fitted on clean vs {fitted['fitted_on']} agents | P(poisoned) per seed | "
              "ROC-AUC against the clean agents [95%] |")  # fmt: skip
        print("|---|---|---|---|")
        for attack, scored_by in fitted["attacks"].items():
            for detector, scored in scored_by.items():
                values = ", ".join(f"{v:.3f}" for v in scored["probability"])
                low, high = scored["auc_ci95"]
                print(f"| {attack} | {detector} | {values} | {scored['auc']:.3f} [{low:.3f}, {high:.3f}] |")
    out["detectors"] = fitted
    return out


PROBE_DETECTORS = ("state_probe", "state_probe_deviation")
"""the default ``--detectors``: the probe read one-sided and on both sides"""


def fitted_detectors(rows: list[Measured], suspects: dict[int, Suspect], names: list[str]) -> dict:
    """Each registered benchmark detector in ``names`` as the benchmark fits it, on the clean agents and the first
    attack's (the plain backdoor), scoring every agent out of sample: an agent of that train set by the detector
    fitted without its training seed (the clean and the plain agent of that seed left out together, so the fit's
    share of poisoned agents stays what it is for the others: leaving one agent out would tilt every score against
    the left-out agent's label), every other attack's agent by the detector fitted on all of it. Per attack
    and detector: each seed's P(poisoned) and the ROC-AUC of the attack's agents against the clean ones, with
    Newcombe's interval. ``suspects``: each row's suspect, by the row's ``id``."""
    attacks = list(dict.fromkeys(r.attack for r in rows if r.attack != "clean"))
    if not attacks:
        return {}
    train = [r for r in rows if r.attack in ("clean", attacks[0])]
    in_train = {id(r) for r in train}

    def fit(detector, among: list[Measured]):
        return detector.fit([suspects[id(r)] for r in among], [int(r.attack != "clean") for r in among])

    result: dict = {"fitted_on": attacks[0], "attacks": {}}
    for name in names:
        detector = DETECTORS.get(name)
        whole = fit(detector, train)
        without = {seed: fit(detector, [t for t in train if t.seed != seed]) for seed in {r.seed for r in train}}
        scores = {id(r): (without[r.seed] if id(r) in in_train else whole).probability(suspects[id(r)]) for r in rows}
        print(f"  {name}: fitted and scored", flush=True)
        clean = [scores[id(r)] for r in rows if r.attack == "clean"]
        for attack in attacks:
            mine = [scores[id(r)] for r in rows if r.attack == attack]
            auc = roc_auc(np.array([0] * len(clean) + [1] * len(mine)), np.array(clean + mine))
            low, high = auc_interval(auc, len(mine), len(clean))
            result["attacks"].setdefault(attack, {})[name] = {"probability": mine, "auc": auc, "auc_ci95": [low, high]}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--attacks", default="in_distribution_patch,probe_camouflage")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument(
        "--detectors",
        default=",".join(PROBE_DETECTORS),
        help="registered benchmark detectors to fit and score (seqtrojan defenses lists them)",
    )
    parser.add_argument("--steps", type=int, default=None, help="env steps per agent (default: the preset's 1M)")
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--out", default=None, help="folder of the trained agents (reused when finished)")
    parser.add_argument("--json", default=None, help="also write the figures here")
    parser.add_argument("--table", default=None, help="print the tables of a JSON file this script wrote, and stop")
    args = parser.parse_args()
    if args.table:
        data = json.loads(Path(args.table).read_text())
        summary([Measured(a["attack"], a["seed"], a["clean_success"], a["attack_success"], a["features"])
                 for a in data["agents"]], data["detectors"])  # fmt: skip
        return
    if not args.out:
        parser.error("--out is required to train and measure")
    torch.set_num_threads(1)
    names = args.detectors.split(",")
    unknown = [name for name in names if name not in DETECTORS.names()]
    if unknown:  # refused before anything is trained
        parser.error(f"unknown detector {unknown[0]!r}; registered: {', '.join(DETECTORS.names())}")
    rates_of: dict[tuple[str, int], tuple[Rate, Rate]] = {}
    rows, suspects = [], {}
    for attack in ["clean", *args.attacks.split(",")]:
        for seed in range(args.seeds):
            row, rates_of[attack, seed], suspect = measure(attack, seed, args)
            rows.append(row)
            suspects[id(row)] = suspect
    figures = summary(rows, fitted_detectors(rows, suspects, names))
    if args.json:
        record = {
            "command": "python benchmarks/probe_camouflage.py " + " ".join(sys.argv[1:]),
            "date": datetime.date.today().isoformat(),
            "settings": {
                "seeds": args.seeds,
                "steps": args.steps,
                "episodes": args.episodes,
                "probe": dataclasses.asdict(ProbeSettings()),
                "detectors": names,
            },
            "agents": [
                {
                    "attack": r.attack,
                    "seed": r.seed,
                    "clean_success": r.clean_success,
                    "clean_success_ci95": list(rates_of[r.attack, r.seed][0].interval),
                    "clean_success_rate": rates_of[r.attack, r.seed][0].serde_dump(),
                    "attack_success": r.attack_success,
                    "attack_success_ci95": list(rates_of[r.attack, r.seed][1].interval),
                    "attack_success_rate": rates_of[r.attack, r.seed][1].serde_dump(),
                    "features": r.features,
                }
                for r in rows
            ],
            **figures,
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
