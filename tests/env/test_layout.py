"""Hole layouts: count, placement, solvability (property-based) and uniformity."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seqtrojan.env import EnvConfig, GridSpec, Layout, TrojanGridCore, rng
from seqtrojan.env.codes import ADV_GOAL, HOLE, USER_GOAL
from seqtrojan.env.config import max_holes
from seqtrojan.env.layout import LayoutSampler, layout_tries_needed
from seqtrojan.errors import ConfigError, LayoutError


@st.composite
def grid_and_holes(draw, max_size: int = 15):
    size = draw(st.sampled_from(list(range(5, max_size + 1, 2))))
    holes = draw(st.integers(0, int(0.3 * size * size)))
    return size, holes


@settings(max_examples=25, deadline=None)
@given(grid_and_holes(), st.integers(0, 2**31))
def test_sampled_layouts_have_h_holes_off_start_and_goals_and_are_solvable(grid, seed):
    size, holes = grid
    try:
        core = TrojanGridCore(EnvConfig(size=size, holes=holes), 16, seed=seed)
    except LayoutError:
        return  # solvable layouts too rare for this (size, holes): refused up front, which is also correct
    for i in range(16):
        layout = core.layout(i)
        assert layout.num_holes == holes
        assert layout.cells[0, 0] == ADV_GOAL and layout.cells[0, size - 1] == USER_GOAL
        assert layout.cells[size - 1, size // 2] != HOLE
        assert layout.is_solvable()


@settings(max_examples=30, deadline=None)
@given(grid_and_holes(max_size=13), st.integers(0, 2**31))
def test_bitboard_solvability_matches_reference_bfs(grid, seed):
    size, holes = grid
    holes = min(holes + size, max_holes(size))  # more holes: many unsolvable layouts to check
    sampler = LayoutSampler([GridSpec(size, holes)], view_size=3, max_tries=1, device=torch.device("cpu"))
    keys = rng.seed_keys(torch.arange(64) + seed)
    stages = torch.zeros(64, dtype=torch.int64)
    masks = sampler.hole_masks(keys, stages)
    fast = sampler.solvable(masks, stages)
    p = sampler.side
    for i in range(64):
        cells = np.zeros((size, size), dtype=np.int8)
        cells[0, 0], cells[0, size - 1] = ADV_GOAL, USER_GOAL
        cells[masks[i].view(p, p)[1 : 1 + size, 1 : 1 + size].numpy()] = HOLE
        assert Layout(cells).num_holes == holes
        assert bool(fast[i]) == Layout(cells).is_solvable()


def test_holes_are_uniform_over_candidate_cells():
    size, holes, n = 7, 5, 20000
    sampler = LayoutSampler([GridSpec(size, holes)], view_size=3, max_tries=1, device=torch.device("cpu"))
    masks = sampler.hole_masks(rng.seed_keys(torch.arange(n)), torch.zeros(n, dtype=torch.int64))
    counts = masks.view(n, 9, 9)[:, 1:8, 1:8].sum(0).float()
    expected = n * holes / (size * size - 3)
    candidates = counts[counts > 0]
    assert candidates.numel() == size * size - 3
    chi2 = float(((candidates - expected) ** 2 / expected).sum())
    assert chi2 < 46 * 2.0  # 45 degrees of freedom; a biased sampler is far above this


def test_many_holes_uses_complement_sampling_and_keeps_count():
    grid = GridSpec(7, 30)  # 30 of 46 candidates: the sampler draws the 16 free cells instead
    sampler = LayoutSampler([grid], view_size=3, max_tries=1, device=torch.device("cpu"))
    masks = sampler.hole_masks(rng.seed_keys(torch.arange(200)), torch.zeros(200, dtype=torch.int64))
    assert bool((masks.sum(1) == 30).all())


def test_impossible_hole_count_is_refused_with_n_and_h():
    with pytest.raises(ConfigError, match=r"size=7, holes=37"):
        EnvConfig(size=7, holes=37)


def test_near_impossible_hole_count_fails_fast_naming_n_and_h():
    # (N-1)^2 holes: exactly one solvable layout exists; rejection sampling cannot find it.
    with pytest.raises(LayoutError, match=r"size=7, holes=36"):
        TrojanGridCore(EnvConfig(size=7, holes=36, max_layout_tries=50), 4)


def test_layout_error_when_tries_run_out_mid_run():
    sampler = LayoutSampler([GridSpec(9, 40)], view_size=3, max_tries=1, device=torch.device("cpu"))
    keys = rng.seed_keys(torch.arange(256))
    with pytest.raises(LayoutError, match=r"size=9, holes=40 within 1 tries"):
        sampler.sample(keys, torch.zeros(256, dtype=torch.int64))


def test_layout_from_ascii_rejects_bad_maps():
    with pytest.raises(LayoutError, match="unknown layout symbol"):
        Layout.from_ascii("A . . . U\n. . . . .\n. . X . .\n. . . . .\n. . . . .")
    with pytest.raises(LayoutError, match="top-right"):
        Layout.from_ascii("U . . . A\n. . . . .\n. . . . .\n. . . . .\n. . . . .")
    with pytest.raises(LayoutError, match="start cell"):
        Layout.from_ascii("A . . . U\n. . . . .\n. . . . .\n. . . . .\n. . O . .")


def test_numpy_and_torch_backends_give_identical_results():
    grids = [GridSpec(7, 3), GridSpec(11, 30), GridSpec(9, 50)]  # the last draws its free cells (H > M/2)
    keys = rng.seed_keys(torch.arange(300))
    stages = torch.arange(300) % 3
    results = []
    for backend in ("numpy", "torch"):
        sampler = LayoutSampler(grids, view_size=3, max_tries=1000, device=torch.device("cpu"), backend=backend)
        sampler.attempts_per_round = 3
        masks = sampler.hole_masks(keys, stages)
        easy = stages < 2
        results.append((masks, sampler.solvable(masks, stages), sampler.sample(keys[easy], stages[easy])))
    for a, b in zip(*results):
        assert torch.equal(a, b)


@pytest.mark.parametrize("tries", [1, 2, 5, 29])
def test_a_grid_without_holes_is_accepted_with_any_positive_tries(tries):
    core = TrojanGridCore(EnvConfig(size=5, holes=0, max_layout_tries=tries), 16, seed=3)
    ended = torch.zeros(16, dtype=torch.int64)
    for _ in range(40):  # many episodes end and reset within 40 random steps
        ended += core.step(torch.randint(0, 4, (16,))).done.long()
    assert int(ended.min()) > 0 and torch.equal(core.episode, ended)  # every env reset once per ended episode


def test_one_hole_can_never_cut_a_goal_off_so_one_try_suffices():
    core = TrojanGridCore(EnvConfig(size=5, holes=1, max_layout_tries=1), 64, seed=0)
    for _ in range(40):
        core.step(torch.randint(0, 4, (64,)))
    assert all(core.layout(i).is_solvable() for i in range(64))


def test_layout_tries_rule_is_the_exact_failure_bound():
    assert layout_tries_needed(1.0, holes=0) == layout_tries_needed(0.2, holes=1) == 1
    assert layout_tries_needed(0.9, holes=3) == 14  # 0.1 ** 14 <= e^-30 < 0.1 ** 13
    assert layout_tries_needed(1.0, holes=2) == 5  # none of 1024 failed: assume a 1/1024 failure share
    assert layout_tries_needed(0.0, holes=36) is None
    for fraction in (0.03, 0.3, 0.7, 0.99):
        t = layout_tries_needed(fraction, holes=4)
        assert (1 - fraction) ** t <= np.exp(-30) < (1 - fraction) ** (t - 1)


def test_too_few_tries_for_a_holey_grid_names_the_tries_needed():
    fraction = LayoutSampler([GridSpec(7, 3)], view_size=3, max_tries=1, device=torch.device("cpu")).probe()[0]
    needed = layout_tries_needed(fraction, holes=3)
    assert 1 < needed < 30
    with pytest.raises(LayoutError, match=rf"size=7, holes=3 with max_layout_tries={needed - 1}: .* >= {needed}$"):
        TrojanGridCore(EnvConfig(size=7, holes=3, max_layout_tries=needed - 1), 4)
    core = TrojanGridCore(EnvConfig(size=7, holes=3, max_layout_tries=needed), 256, seed=1)
    for _ in range(60):
        core.step(torch.randint(0, 4, (256,)))
    assert all(core.layout(i).is_solvable() for i in range(256))


@pytest.mark.parametrize("view_size", [1, 2, 4, -1, True])
def test_view_size_must_be_odd_and_at_least_3(view_size):
    with pytest.raises(ConfigError, match=rf"view_size must be an odd integer >= 3, got view_size={view_size!r}"):
        EnvConfig(view_size=view_size)
