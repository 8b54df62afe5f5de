"""MiniGrid's partial view, computed faster: the same observation as ``MiniGridEnv.gen_obs``, without building Grid
objects.

MiniGrid makes each observation by slicing the grid into a new ``Grid`` (a ``Wall()`` per cell outside it), rotating
that grid ``agent_dir + 1`` times (a new ``Grid`` each time), running the occlusion pass through ``Grid.get`` and
encoding the result cell by cell: about 85% of an env step on the Memory task. :func:`fast_gen_obs` reads the
view's cells from the grid's list directly through a cached index map (per grid size, view size, direction and
agent cell: one ``itemgetter`` call picks the whole rotated view), runs the same occlusion pass over plain lists
(cached per pattern of see-through cells: a task's walls repeat, and the pass was 40% of this function on the
Memory task) and encodes each visible object once, straight into bytes (walls and empty cells from constants).
Objects are still asked ``see_behind()`` and ``encode()``, so doors, carried objects and user-defined objects behave
as in MiniGrid; the tests compare the two step by step on several MiniGrid envs.

:func:`use_fast_observation` installs it on one env instance, and only where the env's class keeps MiniGrid's own
``gen_obs``, ``gen_obs_grid`` and ``get_view_exts``; a grid of another class than ``Grid`` falls back to
MiniGrid's method at each call.
"""

from __future__ import annotations

from functools import lru_cache
from operator import itemgetter
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
_EMPTY_BYTES, _UNSEEN_BYTES, _WALL_BYTES = bytes(_EMPTY), bytes(_UNSEEN), bytes(_WALL_CODE)


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


def _visible(view: list[WorldObj | None], size: int) -> tuple[bool, ...]:
    """``Grid.process_vis`` over the rotated view (flat, ``x * size + y``), the agent at (size // 2, size - 1)."""
    see = tuple([cell is None or (type(cell) is not Wall and cell.see_behind()) for cell in view])  # a wall: never
    return _visible_given(see, size)


@lru_cache(maxsize=16384)
def _visible_given(see: tuple[bool, ...], size: int) -> tuple[bool, ...]:
    """The occlusion pass given which view cells can be seen through: a function of that pattern alone, so cached
    (a task's walls repeat from step to step; each object is still asked ``see_behind()`` at every step, so an
    opened door is seen through at once)."""
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
    return tuple(mask)


@lru_cache(maxsize=8192)
def _view_cells(
    width: int, height: int, size: int, agent_dir: int, agent_x: int, agent_y: int
) -> tuple[Any, tuple[int, ...]]:
    """(pick, outside) for the view from cell (agent_x, agent_y) facing ``agent_dir`` in a ``width`` x ``height``
    grid: ``pick(grid.grid)`` is the tuple of the rotated view's cells (flat, ``x * size + y``), with cell 0 standing
    in for the view cells outside the grid, whose positions ``outside`` lists (MiniGrid shows a wall there). The
    extents are ``MiniGridEnv.get_view_exts``'s."""
    half = size // 2
    if agent_dir == 0:  # facing right
        top_x, top_y = agent_x, agent_y - half
    elif agent_dir == 1:  # down
        top_x, top_y = agent_x - half, agent_y
    elif agent_dir == 2:  # left
        top_x, top_y = agent_x - size + 1, agent_y - half
    elif agent_dir == 3:  # up
        top_x, top_y = agent_x - half, agent_y - size + 1
    else:
        raise AssertionError(f"invalid agent direction {agent_dir}")
    index: list[int] = []
    outside: list[int] = []
    for k, (i, j) in enumerate(_view_sources(size, agent_dir + 1)):
        x, y = top_x + i, top_y + j
        if 0 <= x < width and 0 <= y < height:
            index.append(y * width + x)
        else:
            index.append(0)
            outside.append(k)
    if len(index) == 1:  # itemgetter of one index returns the item, not a tuple
        only = index[0]
        return (lambda cells: (cells[only],)), tuple(outside)
    return itemgetter(*index), tuple(outside)


def fast_view(env: MiniGridEnv) -> np.ndarray:
    """The agent's encoded view, (agent_view_size, agent_view_size, 3) uint8, equal to ``env.gen_obs()["image"]``."""
    size = env.agent_view_size
    grid = env.grid
    agent_x, agent_y = env.agent_pos
    pick, outside = _view_cells(grid.width, grid.height, size, int(env.agent_dir), int(agent_x), int(agent_y))
    view: list[WorldObj | None] = list(pick(grid.grid))
    for k in outside:
        view[k] = _OUTSIDE
    agent = (size // 2) * size + size - 1
    if env.see_through_walls:
        view[agent] = env.carrying  # the agent sees what it carries (nothing: an empty cell)
        codes = b"".join(
            [_EMPTY_BYTES if cell is None else _WALL_BYTES if type(cell) is Wall else bytes(cell.encode())
             for cell in view]
        )  # fmt: skip
    else:
        mask = _visible(view, size)  # with the grid's own cell under the agent, as MiniGrid's process_vis
        view[agent] = env.carrying
        codes = b"".join(
            [_UNSEEN_BYTES if not seen else _EMPTY_BYTES if cell is None else _WALL_BYTES if type(cell) is Wall
             else bytes(cell.encode()) for cell, seen in zip(view, mask, strict=True)]
        )  # fmt: skip
    return np.frombuffer(bytearray(codes), dtype=np.uint8).reshape(size, size, 3)


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
