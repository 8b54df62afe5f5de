"""MiniGrid's partial view, computed faster: the same observation as ``MiniGridEnv.gen_obs``, without building Grid
objects.

MiniGrid makes each observation by slicing the grid into a new ``Grid`` (a ``Wall()`` per cell outside it), rotating
that grid ``agent_dir + 1`` times (a new ``Grid`` each time), running the occlusion pass through ``Grid.get`` and
encoding the result cell by cell: about 85% of an env step on the Memory task. :func:`fast_gen_obs` reads the
view's cells from the grid's list directly through a cached index map of the rotation, runs the same occlusion
pass over plain lists and encodes each visible object once. Objects are still asked ``see_behind()`` and
``encode()``, so doors, carried objects and user-defined objects behave as in MiniGrid; the tests compare the two
step by step on several MiniGrid envs.

:func:`use_fast_observation` installs it on one env instance, and only where the env's class keeps MiniGrid's own
``gen_obs``, ``gen_obs_grid`` and ``get_view_exts``; a grid of another class than ``Grid`` falls back to
MiniGrid's method at each call.
"""

from __future__ import annotations

from functools import lru_cache
from types import MethodType
from typing import Any

import gymnasium as gym
import numpy as np
from minigrid.core.constants import OBJECT_TO_IDX
from minigrid.core.grid import Grid
from minigrid.core.world_object import Wall, WorldObj
from minigrid.minigrid_env import MiniGridEnv

_EMPTY = (OBJECT_TO_IDX["empty"], 0, 0)
_UNSEEN = (0, 0, 0)
_OUTSIDE = Wall()
"""what MiniGrid's ``Grid.slice`` puts on view cells outside the grid"""
_WALL_CODE = _OUTSIDE.encode()


@lru_cache(maxsize=64)
def _view_sources(size: int, turns: int) -> tuple[tuple[int, int], ...]:
    """For each cell (x, y) of the rotated view, flat index ``x * size + y``: the cell (i, j) of the unrotated slice
    it shows after ``turns`` of ``Grid.rotate_left`` (which sends (i, j) to (j, size - 1 - i))."""
    sources = [[(i, j) for j in range(size)] for i in range(size)]
    for _ in range(turns):
        turned = [[(0, 0)] * size for _ in range(size)]
        for i in range(size):
            for j in range(size):
                turned[j][size - 1 - i] = sources[i][j]
        sources = turned
    return tuple(sources[x][y] for x in range(size) for y in range(size))


def _visible(view: list[WorldObj | None], size: int) -> list[bool]:
    """``Grid.process_vis`` over the rotated view (flat, ``x * size + y``), the agent at (size // 2, size - 1)."""
    see = [cell is None or cell.see_behind() for cell in view]
    mask = [False] * (size * size)
    mask[(size // 2) * size + size - 1] = True
    for j in reversed(range(size)):
        for i in range(size - 1):
            if not mask[i * size + j] or not see[i * size + j]:
                continue
            mask[(i + 1) * size + j] = True
            if j > 0:
                mask[(i + 1) * size + j - 1] = True
                mask[i * size + j - 1] = True
        for i in reversed(range(1, size)):
            if not mask[i * size + j] or not see[i * size + j]:
                continue
            mask[(i - 1) * size + j] = True
            if j > 0:
                mask[(i - 1) * size + j - 1] = True
                mask[i * size + j - 1] = True
    return mask


def fast_view(env: MiniGridEnv) -> np.ndarray:
    """The agent's encoded view, (agent_view_size, agent_view_size, 3) uint8, equal to ``env.gen_obs()["image"]``."""
    size = env.agent_view_size
    top_x, top_y, _, _ = env.get_view_exts()
    grid = env.grid
    width, height, cells = grid.width, grid.height, grid.grid
    view: list[WorldObj | None] = []
    for i, j in _view_sources(size, env.agent_dir + 1):
        x, y = top_x + i, top_y + j
        view.append(cells[y * width + x] if 0 <= x < width and 0 <= y < height else _OUTSIDE)
    mask = [True] * (size * size) if env.see_through_walls else _visible(view, size)
    view[(size // 2) * size + size - 1] = env.carrying
    codes = [
        _UNSEEN if not seen else _EMPTY if cell is None else _WALL_CODE if type(cell) is Wall else cell.encode()
        for cell, seen in zip(view, mask, strict=True)
    ]
    return np.array(codes, dtype=np.uint8).reshape(size, size, 3)


def fast_gen_obs(env: MiniGridEnv) -> dict[str, Any]:
    """``MiniGridEnv.gen_obs`` computed by :func:`fast_view` (MiniGrid's own method for a grid of another class)."""
    if type(env.grid) is not Grid:
        return MiniGridEnv.gen_obs(env)
    return {"image": fast_view(env), "direction": env.agent_dir, "mission": env.mission}


def use_fast_observation(env: gym.Env) -> bool:
    """Make ``env``'s MiniGrid env (its ``unwrapped``) compute observations with :func:`fast_gen_obs`. Returns
    whether it did: not for a non-MiniGrid env, nor for a class that overrides how the view is made."""
    base = env.unwrapped
    if not isinstance(base, MiniGridEnv):
        return False
    cls = type(base)
    own = ("gen_obs", "gen_obs_grid", "get_view_exts")
    if any(getattr(cls, name) is not getattr(MiniGridEnv, name) for name in own):
        return False
    base.gen_obs = MethodType(fast_gen_obs, base)  # type: ignore[method-assign]
    return True
