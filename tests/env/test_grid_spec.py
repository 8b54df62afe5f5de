"""One grid parser (GridSpec.parse), one way to move an env onto a grid (EnvConfig.with_grid), and the grid's
geometry (start and goals) from one place."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqtrojan.env import EnvConfig, GridSpec, Layout, TrojanGridCore
from seqtrojan.env.codes import ADV_GOAL, USER_GOAL
from seqtrojan.env.config import RewardConfig, TriggerConfig, min_steps_to_goal
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.sweep import parse_configs


@pytest.mark.parametrize(
    ("written", "expected"),
    [
        ("7x7/0", GridSpec(7, 0)),
        ("7/0", GridSpec(7, 0)),
        (" 11 x 11 / 11 ", GridSpec(11, 11)),
        ("17x17/30", GridSpec(17, 30)),
        ((7, 3), GridSpec(7, 3)),
        ([9, 6], GridSpec(9, 6)),
        ((9, 6, 50), GridSpec(9, 6, 50)),
        ((9, 6, None), GridSpec(9, 6)),
        ((np.int64(5), np.int64(1)), GridSpec(5, 1)),
        ({"size": 9, "holes": 4}, GridSpec(9, 4)),
        ({"size": 9, "holes": 4, "max_steps": 20}, GridSpec(9, 4, 20)),
        ({"size": 9, "holes": 4, "max_steps": None}, GridSpec(9, 4)),
        ({"holes": 0}, GridSpec(7, 0)),  # GridSpec's defaults, as a config mapping gets them
        (GridSpec(5, 1, 9), GridSpec(5, 1, 9)),
    ],
)
def test_every_written_form_parses_to_the_same_grid(written, expected):
    assert GridSpec.parse(written) == expected


@pytest.mark.parametrize(
    ("written", "message"),
    [
        ("7x7", "cannot read grid config '7x7'"),
        ("7x7/3/5", "cannot read grid config"),
        ("seven/3", "cannot read grid config"),
        ("7x7/-1", "cannot read grid config"),
        ("", "cannot read grid config"),
        ("7x9/3", "not square"),
        ("6/0", "odd integer >= 5"),  # GridSpec's own checks apply
        ("5/17", "no solvable layout"),
        ((7,), "cannot read grid config"),
        ((7, 3, 20, 1), "cannot read grid config"),
        ((7.0, 3), "grid size must be an integer"),
        ((7, True), "grid holes must be an integer"),
        ((7, "3"), "grid holes must be an integer"),
        ((7, 3, 0), "max_steps must be a positive integer"),
        ({"size": 7, "holes": 3, "view": 3}, r"unknown grid key\(s\) \['view'\]"),
        ({"size": "7", "holes": 3}, "grid size must be an integer"),
        (7, "cannot read grid config 7"),
        (None, "cannot read grid config None"),
    ],
)
def test_bad_grids_are_refused_naming_the_value(written, message):
    with pytest.raises(ConfigError, match=message):
        GridSpec.parse(written)


def test_parse_configs_reads_lists_through_the_one_parser():
    assert parse_configs("7x7/0, 11/11 ,17x17/30") == [(7, 0), (11, 11), (17, 30)]
    assert parse_configs("5/1") == [(5, 1)]
    with pytest.raises(ConfigError, match="not square"):
        parse_configs("7x7/0,7x9/3")  # read as 7/3 before: a typo went through silently
    with pytest.raises(ConfigError, match="odd integer"):
        parse_configs("8/3")  # refused when read, not at the first episode


def test_with_grid_takes_size_holes_and_the_grids_time_limit():
    env = EnvConfig(size=7, holes=3, max_steps=40, view_size=5, rewards=RewardConfig(timeout=0.0))
    moved = env.with_grid("11x11/11")
    assert (moved.size, moved.holes, moved.max_steps) == (11, 11, None)
    assert moved.grid.time_limit == 44  # 4N: the env's own 40 was set for 7x7 and is not carried over
    assert env.with_grid((11, 11, 60)).grid.time_limit == 60  # unless the grid sets one
    assert env.with_grid(GridSpec(9, 4, 30)).grid == GridSpec(9, 4, 30)
    # everything else is kept
    assert dataclasses.replace(moved, size=7, holes=3, max_steps=40) == env
    with pytest.raises(ConfigError, match="not square"):
        env.with_grid("9x11/3")


@pytest.mark.parametrize("grid", [GridSpec(9, 4), GridSpec(9, 4, 30), GridSpec(5, 0)])
@pytest.mark.parametrize("max_steps", [None, 40])
def test_with_grid_equals_the_call_sites_former_replace(grid, max_steps):
    """The former call sites: ``replace(env, size=, holes=, max_steps=grid.max_steps)`` (evaluation, monitor,
    fine-tuning) and ``replace(env, size=, holes=, max_steps=None)`` from a bare (size, holes) (searches, curves,
    trajectory figure) both give exactly what ``with_grid`` gives, so their results cannot change."""
    env = EnvConfig(size=7, holes=3, max_steps=max_steps, trigger=TriggerConfig(delay=1))
    assert env.with_grid(grid) == dataclasses.replace(env, size=grid.size, holes=grid.holes, max_steps=grid.max_steps)
    assert env.with_grid((grid.size, grid.holes)) == dataclasses.replace(
        env, size=grid.size, holes=grid.holes, max_steps=None
    )


@pytest.mark.parametrize("size", [5, 7, 9, 27])
def test_start_and_goals_come_from_one_place(size):
    grid = GridSpec(size, 0)
    env = EnvConfig(size=size, holes=0)
    assert grid.start == env.start == Layout.empty(size).start == (size - 1, size // 2)  # docs/environment.md
    assert env.goals == (grid.user_goal, grid.adversary_goal) == ((0, size - 1), (0, 0))
    cells = Layout.empty(size).cells
    assert cells[grid.user_goal] == USER_GOAL and cells[grid.adversary_goal] == ADV_GOAL
    core = TrojanGridCore(env, 1, phase="eval")
    assert core.snapshot(0).agent == grid.start  # the env starts its agent there
    (sr, sc), (gr, gc) = grid.start, grid.user_goal
    assert min_steps_to_goal(size) == abs(sr - gr) + abs(sc - gc) == (size - 1) + (size - 1) // 2
