"""The evaluator on scripted agents with known success rates, the confidence interval, and the paper lookup."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.config import AgentConfig, BackdoorConfig, ExperimentConfig
from seqtrojan.env import EnvConfig, GridSpec
from seqtrojan.env.scripted import OracleAgent
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_policy
from seqtrojan.evaluation.sweep import evaluate_sweep, parse_configs
from seqtrojan.paper import paper_configs, paper_success
from seqtrojan.stats import wilson_interval


class WrongGoalOracle(OracleAgent):
    """The oracle, except that the envs in ``wrong`` (B,) head for the other goal: success is exactly 1 - mean."""

    def __init__(self, core, wrong: torch.Tensor) -> None:
        super().__init__(core)
        self.wrong = wrong

    def heads_for_adversary(self) -> torch.Tensor:
        return self.core.adversary_active() ^ self.wrong


def oracle_with_fraction(fraction: float, generator=None):
    def make(core):
        if generator is None:
            wrong = torch.arange(core.num_envs) >= round(fraction * core.num_envs)
        else:
            wrong = torch.rand(core.num_envs, generator=generator) >= fraction
        return WrongGoalOracle(core, wrong).act

    return make


@pytest.mark.parametrize("trojan", [False, True])
def test_known_success_rate_is_measured_exactly(trojan):
    batch = evaluate_policy(
        oracle_with_fraction(0.75), EnvConfig(), GridSpec(9, 6), trojan=trojan, episodes=400, seed=0
    )
    assert batch.success_rate == 0.75
    assert batch.rate("hole") == 0.0 and batch.rate("timeout") == 0.0
    assert batch.rate("user_goal" if trojan else "adversary_goal") == 0.25
    assert bool(batch.trojan.all()) == trojan


def test_interval_covers_a_random_success_rate():
    gen = torch.Generator().manual_seed(0)
    batch = evaluate_policy(
        oracle_with_fraction(0.6, gen), EnvConfig(), GridSpec(7, 3), trojan=False, episodes=1000, seed=1
    )
    lo, hi = batch.success_interval()
    assert lo < 0.6 < hi and hi - lo < 0.07


def test_wilson_interval_known_values():
    assert wilson_interval(50, 100) == pytest.approx((0.4038, 0.5962), abs=1e-4)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson_interval(10, 10) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson_interval(963, 1000) == pytest.approx((0.9494, 0.9730), abs=1e-4)


def test_paper_numbers_are_looked_up():
    assert len(paper_configs()) == 14 and paper_configs()[1] == (7, 7)
    assert paper_success("clean", "normal", 7, 7) == 0.928
    assert paper_success("backdoored", "normal", 23, 0) == 0.0
    assert paper_success("backdoored", "trojan", 7, 7) == 0.549
    assert paper_success("backdoored", "trojan", 17, 30) == 0.934
    assert paper_success("clean", "trojan", 7, 7) is None
    assert paper_success("clean", "normal", 9, 9) is None


def test_config_lists_are_parsed():
    assert parse_configs("7x7/0, 11/11 ,17x17/30") == [(7, 0), (11, 11), (17, 30)]
    assert parse_configs("paper") == paper_configs()
    with pytest.raises(ConfigError, match="cannot read grid config '7x7'"):
        parse_configs("7x7")


def test_sweep_rows_for_clean_and_backdoored_agents():
    clean_cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,)))
    bad_cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(8,)), backdoor=BackdoorConfig(enabled=True))
    agents = [("c", build_agent(clean_cfg), clean_cfg), ("b", build_agent(bad_cfg), bad_cfg)]
    rows = evaluate_sweep(agents, [(7, 7), (9, 4)], episodes=32)
    assert [(r.agent, r.env, r.config) for r in rows] == [
        ("c", "normal", "7x7/7"), ("c", "normal", "9x9/4"),
        ("b", "normal", "7x7/7"), ("b", "trojan", "7x7/7"), ("b", "normal", "9x9/4"), ("b", "trojan", "9x9/4"),
    ]  # fmt: skip
    assert rows[0].paper == 0.928 and rows[3].paper == 0.549 and rows[1].paper is None
    for r in rows:  # every rate over the cell's 32 episodes, each episode ending one way
        assert r.episodes == r.hole.n == r.timeout.n == r.wrong_goal.n == 32
        assert r.success.k + r.hole.k + r.timeout.k + r.wrong_goal.k == 32
