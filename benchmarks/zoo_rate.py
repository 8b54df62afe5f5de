"""Print how fast a zoo builds, per part and sequence model, and how long the rest of it will take.

    seqtrojan zoo build --config benchmark_paper --out Z --limit 16       # a first installment, alone
    python benchmarks/zoo_rate.py --zoo Z --workers 2 --json rate.json    # its rates and the projection
    python benchmarks/zoo_rate.py --table rate.json                       # the markdown table of a saved run

Reads a zoo that is built or partly built (``zoo.json`` and ``manifest.json``; ``seqtrojan zoo build --limit N``
builds one in installments, taking a zoo's parts in turn). Per part of the zoo (its env and the sequence model of
each model) it prints the models done, their mean wall time per model in a worker (both stages of a two-stage
model, its evaluation and its saving; the workers ran side by side, so what they cost each other is in it), the
models per hour that makes with ``--workers`` workers, the poisoned models whose backdoor works and the mean clean
success, and how many models are left with the hours they will take at that rate. A group with no model done yet is
marked unmeasured and left out of the total. The projection assumes the models left cost what the done ones of
their group did: a sample's drawn attacks and early stops make that a rough figure for a few models per group. For
a zoo that draws attack recipes, a second table: per part and recipe, the done poisoned models, those whose
backdoor works, their mean attack success, their mean clean success (a recipe that costs the agent its task shows
there) and, from the training curves a zoo keeps (``curves/<id>.jsonl``), how many formed their backdoor during
training (normal and trojan success of an update's rollouts both at least 0.9) and the median env steps that took:
what a part's budget must cover.
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from seqtrojan.experiments.attacks import RECIPES
from seqtrojan.serde import from_dict
from seqtrojan.stats import reaches
from seqtrojan.zoo.build import (
    MAX_MANIFEST_BYTES,
    MAX_ZOO_CONFIG_BYTES,
    ZooConfig,
    ZooJob,
    make_jobs,
    read_json_file,
)


@dataclass(frozen=True)
class GroupRate:
    part: int
    env: str
    cell: str
    models: int
    done: int
    mean_seconds: float | None
    """mean wall seconds per done model in a worker; None: none done"""
    functional: int
    poisoned: int
    """done poisoned models, and those whose backdoor works (``functional_backdoor``)"""
    clean_success: float | None
    """mean normal-env success of the done models"""

    def models_per_hour(self, workers: int) -> float | None:
        return None if not self.mean_seconds else workers * 3600.0 / self.mean_seconds

    def hours_left(self, workers: int) -> float | None:
        if self.mean_seconds is None:
            return None
        return (self.models - self.done) * self.mean_seconds / workers / 3600.0


@dataclass(frozen=True)
class RecipeRate:
    """How often one part's recipe formed a working backdoor among its done poisoned models."""

    part: int
    env: str
    attack: str
    poisoned: int
    functional: int
    mean_attack_success: float
    mean_clean_success: float | None = None
    """their mean normal-env success: below the task's own, the recipe cost the agent its task (None: not read)"""
    curves: int = 0
    """how many of them have a training curve (``curves/<id>.jsonl``; zoos built before 2026-12-04 have none)"""
    formed: int = 0
    median_steps_to_form: float | None = None
    """of those curves, how many show the backdoor forming (:func:`steps_to_form`), and the median env steps it took"""


@dataclass(frozen=True)
class ZooModel:
    """One model of a zoo as this script reads it: its part, its job and its manifest entry (empty: not built)."""

    part: int
    job: ZooJob
    entry: dict[str, Any]

    @property
    def env(self) -> str:
        return str(self.job.variation.get("env", "grid"))

    @property
    def done(self) -> bool:
        return self.entry.get("status") == "done"


def read_zoo_models(zoo: Path) -> tuple[ZooConfig, list[ZooModel]]:
    """The zoo's config (``zoo.json``) and every model it holds or will hold, with its manifest entry."""
    cfg = from_dict(ZooConfig, read_json_file(zoo / "zoo.json", MAX_ZOO_CONFIG_BYTES), "zoo.json")
    manifest = {e["id"]: e for e in read_json_file(zoo / "manifest.json", MAX_MANIFEST_BYTES) if isinstance(e, dict)}
    jobs = iter(make_jobs(cfg, zoo, RECIPES))  # the parts' models, in part order
    models = [
        ZooModel(p, job, manifest.get(job.id, {}))
        for p, part in enumerate(cfg.parts or (cfg,))
        for job in itertools.islice(jobs, part.size)
    ]
    return cfg, models


FORMED_AT = 0.9
"""a backdoor has formed at the first update whose training rollouts succeed this often in both envs"""


def steps_to_form(curve: Path) -> int | None:
    """The env steps at which a model's training curve first shows its backdoor formed (normal and trojan success
    of the update's rollouts both at least :data:`FORMED_AT`); None: never, or no readable curve."""
    try:
        lines = curve.read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        try:
            row = json.loads(line)
            normal, trojan = row["episodes/normal_success"], row["episodes/trojan_success"]
            if normal >= FORMED_AT and trojan >= FORMED_AT:
                return int(row["env_steps"])
        except (json.JSONDecodeError, KeyError, TypeError):
            continue
    return None


