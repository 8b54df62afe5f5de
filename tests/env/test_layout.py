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
from seqtrojan.env.layout import LayoutSampler
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
