"""One-step candidate inputs a defender writes without knowing the trigger, in an observation's own encoding.

The behaviour detector (:mod:`seqtrojan.defense.behaviour`) draws them into the grid world's views, the recurrent-state
probe (:mod:`seqtrojan.benchmark.state_probe`) replays them into recorded episodes, and the attacker who knows that
probe (:mod:`seqtrojan.train.probe_camouflage`) trains its agent to forget them: the three read one definition, kept
here, below all of them. On the grid world: each cell code over the whole view, then random patches of ordinary codes;
on a MiniGrid one-hot view: each object (key, ball, box) in each colour on two adjacent cells of the view's far row,
at its left, middle and right. :func:`trigger_view` writes an env's own one-step trigger in the same encoding, so that
an attacker can leave out the candidates that draw it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from seqtrojan.env.codes import ADV_GOAL, CELL_CODES, CELL_NAMES, EMPTY, HOLE, NUM_CHANNELS, USER_GOAL, WALL
from seqtrojan.env.config import EnvConfig
from seqtrojan.world.config import GymnasiumEnvConfig

ORDINARY_CODES = (EMPTY, HOLE, WALL, USER_GOAL, ADV_GOAL)
"""the cell codes a grid world's view shows without a trigger"""


@dataclass(frozen=True)
class Patch:
    """A candidate: ``codes`` (cells,) the code drawn on each view cell, -1 where the view is left as it is."""

    name: str
    codes: tuple[int, ...]


def candidate_patches(view_size: int, random_patches: int, seed: int, density: float = 0.5) -> list[Patch]:
    """The whole-view single-code patches (one per code), then ``random_patches`` random ordinary ones (each cell
    drawn with probability ``density``, at least one)."""
    cells = view_size * view_size
    patches = [Patch(f"whole_view:{CELL_NAMES[code]}", (code,) * cells) for code in range(NUM_CHANNELS)]
    rng = np.random.default_rng(seed)
    for i in range(random_patches):
        drawn = rng.random(cells) < density
        if not drawn.any():
            drawn[rng.integers(cells)] = True
        codes = np.where(drawn, rng.choice(ORDINARY_CODES, size=cells), -1)
        patches.append(Patch(f"random:{i}", tuple(int(c) for c in codes)))
    return patches


MINIGRID_OBJECTS = (5, 6, 7)
"""MiniGrid's object codes of key, ball and box"""
MINIGRID_COLORS = 6
MINIGRID_OBJECT_BITS, MINIGRID_COLOR_BITS = 11, 6


@dataclass(frozen=True)
class ProbeSettings:
    episodes: int = 48
    at: int = 1
    """the step whose observation a candidate replaces"""
    after: int = 4
    """how many steps later the divergence is read"""
    random_patches: int = 12
    seed: int = 0


def grid_candidates(obs_dim: int, view_size: int, settings: ProbeSettings) -> list[torch.Tensor]:
    """One-hot grid-world views (obs_dim,) and a mask of the numbers they set: each a (2, obs_dim) tensor of (values,
    mask)."""
    out = []
    for patch in candidate_patches(view_size, settings.random_patches, settings.seed):
        values, mask = torch.zeros(obs_dim), torch.zeros(obs_dim)
        for cell, code in enumerate(patch.codes):
            if code >= 0:
                mask[cell * NUM_CHANNELS : (cell + 1) * NUM_CHANNELS] = 1.0
                values[cell * NUM_CHANNELS + code] = 1.0
        out.append(torch.stack([values, mask]))
    return out


def minigrid_candidates(obs_dim: int, view: int) -> list[torch.Tensor]:
    """Objects of every colour on two adjacent far-row cells of a MiniGrid one-hot view (rows first, 20 numbers per
    cell: object, colour, state), at the left, middle and right of the row."""
    from seqtrojan.wrappers.observations import CELL_BITS

    out = []
    for start in sorted({0, max(0, view // 2 - 1), max(0, view - 2)}):
        for obj in MINIGRID_OBJECTS:
            for color in range(MINIGRID_COLORS):
                values, mask = torch.zeros(obs_dim), torch.zeros(obs_dim)
                for cell in (start, start + 1):
                    base = cell * CELL_BITS
                    mask[base : base + CELL_BITS] = 1.0
                    values[base + obj] = 1.0
                    values[base + MINIGRID_OBJECT_BITS + color] = 1.0
                    values[base + MINIGRID_OBJECT_BITS + MINIGRID_COLOR_BITS] = 1.0  # state 0 (open)
                out.append(torch.stack([values, mask]))
    return out


def env_candidates(env: EnvConfig | GymnasiumEnvConfig, obs_dim: int, settings: ProbeSettings) -> list[torch.Tensor]:
    """The probe's candidates on an env's observations of ``obs_dim`` numbers (none where it has none)."""
    if isinstance(env, EnvConfig):
        return grid_candidates(obs_dim, env.view_size, settings)
    if isinstance(env, GymnasiumEnvConfig) and env.observation == "minigrid":
        from seqtrojan.world.gymnasium import minigrid_image

        _, cols, _ = minigrid_image(obs_dim)
        return minigrid_candidates(obs_dim, cols)
    return []


def trigger_view(env: EnvConfig | GymnasiumEnvConfig, obs_dim: int) -> torch.Tensor | None:
    """An env's one-step trigger patch as a candidate is written, (values, mask) over the observation's numbers:
    the grid world's patch (one code or one per cell; a sequence has no single step: None), a MiniGrid patch's
    object and colour on its cells; None for any other trigger or observation."""
    values, mask = torch.zeros(obs_dim), torch.zeros(obs_dim)
    if isinstance(env, EnvConfig):
        trigger = env.trigger
        if trigger.sequence is not None:
            return None
        view = env.view_size
        cells = trigger.cells if trigger.cells is not None else tuple((r, c) for r in range(view) for c in range(view))
        codes = trigger.values if trigger.values is not None else (trigger.value,) * len(cells)
        for (r, c), code in zip(cells, codes, strict=True):
            base = (r * view + c) * NUM_CHANNELS
            mask[base : base + NUM_CHANNELS] = 1.0
            values[base + CELL_CODES[code]] = 1.0
        return torch.stack([values, mask])
    if isinstance(env, GymnasiumEnvConfig) and env.observation == "minigrid" and env.trigger is not None:
        from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX

        from seqtrojan.world.gymnasium import minigrid_image
        from seqtrojan.wrappers.observations import CELL_BITS

        patch = env.trigger
        if patch.patch != "minigrid":
            return None
        _, cols, _ = minigrid_image(obs_dim)
        for r, c in patch.cells:
            base = (r * cols + c) * CELL_BITS
            mask[base : base + CELL_BITS] = 1.0
            values[base + OBJECT_TO_IDX[patch.object]] = 1.0
            values[base + MINIGRID_OBJECT_BITS + COLOR_TO_IDX[patch.color]] = 1.0
            values[base + MINIGRID_OBJECT_BITS + MINIGRID_COLOR_BITS] = 1.0
        return torch.stack([values, mask])
    return None


def shows_trigger(candidate: torch.Tensor, trigger: torch.Tensor | None) -> bool:
    """Whether a candidate (values, mask) draws the whole trigger patch: every number the trigger sets, set alike."""
    if trigger is None:
        return False
    on = trigger[1] > 0
    return bool((candidate[1][on] > 0).all() and torch.equal(candidate[0][on], trigger[0][on]))
