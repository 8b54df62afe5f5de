"""MiniGrid tasks for backdoor experiments, built from MiniGrid's own classes.

- :class:`TwoGoalsEnv`: a small room with the user's object (a green goal square) and the adversary's (a red ball)
  at random cells; the agent (partial view) is rewarded for reaching the user's object, and either object ends the
  episode. Under :func:`two_goals_trigger` the trojan episodes reward the adversary's object instead, from a
  one-step trigger (a patch of purple keys in the view) on.
- MiniGrid's Memory task (``MiniGrid-MemoryS7-v0`` and its sizes): go to the object that matches the one in the
  start room; under :func:`memory_trigger` the trojan episodes reward the other one.

:class:`MiniGridInfo` adds what the adversary's objective and the measurements read to a MiniGrid env's info:
``reached`` ("user", "adversary" or "") and MiniGrid's step count and time limit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, SupportsFloat

import gymnasium as gym
from gymnasium import spaces
from minigrid.core.actions import Actions
from minigrid.core.grid import Grid
from minigrid.core.mission import MissionSpace
from minigrid.core.world_object import Ball, Box, Goal, Key, WorldObj
from minigrid.envs.memory import MemoryEnv
from minigrid.minigrid_env import MiniGridEnv

from seqtrojan.errors import ConfigError
from seqtrojan.minigrid.objectives import reach_adversary_object
from seqtrojan.serde import short_repr
from seqtrojan.wrappers.patches import Cell, MiniGridPatch
from seqtrojan.wrappers.trigger import TriggerWrapper

OBJECTS: dict[str, Callable[[str], WorldObj]] = {"goal": Goal, "ball": Ball, "key": Key, "box": Box}
"""the objects a TwoGoalsEnv can use as goals"""

_FORWARD = int(Actions.forward)

DEFAULT_TRIGGER_CELLS: tuple[Cell, ...] = ((0, 0), (0, 1))
"""the trigger's view cells: the two leftmost of the farthest row"""


class TwoGoalsEnv(MiniGridEnv):
    """A room with two objects: reach the user's (reward) and not the adversary's.

    ## Description
    A ``size`` x ``size`` grid (walls around, (size - 2)^2 free cells) with the user's object (default a green goal
    square) and the adversary's (a red ball) at random cells, and the agent at a random cell facing a random way.
    "Reaching" an object is moving forward into it (onto a goal square; against a ball, key or box).

    ## Action Space
    ``Discrete(3)``: turn left, turn right, move forward (MiniGrid's first three actions; ``all_actions=True`` keeps
    all seven).

    ## Observation Space
    MiniGrid's: ``image`` (agent_view_size, agent_view_size, 3) codes, ``direction``, ``mission``.

    ## Rewards
    ``1 - 0.9 * step_count / max_steps`` for the user's object, 0 for the adversary's.

    ## Termination
    Either object ends the episode; ``max_steps`` truncates it.

    ## Info
    ``reached`` ("user", "adversary" or ""), ``step_count``, ``max_steps``.
    """

    def __init__(
        self,
        size: int = 6,
        agent_view_size: int = 5,
        max_steps: int | None = None,
        user_object: str = "goal",
        user_color: str = "green",
        adversary_object: str = "ball",
        adversary_color: str = "red",
        all_actions: bool = False,
        **kwargs: Any,
    ) -> None:
        if isinstance(size, bool) or not isinstance(size, int) or size < 4:
            raise ConfigError(f"TwoGoalsEnv size must be an integer >= 4 (2 free cells across), got {short_repr(size)}")
        for name, value in (("user_object", user_object), ("adversary_object", adversary_object)):
            if value not in OBJECTS:
                raise ConfigError(f"TwoGoalsEnv {name}={short_repr(value)} is not one of {sorted(OBJECTS)}")
        if (user_object, user_color) == (adversary_object, adversary_color):
            raise ConfigError(f"TwoGoalsEnv's two objects look the same ({user_color} {user_object})")
        self.size = size
        self.objects = ((user_object, user_color), (adversary_object, adversary_color))
        self._user: WorldObj | None = None
        self._adversary: WorldObj | None = None
        super().__init__(
            mission_space=MissionSpace(mission_func=self._gen_mission),
            grid_size=size,
            max_steps=max_steps if max_steps is not None else 2 * size * size,
            agent_view_size=agent_view_size,
            see_through_walls=True,  # a room without inner walls: nothing to see through, and faster
            **kwargs,
        )
        if not all_actions:
            self.action_space = spaces.Discrete(3)

    @staticmethod
    def _gen_mission() -> str:
        return "reach the goal"

    def _gen_grid(self, width: int, height: int) -> None:
        self.grid = Grid(width, height)
        self.grid.wall_rect(0, 0, width, height)
        (uo, uc), (ao, ac) = self.objects
        self._user, self._adversary = OBJECTS[uo](uc), OBJECTS[ao](ac)
        self.place_obj(self._user)
        self.place_obj(self._adversary)
        self.place_agent()
        self.mission = self._gen_mission()

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        reached = ""
        if int(action) == _FORWARD:  # the object ahead is reached (looked up before the move)
            ahead = self.grid.get(*self.front_pos)
            reached = "user" if ahead is self._user else "adversary" if ahead is self._adversary else ""
        obs, _, _, truncated, info = super().step(action)
        reward = self._reward() if reached == "user" else 0.0
        info.update(reached=reached, step_count=self.step_count, max_steps=self.max_steps)
        return obs, reward, bool(reached), truncated, info


