"""FirstActions keeps an env's first discrete actions, numbers and meaning unchanged."""

from __future__ import annotations

import warnings

import gymnasium as gym
import minigrid  # noqa: F401  (registers MiniGrid's ids)
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env
from minigrid.envs.memory import MemoryEnv

from seqtrojan.errors import ConfigError
from seqtrojan.wrappers import FirstActions


def test_three_of_minigrids_seven_actions_step_as_before() -> None:
    plain, kept = gym.make("MiniGrid-MemoryS7-v0"), FirstActions(gym.make("MiniGrid-MemoryS7-v0"), 3)
    assert kept.action_space == spaces.Discrete(3)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*different from the unwrapped")
        check_env(FirstActions(MemoryEnv(size=7), 3), skip_render_check=True)
    a, _ = plain.reset(seed=4)
    b, _ = kept.reset(seed=4)
    rng = np.random.default_rng(0)
    for _ in range(100):
        action = int(rng.integers(3))
        a, ra, ta, ua, _ = plain.step(action)
        b, rb, tb, ub, _ = kept.step(action)
        np.testing.assert_array_equal(a["image"], b["image"])
        assert (ra, ta, ua) == (rb, tb, ub)
        if ta or ua:
            plain.reset(seed=5)
            kept.reset(seed=5)


def test_refusals() -> None:
    with pytest.raises(ConfigError, match=r"env\.num_actions=8 must be 1 to the env's 7 actions"):
        FirstActions(gym.make("MiniGrid-MemoryS7-v0"), 8)
    with pytest.raises(ConfigError, match="needs a Discrete action space starting at 0"):
        FirstActions(gym.make("Pendulum-v1"), 1)
