"""Keeping the first actions of a discrete action space (:class:`FirstActions`)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from gymnasium import spaces

from seqtrojan.errors import ConfigError
from seqtrojan.serde import short_repr


class FirstActions(gym.ActionWrapper):
    """The env with only its first ``n`` discrete actions (``Discrete(n)``, the same numbers).

    MiniGrid's envs take seven actions, of which many tasks use three (turn left, turn right, forward: the first
    three); the others do nothing there and only slow exploration down. MiniGrid's own tasks are unchanged: an
    action keeps its number and meaning."""

    def __init__(self, env: gym.Env, n: int) -> None:
        super().__init__(env)
        space = env.action_space
        if not isinstance(space, spaces.Discrete) or int(space.start) != 0:
            raise ConfigError(f"env.num_actions needs a Discrete action space starting at 0, got {short_repr(space)}")
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= int(space.n):
            raise ConfigError(f"env.num_actions={short_repr(n)} must be 1 to the env's {int(space.n)} actions")
        self.action_space = spaces.Discrete(n)

    def action(self, action: Any) -> Any:
        return action
