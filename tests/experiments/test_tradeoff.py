"""Planning the trade-off's agents: which are trained and which are the headline's backdoored agents."""

from __future__ import annotations

from pathlib import Path

from seqtrojan.experiments.specs import AgentSpec, experiment_from_spec
from seqtrojan.experiments.tradeoff import TradeoffConfig, tradeoff_agents


def test_the_base_penalty_reuses_every_trained_seed_and_only_those(tmp_path: Path):
    base = experiment_from_spec(AgentSpec(preset="trojan_s17_h30"), tmp_path, "backdoor", "cpu")
    cfg = TradeoffConfig(penalties=(-1.0, -3.0), seeds=3)
    agents = tradeoff_agents(base, cfg, tmp_path, trained_seeds=2)
    planned = [(a.penalty, a.seed_offset, None if a.job is None else a.job.id) for a in agents]
    assert planned == [
        (-1.0, 0, None),
        (-1.0, 1, None),  # the headline's backdoored agent of training seed 1
        (-1.0, 2, f"backdoor_penalty-1_seed{base.run.seed + 2}"),
        (-3.0, 0, "backdoor_penalty-3"),
        (-3.0, 1, f"backdoor_penalty-3_seed{base.run.seed + 1}"),
        (-3.0, 2, f"backdoor_penalty-3_seed{base.run.seed + 2}"),
    ]
    assert [a.config.run.seed - base.run.seed for a in agents[:3]] == [0, 1, 2]
    longer = TradeoffConfig(penalties=(-1.0,), seeds=2, total_steps=base.ppo.total_steps + 1)
    assert all(a.job is not None for a in tradeoff_agents(base, longer, tmp_path, trained_seeds=2))