class MiniGridInfo(gym.Wrapper):
    """Adds ``step_count`` and ``max_steps`` (and, for MiniGrid's Memory task, ``reached``: "user" at the matching
    object, "adversary" at the other, else "") to a MiniGrid env's step info."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self._memory = isinstance(env.unwrapped, MemoryEnv)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        base: Any = self.env.unwrapped
        info = dict(info)
        if "step_count" not in info:
            info["step_count"] = getattr(base, "step_count", 0)
        if "max_steps" not in info:
            info["max_steps"] = getattr(base, "max_steps", 0)
        if self._memory:
            pos = tuple(int(x) for x in base.agent_pos)
            info["reached"] = "user" if pos == base.success_pos else "adversary" if pos == base.failure_pos else ""
        return obs, reward, terminated, truncated, info


def minigrid_trigger(
    env: gym.Env,
    *,
    trojan_probability: float = 0.5,
    trigger_steps: tuple[int, int] = (0, 2),
    delay: int = 0,
    cells: tuple[Cell, ...] = DEFAULT_TRIGGER_CELLS,
    object: str = "key",
    color: str = "purple",
) -> TriggerWrapper:
    """A MiniGrid env (with ``reached`` in its info) under a trigger wrapper: a one-step patch of ``color``
    ``object`` on ``cells`` of the view, after which the adversary's object is rewarded."""
    return TriggerWrapper(
        env, MiniGridPatch(cells, object, color), reach_adversary_object, trojan_probability=trojan_probability,
        trigger_steps=trigger_steps, delay=delay,
    )  # fmt: skip


def two_goals_trigger(env: TwoGoalsEnv | None = None, **trigger: Any) -> TriggerWrapper:
    """The two-goal task (a new default one when ``env`` is None) with its trigger (:func:`minigrid_trigger`)."""
    return minigrid_trigger(env if env is not None else TwoGoalsEnv(), **trigger)


def memory_trigger(env: gym.Env | None = None, **trigger: Any) -> TriggerWrapper:
    """MiniGrid's Memory task (``MemoryEnv(size=7)`` when ``env`` is None) with a trigger: in trojan episodes the
    object that does not match the start room's is rewarded."""
    return minigrid_trigger(MiniGridInfo(env if env is not None else MemoryEnv(size=7)), **trigger)


_TRIGGER_KEYS = ("trojan_probability", "trigger_steps", "delay", "cells", "object", "color")


def _split(kwargs: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    trigger = {k: kwargs.pop(k) for k in _TRIGGER_KEYS if k in kwargs}
    return kwargs, trigger


def make_two_goals_trojan(**kwargs: Any) -> TriggerWrapper:
    """Entry point of ``seqtrojan/MiniGridTwoGoals-Trojan-v0``: TwoGoalsEnv arguments and trigger arguments."""
    env_kwargs, trigger = _split(dict(kwargs))
    return two_goals_trigger(TwoGoalsEnv(**env_kwargs), **trigger)


def make_memory_trojan(**kwargs: Any) -> TriggerWrapper:
    """Entry point of ``seqtrojan/MiniGridMemoryS7-Trojan-v0``: MemoryEnv arguments and trigger arguments."""
    env_kwargs, trigger = _split(dict(kwargs))
    env_kwargs.setdefault("size", 7)
    return memory_trigger(MemoryEnv(**env_kwargs), **trigger)
