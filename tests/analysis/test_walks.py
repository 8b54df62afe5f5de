"""Walkable observation sequences: the plausibility checks against real episodes, and the walk search."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.analysis.unintentional import GoalUnits
from seqtrojan.analysis.walks import (
    WalkSearchConfig,
    _codes,
    frame_is_plausible,
    is_walkable,
    random_walks,
    search_walks,
)
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.env import EnvConfig, Layout, TrojanGridCore
from seqtrojan.env.codes import ADV_GOAL, EMPTY, HOLE, TRIGGER, USER_GOAL, WALL


def real_views(size: int, holes: int, seed: int, envs: int = 64, steps: int = 40) -> list[np.ndarray]:
    """Each env's views up to (not including) the step its first episode ended, under random actions."""
    core = TrojanGridCore(EnvConfig(size=size, holes=holes), envs, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    views, alive = [[] for _ in range(envs)], np.ones(envs, bool)
    for _ in range(steps):
        codes = core.observe_codes().numpy()
        for e in np.flatnonzero(alive):
            views[e].append(codes[e])
        done = core.step(torch.randint(0, 4, (envs,), generator=gen)).done.numpy()
        alive &= ~done
    return [np.asarray(v) for v in views]


@pytest.mark.parametrize(("size", "holes"), [(5, 0), (7, 3), (9, 20)])
def test_every_real_episode_is_walkable(size, holes):
    for views in real_views(size, holes, seed=size):
        assert is_walkable(views)


def test_implausible_frames_are_refused():
    start = np.array([[EMPTY] * 3, [EMPTY] * 3, [WALL] * 3])
    assert frame_is_plausible(start)
    corner = np.array([[WALL] * 3, [ADV_GOAL, EMPTY, EMPTY], [EMPTY] * 3])  # the agent right of the goal
    assert frame_is_plausible(corner)
    for bad in (
        np.array([[EMPTY] * 3, [EMPTY, HOLE, EMPTY], [EMPTY] * 3]),  # the agent stands on a hole
        np.array([[EMPTY] * 3, [EMPTY, EMPTY, TRIGGER], [EMPTY] * 3]),  # a trigger is not ordinary
        np.array([[ADV_GOAL, EMPTY, ADV_GOAL], [EMPTY] * 3, [EMPTY] * 3]),  # two adversary goals
        np.array([[EMPTY, WALL, EMPTY], [EMPTY] * 3, [EMPTY] * 3]),  # a wall inside the grid
        np.array([[WALL] * 3, [USER_GOAL, EMPTY, EMPTY], [EMPTY] * 3]),  # the user's goal at the left
        np.array([[WALL] * 3, [EMPTY] * 3, [WALL] * 3]),  # both the top and bottom border
    ):  # fmt: skip
        assert not frame_is_plausible(bad)


def test_views_that_do_not_follow_by_a_move_are_not_walkable():
    (views, *_) = [v for v in real_views(9, 8, seed=3) if len(v) >= 6]
    assert is_walkable(views)
    two_up = views[[0, 0]].copy()
    two_up[1] = [EMPTY] * 6 + [HOLE] * 3  # the bottom wall turned into holes: no move explains it
    assert frame_is_plausible(two_up[1].reshape(3, 3))
    assert not is_walkable(two_up)
    assert not is_walkable(np.array([[EMPTY] * 4 + [HOLE] + [EMPTY] * 4]))  # standing in a hole


def test_random_walks_start_at_the_start_move_one_cell_and_stay_below_the_top_row():
    walks = random_walks(9, 30, 16, np.random.default_rng(0))
    assert (walks[:, 0] == (8, 4)).all()
    assert (np.abs(np.diff(walks, axis=1)).sum(-1) == 1).all()
    assert (walks[..., 0] >= 1).all() and (walks[..., 1] >= 0).all() and (walks[..., 1] < 9).all()
    assert (np.diff(walks[..., 0], axis=1) <= 0).all()  # never a step down


def test_walk_search_gives_walkable_views_of_its_own_grids():
    cfg = ExperimentConfig(agent=AgentConfig(lstm_sizes=(16, 8)))
    torch.manual_seed(0)
    agent = build_agent(cfg).eval()
    goal = GoalUnits(0, "c", (0, 1, 2), (0.0, 0.0, 0.0), (0.5, -0.5, 0.5))
    search = WalkSearchConfig(size=9, holes=6, length=10, restarts=6, steps=20)
    result, codes, grids = search_walks(agent, goal, search)
    assert codes.shape == (6, 10, 9) and grids.shape == (6, 9, 9)
    assert result.walkable == 6 and all(is_walkable(c) for c in codes)
    found = [a >= search.success_at for a in result.rounded_activation]
    assert len(found) == 6 and result.found == sum(found)
    assert result.solvable == sum(Layout(g.astype(np.int8)).is_solvable() for g, f in zip(grids, found) if f)
    assert result.target_density == pytest.approx(6 / 78)
    # Revealed density, recomputed from the rounded grids; a search started at density 0.5 with no penalty keeps
    # holes in the revealed cells (the penalised one above rounds every cell to empty: density 0).
    dense = WalkSearchConfig(size=9, density=0.5, density_weight=0.0, length=10, restarts=6, steps=20)
    dense_result, _, dense_grids = search_walks(agent, goal, dense)
    walks = random_walks(9, 10, 6, np.random.default_rng(0))  # both searches' walks (seed 0)
    for res, res_grids in ((result, grids), (dense_result, dense_grids)):
        for grid, walk, density in zip(res_grids, walks, res.revealed_density, strict=True):
            seen = np.zeros((9, 9), bool)  # free cells the walk's 3x3 views reveal: not a goal, not on the walk
            for r, c in walk:
                seen[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2] = True
            seen[walk[:, 0], walk[:, 1]] = False
            seen[0, 0] = seen[0, 8] = False
            assert density == pytest.approx((grid[seen] == HOLE).mean(), abs=1e-6)
    assert min(dense_result.revealed_density) > 0.1  # the dense case really has revealed holes to count
    for grid in grids:  # goals where the grid has them, the start cell free
        assert grid[0, 0] == ADV_GOAL and grid[0, 8] == USER_GOAL and grid[8, 4] == EMPTY
        assert set(np.unique(grid)) <= {EMPTY, HOLE, USER_GOAL, ADV_GOAL}
        Layout(grid.astype(np.int8))  # a valid layout
    assert (_codes(grids, random_walks(9, 10, 6, np.random.default_rng(0)), 3) == codes).all()
