"""Natural occurrence of a trigger pattern in normal episodes (seqtrojan.analysis.occurrence)."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis.occurrence import OccurrenceResult, natural_occurrence
from seqtrojan.analysis.unintentional import sweep_unintentional
from seqtrojan.env import EnvConfig, GridSpec, PatternConfig, TriggerConfig, TrojanGridCore
from seqtrojan.env.codes import CELL_CODES
from seqtrojan.env.scripted import RandomAgent
from seqtrojan.errors import ConfigError
from seqtrojan.serde import from_dict, to_dict
from seqtrojan.stats import Rate

TOP_EMPTY = EnvConfig(trigger=TriggerConfig(cells=((0, 0), (0, 1), (0, 2)), values=("empty",) * 3))
SIDE_HOLES = EnvConfig(
    trigger=TriggerConfig(
        sequence=(
            PatternConfig(cells=((0, 1),), values=("hole",)),
            PatternConfig(cells=((1, 2),), values=("hole",)),
        )
    )
)


def brute_force(env: EnvConfig, grid: GridSpec, episodes: int, seed: int) -> tuple[int, int, int]:
    """(episodes with the pattern, steps completing it, steps) by a plain Python scan of every episode's views."""
    core = TrojanGridCore(env.with_grid(grid), episodes, seed=seed, trojan_probability=0.0, phase="eval")
    agent = RandomAgent(core, seed)
    frames = [{r * 3 + c: CELL_CODES[name] for (r, c), name in frame} for frame in env.on_frames]
    views: list[list[list[int]]] = [[] for _ in range(episodes)]
    running = torch.ones(episodes, dtype=torch.bool)
    for _ in range(grid.time_limit):
        codes = core.observe_codes().tolist()
        for e in range(episodes):
            if running[e]:
                views[e].append(codes[e])
        result = core.step(agent.act(), autoreset=False)
        running &= ~result.done
        if not bool(running.any()):
            break
    with_pattern = hits = steps = 0
    for seen in views:
        steps += len(seen)
        count = 0
        for t in range(len(frames) - 1, len(seen)):
            start = t - len(frames) + 1
            if all(all(seen[start + k][i] == v for i, v in f.items()) for k, f in enumerate(frames)):
                count += 1
        hits += count
        with_pattern += count > 0
    return with_pattern, hits, steps


def test_the_dedicated_trigger_code_never_occurs_naturally():
    result = natural_occurrence(None, EnvConfig(), GridSpec(5, 0), episodes=64, seed=0)
    assert result.episodes_with_pattern == Rate(0, 64)
    assert result.steps_with_pattern.k == 0 and result.steps_with_pattern.n > 64 * 6  # random walks run long
    assert result.policy == "random" and result.frames == 1 and result.grid == "5x5/0"


def test_an_all_empty_patch_occurs_in_most_episodes_on_an_empty_grid():
    result = natural_occurrence(None, TOP_EMPTY, GridSpec(5, 0), episodes=128, seed=1)
    assert result.episodes_with_pattern.value > 0.8  # any step off the top row shows three empty cells above
    # The first observation (the start, bottom row) always shows it: at least one step per episode.
    assert result.steps_with_pattern.k >= 128 and result.steps_with_pattern.value < 1.0


def test_counts_equal_a_plain_scan_of_every_view():
    for env, grid in ((TOP_EMPTY, GridSpec(7, 6)), (SIDE_HOLES, GridSpec(7, 12))):
        result = natural_occurrence(None, env, grid, episodes=96, seed=5)
        episodes, hits, steps = brute_force(env, grid, 96, 5)
        assert (result.episodes_with_pattern.k, result.steps_with_pattern.k, result.steps_with_pattern.n) == (
            episodes,
            hits,
            steps,
        )
        assert 0 < hits < steps  # the scan saw both outcomes, so the comparison can fail


def test_a_sequence_needs_its_frames_in_order_on_consecutive_steps():
    one = EnvConfig(trigger=TriggerConfig(cells=((0, 1),), values=("hole",)))
    both = natural_occurrence(None, SIDE_HOLES, GridSpec(7, 12), episodes=256, seed=2)
    first = natural_occurrence(None, one, GridSpec(7, 12), episodes=256, seed=2)
    assert both.frames == 2 and 0 < both.steps_with_pattern.k < first.steps_with_pattern.k
    reverse = EnvConfig(trigger=TriggerConfig(sequence=tuple(reversed(SIDE_HOLES.trigger.sequence or ()))))
    other = natural_occurrence(None, reverse, GridSpec(7, 12), episodes=256, seed=2)
    assert other.steps_with_pattern.k != both.steps_with_pattern.k


def test_an_agent_policy_runs_and_the_result_round_trips():
    torch.manual_seed(0)
    agent = RecurrentActorCritic(54, 4, (16,))
    result = natural_occurrence(agent, TOP_EMPTY, GridSpec(7, 3), episodes=32, seed=0, greedy=True)
    assert result.policy == "agent" and result.episodes_with_pattern.n == 32
    assert result.episodes_with_pattern.k > 0
    assert from_dict(OccurrenceResult, to_dict(result)) == result
    with pytest.raises(ConfigError, match="the agent takes 54 inputs and 4 actions; this env gives 150"):
        natural_occurrence(agent, EnvConfig(view_size=5), GridSpec(7, 3), episodes=4)
    with pytest.raises(ConfigError, match="episodes must be a positive integer, got 0"):
        natural_occurrence(None, TOP_EMPTY, GridSpec(7, 3), episodes=0)


def test_unintentional_sweep_runs_with_the_new_trigger_kinds():
    torch.manual_seed(0)
    agent = RecurrentActorCritic(54, 4, (8,))
    for env in (TOP_EMPTY, SIDE_HOLES):
        summaries, findings = sweep_unintentional(agent, env, [(7, 3)], episodes=16, seed=0, keep=2)
        (summary,) = summaries
        assert summary.episodes == 16 and sum(summary.trojan_outcomes.values()) == 16
        last = 8 - (env.trigger.frame_count - 1)  # the last trigger step on 7x7: the sequence ends by step 8
        assert all(f.trigger_step is None or f.trigger_step <= last for f in findings)
