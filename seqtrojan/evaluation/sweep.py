"""Success rates over a list of grid configs (the paper's Tables 1 and 2 by default), beside the paper's numbers.

The clean agent is evaluated in the normal env; a backdoored agent in the normal and the trojan env. Each
(agent, env, config) is ``episodes`` trials (the paper: 1000) run as one batch, reported with a 95% Wilson
interval, hole-fall, time-out and wrong-goal rates, and the paper's value where it reports one: a
:class:`~seqtrojan.evaluation.results.SweepRow` each (saved by :func:`write_sweep`, read by :func:`load_sweep`).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import ExperimentConfig
from seqtrojan.env.config import GridSpec
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate, success_rate
from seqtrojan.evaluation.results import SweepRow, load_sweep, write_sweep
from seqtrojan.paper import paper_configs, paper_success

__all__ = ["SweepRow", "evaluate_sweep", "load_sweep", "parse_configs", "write_sweep"]


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
    labels: Sequence[str] | None = None,
) -> list[SweepRow]:
    """Evaluate every agent on every config; ``training_seed`` tags the rows (see evaluation/seeds.py).

    ``labels``: each agent's label (its card's; default: its config's). Only an agent known to be clean skips the
    trojan env: a backdoored one and one of unknown lineage (an imported suspect) are evaluated in both."""
    rows = []
    for i, (name, agent, cfg) in enumerate(agents):
        label = cfg.label if labels is None else labels[i]
        envs = ("normal",) if label == "clean" else ("normal", "trojan")
        for size, holes in configs:
            grid = GridSpec(size, holes)
            for env in envs:
                batch = evaluate_agent(
                    agent, cfg.grid_env, grid, trojan=env == "trojan", episodes=episodes, seed=seed, greedy=greedy,
                    device=device,
                )  # fmt: skip
                wrong = outcome_rate(batch, "adversary_goal" if env == "normal" else "user_goal")
                rows.append(
                    SweepRow(
                        name,
                        label,
                        env,
                        size,
                        holes,
                        success_rate(batch),
                        outcome_rate(batch, "hole"),
                        outcome_rate(batch, "timeout"),
                        wrong,
                        float(batch.length.float().mean()),
                        paper_success(label, env, size, holes),
                        training_seed,
                    )
                )
    return rows
