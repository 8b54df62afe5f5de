"""Summaries over training seeds: mean, sample sd, the t-interval, and the paper comparison."""

from __future__ import annotations

import math

import pytest

from seqtrojan.evaluation.seeds import find_summary, summarise_over_seeds
from seqtrojan.evaluation.sweep import SweepRow
from seqtrojan.stats import Rate, wilson_interval


def _row(seed: int, successes: int, agent="backdoor", env="trojan", paper=0.934) -> SweepRow:
    """A cell of 1000 episodes with ``successes`` of them successful."""
    none = Rate(0, 1000)
    return SweepRow(agent, "backdoored", env, 17, 30, Rate(successes, 1000), none, none, none, 30.0, paper, seed)


def test_mean_sd_and_t_interval_over_seeds():
    rows = [_row(0, 990), _row(1, 950), _row(2, 970)]
    rows = [r.__class__(**{**r.__dict__, "paper": 0.95}) for r in rows]  # seed 1's interval covers the paper
    (cell,) = summarise_over_seeds(rows)
    assert cell.seeds == (0, 1, 2)
    assert cell.mean == pytest.approx(0.97)
    assert cell.sd == pytest.approx(0.02)  # sample sd, ddof=1: sqrt((0.02^2 + 0.02^2 + 0) / 2)
    low, high = cell.interval
    half = 4.302652729749464 * 0.02 / math.sqrt(3)  # t(0.975, 2 df)
    assert (low, high) == pytest.approx((0.97 - half, min(1.0, 0.97 + half)))
    assert not cell.differs
    record = cell.to_dict()
    assert record["success"] == [0.99, 0.95, 0.97] and record["paper_outside_every_seed_interval"] is False


def test_differs_only_when_no_seed_interval_covers_the_paper():
    above = [_row(0, 990, paper=0.90), _row(1, 970, paper=0.90)]  # intervals [0.982, 0.995], [0.957, 0.979]
    assert summarise_over_seeds(above)[0].differs
    covered = [_row(0, 990, paper=0.965), _row(1, 970, paper=0.965)]
    assert not summarise_over_seeds(covered)[0].differs
    no_paper = [_row(0, 500, paper=None)]
    assert not summarise_over_seeds(no_paper)[0].differs


def test_one_seed_keeps_its_wilson_interval_and_claims_no_spread():
    (cell,) = summarise_over_seeds([_row(0, 900)])
    assert cell.sd == 0.0
    assert cell.interval == wilson_interval(900, 1000)


def test_cells_are_grouped_by_agent_env_and_grid_and_sorted_by_seed():
    rows = [
        _row(1, 900),
        _row(0, 800),
        _row(0, 1000, agent="clean", env="normal"),
    ]
    cells = summarise_over_seeds(rows)
    assert [(c.agent, c.env) for c in cells] == [("backdoor", "trojan"), ("clean", "normal")]
    assert find_summary(cells, "backdoor", "trojan", "17x17/30").successes == (0.8, 0.9)
    assert find_summary(cells, "backdoor", "normal", "17x17/30") is None


def test_a_seed_evaluated_twice_is_refused():
    with pytest.raises(ValueError, match="seed evaluated twice"):
        summarise_over_seeds([_row(0, 900), _row(0, 800)])