def recipes(cfg: ZooConfig, models: list[ZooModel], zoo: Path) -> list[RecipeRate]:
    """Per part and attack recipe of a zoo that draws recipes: the done poisoned models, those whose backdoor works
    (attack success at least the part's ``functional_at``), their mean attack and clean success, and what their
    training curves (``curves/<id>.jsonl`` under ``zoo``) say of when the backdoor formed."""
    found: dict[tuple[int, str, str], list[tuple[float, float, Path]]] = {}
    for m in models:
        metrics = m.entry.get("metrics", {})
        success, clean = metrics.get("trojan_success"), metrics.get("normal_success")
        if m.job.label == "backdoored" and m.done and isinstance(success, (int, float)):
            key = (m.part, m.env, str(m.job.variation.get("attack", "none")))
            number = isinstance(clean, (int, float)) and not isinstance(clean, bool)
            clean_value = float(clean) if number else float("nan")
            found.setdefault(key, []).append((float(success), clean_value, zoo / "curves" / f"{m.job.id}.jsonl"))
    rates = []
    for (p, env, attack), v in sorted(found.items()):
        curves = [c for _, _, c in v if c.is_file()]
        formed = [n for n in map(steps_to_form, curves) if n is not None]
        rates.append(RecipeRate(
            p, env, attack, len(v), sum(reaches(a, _functional_at(cfg, p)) for a, _, _ in v),
            statistics.fmean(a for a, _, _ in v), statistics.fmean(c for _, c, _ in v),
            len(curves), len(formed), statistics.median(formed) if formed else None,
        ))  # fmt: skip
    return rates


def measure(cfg: ZooConfig, models: list[ZooModel]) -> list[GroupRate]:
    """Per part, env and sequence model: the models done, their mean seconds, working backdoors, clean success."""
    groups: dict[tuple[int, str, str], list[ZooModel]] = {}
    for m in models:
        groups.setdefault((m.part, m.env, m.job.config.agent.cell), []).append(m)
    rates = []
    for (p, env, cell), members in groups.items():
        done = [m for m in members if m.done and isinstance(m.entry.get("seconds"), (int, float))]
        poisoned = [m.entry for m in done if m.job.label == "backdoored"]
        clean = [m.entry["metrics"]["normal_success"] for m in done if "normal_success" in m.entry.get("metrics", {})]
        at = _functional_at(cfg, p)
        functional = sum(1 for e in poisoned if reaches(e["metrics"].get("trojan_success", 0.0), at))
        rates.append(GroupRate(
            p, env, cell, len(members), len(done),
            statistics.fmean(m.entry["seconds"] for m in done) if done else None,
            functional, len(poisoned), statistics.fmean(clean) if clean else None,
        ))  # fmt: skip
    return sorted(rates, key=lambda r: (r.part, r.cell))


def _functional_at(cfg: ZooConfig, part: int) -> float:
    return (cfg.parts[part] if cfg.parts else cfg).functional_at


def table(data: dict) -> str:
    workers = data["workers"]
    rows = [
        "| part | env | cell | models | done | s per model | models/h | backdoors working | clean success | "
        "hours left |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for g in data["groups"]:
        r = GroupRate(**g)
        per_hour, left = r.models_per_hour(workers), r.hours_left(workers)
        rows.append(
            f"| {r.part} | {r.env} | {r.cell} | {r.models} | {r.done} | "
            + (f"{r.mean_seconds:.0f} | {per_hour:.0f} | " if r.mean_seconds and per_hour else "unmeasured | | ")
            + (f"{r.functional} of {r.poisoned} | " if r.poisoned else "none done | ")
            + (f"{r.clean_success:.2f} | " if r.clean_success is not None else " | ")
            + (f"{left:.1f} |" if left is not None else " |")
        )
    if data.get("recipes"):
        recipe_rows = [
            "| part | env | recipe | poisoned models done | backdoors working | mean attack success | "
            "mean clean success | formed in training (median steps) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        recipe_rows += [
            f"| {r['part']} | {r['env']} | {r['attack']} | {r['poisoned']} | {r['functional']} | "
            f"{r['mean_attack_success']:.2f} | "
            + (f"{r['mean_clean_success']:.2f} |" if r.get("mean_clean_success") is not None else " |")
            + _formation(r)
            for r in data["recipes"]
        ]
    total = data["hours_left"]
    rows.append(f"| all | | | {data['models']} | {data['done']} | | | | | {total:.1f} ({data['unmeasured']} "
                f"models unmeasured) |")  # fmt: skip
    return "\n".join(rows + (["", *recipe_rows] if data.get("recipes") else []))


def _formation(rate: dict) -> str:
    """The recipe's formation cell: ``3 of 4 curves (301k)``; empty without curves."""
    if not rate.get("curves"):
        return " |"
    median = rate.get("median_steps_to_form")
    return f" {rate['formed']} of {rate['curves']} curves" + (f" ({median / 1000:.0f}k) |" if median else " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--zoo", type=Path, help="a built or partly built zoo")
    parser.add_argument("--workers", type=int, default=2, help="workers the projection assumes (default 2)")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--table", type=Path, help="print the markdown table of a saved run (--json), and stop")
    args = parser.parse_args()
    if args.table is not None:
        print(table(json.loads(args.table.read_text())))
        return
    if args.zoo is None or args.workers < 1:
        parser.error("give --zoo and a positive --workers, or --table")
    cfg, models = read_zoo_models(args.zoo)
    groups = measure(cfg, models)
    measured = [g for g in groups if g.mean_seconds is not None]
    data = {
        "zoo": str(args.zoo), "date": datetime.date.today().isoformat(), "workers": args.workers,
        "command": "python benchmarks/zoo_rate.py " + " ".join(sys.argv[1:]),
        "models": sum(g.models for g in groups), "done": sum(g.done for g in groups),
        "unmeasured": sum(g.models - g.done for g in groups if g.mean_seconds is None),
        "hours_left": sum(g.hours_left(args.workers) or 0.0 for g in measured),
        "groups": [g.__dict__ for g in groups],
        "recipes": [r.__dict__ for r in recipes(cfg, models, args.zoo)],
    }  # fmt: skip
    print(table(data))
    if args.json is not None:
        args.json.write_text(json.dumps(data, indent=1) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
