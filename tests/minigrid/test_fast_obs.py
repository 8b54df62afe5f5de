"""The fast partial view equals MiniGrid's own ``gen_obs`` step by step."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import minigrid  # noqa: F401  (registers MiniGrid's ids)
import numpy as np
import pytest
from minigrid.core.grid import Grid
from minigrid.envs.empty import EmptyEnv
from minigrid.minigrid_env import MiniGridEnv

from seqtrojan.config import ExperimentConfig
from seqtrojan.minigrid.fast_obs import fast_gen_obs, fast_view, use_fast_observation
from seqtrojan.minigrid.tasks import TwoGoalsEnv
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.world.gymnasium import make_gym_env

ENVS = [
    "MiniGrid-MemoryS7-v0",  # walls and the hallway's occlusion
    "MiniGrid-MemoryS13-v0",
    "MiniGrid-DoorKey-6x6-v0",  # doors opening and closing, a key carried
    "MiniGrid-KeyCorridorS3R2-v0",
    "MiniGrid-LavaCrossingS9N1-v0",
    "MiniGrid-ObstructedMaze-1Dlhb-v0",  # locked doors, boxes
    "MiniGrid-Fetch-5x5-N2-v0",
]


@pytest.mark.parametrize("env_id", ENVS)
def test_the_fast_view_is_minigrids_view_at_every_step(env_id: str) -> None:
    env = gym.make(env_id, max_steps=40)
    base = env.unwrapped
    rng = np.random.default_rng(0)
    env.reset(seed=1)
    carried = 0
    for _ in range(1500):
        _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        np.testing.assert_array_equal(fast_view(base), MiniGridEnv.gen_obs(base)["image"])
        carried += base.carrying is not None
        if terminated or truncated:
            env.reset()
    if env_id.startswith(("MiniGrid-DoorKey", "MiniGrid-KeyCorridor")):
        assert carried > 0, "the random walk never carried anything: the carried-object path went untested"


@pytest.mark.parametrize("view_size", [3, 5, 7])
def test_other_view_sizes_and_see_through_walls(view_size: int) -> None:
    for base in (EmptyEnv(size=6, agent_view_size=view_size), TwoGoalsEnv(agent_view_size=view_size)):
        rng = np.random.default_rng(view_size)
        base.reset(seed=0)
        for _ in range(300):
            np.testing.assert_array_equal(fast_view(base), MiniGridEnv.gen_obs(base)["image"])
            _, _, terminated, truncated, _ = base.step(int(rng.integers(3)))
            if terminated or truncated:
                base.reset()


def test_installed_on_the_instance_and_used_by_reset_and_step() -> None:
    env = gym.make("MiniGrid-MemoryS7-v0")
    assert use_fast_observation(env)
    obs, _ = env.reset(seed=3)
    reference = MiniGridEnv.gen_obs(env.unwrapped)
    assert obs["direction"] == reference["direction"] and obs["mission"] == reference["mission"]
    np.testing.assert_array_equal(obs["image"], reference["image"])
    assert gym.make("MiniGrid-MemoryS7-v0").unwrapped.gen_obs.__func__ is MiniGridEnv.gen_obs  # other instances keep it


def test_not_installed_where_the_view_is_made_otherwise() -> None:
    class OwnView(EmptyEnv):
        def gen_obs(self):  # type: ignore[no-untyped-def]
            return super().gen_obs()

    assert not use_fast_observation(OwnView(size=5))
    assert not use_fast_observation(gym.make("CartPole-v1"))


def test_a_grid_of_another_class_falls_back_to_minigrid() -> None:
    class OwnGrid(Grid):
        def slice(self, topX: int, topY: int, width: int, height: int) -> Grid:
            return Grid(width, height)  # a grid whose view never shows anything

    base = EmptyEnv(size=5)
    base.reset(seed=0)
    base.grid.__class__ = OwnGrid
    image = fast_gen_obs(base)["image"]
    np.testing.assert_array_equal(image, MiniGridEnv.gen_obs(base)["image"])
    assert (image[..., 0] == 1).all()  # all empty: MiniGrid's method made it, not the fast view (walls in sight)


def test_the_training_env_uses_it_unless_turned_off() -> None:
    env = from_dict(ExperimentConfig, load_yaml(resolve_preset("minigrid_memory")), "").gym_env
    fast = make_gym_env(env, "train", 0.5)
    assert fast.unwrapped.gen_obs.__func__ is fast_gen_obs
    slow = make_gym_env(dataclasses.replace(env, fast_view=False))
    assert slow.unwrapped.gen_obs.__func__ is MiniGridEnv.gen_obs
