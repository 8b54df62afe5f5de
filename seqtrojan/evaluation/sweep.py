"""Success rates over a list of grid configs (the paper's Tables 1 and 2 by default), beside the paper's numbers.

The clean agent is evaluated in the normal env; a backdoored agent in the normal and the trojan env. Each
(agent, env, config) is ``episodes`` trials (the paper: 1000) run as one batch, reported with a 95% Wilson
interval, hole-fall, time-out and wrong-goal rates, and the paper's value where it reports one.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.config import GridSpec
from seqtrojan.evaluation.episodes import evaluate_agent
from seqtrojan.paper import paper_configs, paper_success


@dataclass(frozen=True)
class SweepRow:
    agent: str  # a name for the model
    label: str  # clean / backdoored
    env: str  # normal / trojan
    size: int
    holes: int
    episodes: int
    success: float
    ci_low: float
    ci_high: float
    hole: float
    timeout: float
    wrong_goal: float
    mean_length: float
    paper: float | None  # the paper's success rate for this cell, if reported
    seed: int = 0  # the agent's training-seed index (0 for a single-seed evaluation)

    @property
    def config(self) -> str:
        return f"{self.size}x{self.size}/{self.holes}"


def parse_configs(text: str) -> list[tuple[int, int]]:
    """``"paper"`` or a comma-separated list like ``"7x7/0,11/11"`` (size x size / holes, or size/holes): the
    (size, holes) of each grid, read by :meth:`GridSpec.parse` (a ConfigError names a grid it cannot read)."""
    if text.strip() == "paper":
        return paper_configs()
    grids = [GridSpec.parse(item.strip()) for item in text.split(",")]
    return [(g.size, g.holes) for g in grids]


def evaluate_sweep(
    agents: Sequence[tuple[str, RecurrentActorCritic, ExperimentConfig]],
    configs: Sequence[tuple[int, int]],
    *,
    episodes: int = 1000,
    seed: int = 0,
    greedy: bool = False,
    device: str | torch.device = "cpu",
    training_seed: int = 0,
) -> list[SweepRow]:
    """Evaluate every agent on every config; ``training_seed`` tags the rows (see evaluation/seeds.py)."""
    rows = []
    for name, agent, cfg in agents:
        envs = ("normal", "trojan") if cfg.label == "backdoored" else ("normal",)
        for size, holes in configs:
            grid = GridSpec(size, holes)
            for env in envs:
                batch = evaluate_agent(
                    agent, cfg.env, grid, trojan=env == "trojan", episodes=episodes, seed=seed, greedy=greedy,
                    device=device,
                )  # fmt: skip
                lo, hi = batch.success_interval()
                wrong = batch.rate("adversary_goal" if env == "normal" else "user_goal")
                rows.append(
                    SweepRow(
                        name,
                        cfg.label,
                        env,
                        size,
                        holes,
                        episodes,
                        batch.success_rate,
                        lo,
                        hi,
                        batch.rate("hole"),
                        batch.rate("timeout"),
                        wrong,
                        float(batch.length.float().mean()),
                        paper_success(cfg.label, env, size, holes),
                        training_seed,
                    )
                )
    return rows


def write_sweep(rows: Sequence[SweepRow], out_dir: Path) -> tuple[Path, Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, csv_path = out_dir / "evaluation.json", out_dir / "evaluation.csv"
    records = [asdict(r) | {"config": r.config} for r in rows]
    json_path.write_text(json.dumps(records, indent=2))
    with csv_path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(records[0]) if records else ["agent"])
        writer.writeheader()
        writer.writerows(records)
    return json_path, csv_path


def load_sweep(path: Path) -> list[SweepRow]:
    """The rows :func:`write_sweep` wrote to ``evaluation.json`` (keys that are not SweepRow fields, such as
    ``config``, are dropped)."""
    names = {f.name for f in fields(SweepRow)}
    return [SweepRow(**{k: v for k, v in r.items() if k in names}) for r in json.loads(path.read_text())]
