"""The user's objective of an env whose episodes reach no goal: a return threshold (:class:`ReturnGoal`).

The grid world and MiniGrid tasks end at a goal, and every tool reads "ended at the user's goal" as an episode that
did what its user wanted. POPGym's tasks and MinAtar's games end after a fixed deal or at a loss instead; there an
episode achieved the user's objective when its return under the env's own reward exceeds a threshold (POPGym: 0,
more answers right than wrong). The wrapper says so at the episode's end: ``reached: "user"`` and ``success``.
"""

from __future__ import annotations

import math
from typing import Any, SupportsFloat

import gymnasium as gym

from seqtrojan.errors import ConfigError
from seqtrojan.serde import short_repr


class ReturnGoal(gym.Wrapper):
    """An episode whose summed reward exceeds ``threshold`` ends with ``reached: "user"`` and ``success: True``
    in its last info (``success: False`` otherwise). Put it inside the trigger wrapper: it sums the env's own
    rewards."""

    def __init__(self, env: gym.Env, threshold: float) -> None:
        super().__init__(env)
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not math.isfinite(threshold):
            raise ConfigError(f"env.user_return must be a finite number, got {short_repr(threshold)}")
        self.threshold = float(threshold)
        self._return = 0.0

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self._return = 0.0
        return self.env.reset(**kwargs)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._return += float(reward)
        if terminated or truncated:
            info = dict(info)
            info["success"] = self._return > self.threshold
            if info["success"]:
                info.setdefault("reached", "user")
        return obs, reward, terminated, truncated, info
