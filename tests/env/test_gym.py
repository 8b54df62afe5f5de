"""The Gymnasium contract: check_env, registered ids, rendering, bad input; and the batched-env seam both kinds of
env answer (the grid core, a Gymnasium env)."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import seqtrojan  # noqa: F401
from seqtrojan.env import EnvConfig, Layout, TrojanGridCore
from seqtrojan.env.gym_env import TrojanGridEnv
from seqtrojan.env.registration import REGISTERED
from seqtrojan.errors import ConfigError, ShapeError
from seqtrojan.world import BatchedEnv, EnvSpec, env_spec, make_batched_env
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig


@pytest.mark.parametrize("env_id", sorted(REGISTERED))
def test_registered_envs_pass_check_env(env_id):
    env = gym.make(env_id, render_mode="ansi")
    check_env(env.unwrapped, skip_render_check=False)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (54,) and obs.dtype == np.float32


def test_docstring_lists_exactly_the_registered_ids():
    documented = set(re.findall(r"``(seqtrojan/[\w.-]+)``", TrojanGridEnv.__doc__))
    assert documented == set(REGISTERED)


def test_render_modes():
    env = gym.make("seqtrojan/Trojan-v0", render_mode="rgb_array")
    env.reset(seed=1)
    for _ in range(3):
        env.step(0)
    img = env.render()
    assert img.shape == (7 * 16, 7 * 16, 3) and img.dtype == np.uint8
    text = gym.make("seqtrojan/Normal-v0", render_mode="ansi")
    text.reset(seed=1)
    out = text.render()
    assert "@" in out and out.startswith("t=0/28 env=normal")


def test_rendered_trigger_and_trajectory():
    env = TrojanGridEnv(render_mode="ansi", holes=0)
    env.reset(seed=0, options={"layout": Layout.empty(7), "on_step": 2})
    env.step(0)
    env.step(0)
    text = env.render()
    assert (
        "[ON visible]" in text and text.count("T") == 8 and text.count("*") == 1
    )  # the trigger hides the first visited cell
    env.step(0)
    assert "T" not in env.render().split("\n", 1)[1]


def test_vector_env_spaces_and_autoreset_mode():
    venv = gym.make_vec("seqtrojan/Normal-v0", num_envs=3, vectorization_mode="vector_entry_point")
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (3, 54)
    assert venv.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    with pytest.raises(ShapeError, match=r"shape \(3,\)"):
        venv.step(np.zeros(4, dtype=np.int64))


def test_step_after_episode_end_needs_reset():
    env = TrojanGridEnv(holes=0)
    layout = Layout.empty(7).cells.copy()
    layout[4, 3] = 1  # a hole two cells above the start
    env.reset(seed=0, options={"layout": Layout(layout)})
    env.step(0)
    _, reward, terminated, _, info = env.step(0)
    assert terminated and reward == -1.0 and info["outcome"] == "hole"
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_bad_actions_are_refused_with_the_value():
    core = TrojanGridCore(EnvConfig(), 4)
    with pytest.raises(ShapeError, match=r"shape \(4,\), got \(2,\)"):
        core.step(torch.zeros(2, dtype=torch.int64))
    with pytest.raises(ShapeError, match="integers"):
        core.step(torch.zeros(4))
    with pytest.raises(ShapeError, match="action 4 is out of range"):
        core.step(torch.tensor([0, 1, 4, 2]))
    with pytest.raises(ShapeError, match="torch tensor"):
        core.step([0, 1, 2, 3])
    env = TrojanGridEnv()
    env.reset(seed=0)
    with pytest.raises(ConfigError, match="action 7"):
        env.step(7)


def test_bad_env_arguments_are_refused():
    with pytest.raises(ConfigError, match="unknown env argument"):
        TrojanGridEnv(colour="red")
    with pytest.raises(ConfigError, match="render_mode"):
        TrojanGridEnv(render_mode="human")
    with pytest.raises(ConfigError, match="num_envs"):
        TrojanGridCore(EnvConfig(), 0)
    with pytest.raises(ConfigError, match="phase"):
        TrojanGridCore(EnvConfig(), 1, phase="test")
    with pytest.raises(ConfigError, match="trojan probability"):
        TrojanGridCore(EnvConfig(), 1, trojan_probability=1.5)


def test_config_dict_is_accepted_and_checked():
    env = TrojanGridEnv({"size": 9, "holes": 4, "trigger": {"duration": 2}})
    assert env.config.size == 9 and env.config.trigger.duration == 2
    with pytest.raises(ConfigError, match=r"unknown config key\(s\) \['durration'\] in env.trigger"):
        TrojanGridEnv({"trigger": {"durration": 2}})


def test_info_leaves_the_episode_key_to_episode_statistics_wrappers():
    env = TrojanGridEnv(size=5, holes=0)
    _, info = env.reset(seed=0)
    assert "episode" not in info and info["episode_index"] == 0
    env = gym.wrappers.RecordEpisodeStatistics(gym.make("seqtrojan/Normal-v0", size=5, holes=0))
    for episode in range(3):
        _, info = env.reset(seed=episode) if episode == 0 else env.reset()
        assert "episode" not in info and info["episode_index"] == episode
        steps, total, done = 0, 0.0, False
        while not done:
            _, reward, terminated, truncated, info = env.step(0)  # up: into the top wall, then out of time
            steps, total, done = steps + 1, total + reward, terminated or truncated
            assert done or "episode" not in info
        assert isinstance(info["episode"], dict) and set(info["episode"]) == {"r", "l", "t"}
        assert info["episode"]["l"] == steps == 20 and info["episode"]["r"] == total == -1.0


# ---------------------------------------------------------------------- the batched-env seam (seqtrojan.world)

TWO_GOALS = GymnasiumEnvConfig(
    "seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5}, trigger=WrapperTriggerConfig()
)


@pytest.mark.parametrize(
    ("section", "spec"),
    [(EnvConfig(size=5, holes=0), EnvSpec(54, 4, None)), (TWO_GOALS, EnvSpec(500, 3, (5, 5, 20)))],
)
def test_both_kinds_of_env_answer_the_batched_env_seam(section, spec):
    env = make_batched_env(section, 3, seed=0)
    try:
        assert isinstance(env, BatchedEnv) and env.num_stages == 1 and env_spec(section) == spec
        assert (env.obs_dim, env.num_actions, env.image) == (spec.obs_dim, spec.num_actions, spec.image)
        obs = env.reset(seed=5)
        assert obs.shape == (3, spec.obs_dim) and obs.dtype == torch.float32 and torch.equal(env.observe(), obs)
        result = env.step(torch.zeros(3, dtype=torch.int64))
        assert result.obs.shape == (3, spec.obs_dim) and all(
            getattr(result, name).shape == (3,) for name in ("reward", "done", "trojan", "success", "length")
        )
        assert bool((result.length == 1).all() | result.done.any())  # one step into every episode
    finally:
        env.close()


def test_bad_input_to_a_gymnasium_batched_env_is_refused():
    env = make_batched_env(TWO_GOALS, 2)
    with pytest.raises(ShapeError, match=r"actions must be \(2,\) integers in \[0, 3\)"):
        env.step(torch.tensor([0, 3]))
    with pytest.raises(ShapeError, match=r"actions must be \(2,\) integers"):
        env.step(torch.zeros(3, dtype=torch.int64))
    with pytest.raises(ShapeError, match="reset needs 2 seeds, got 3"):
        env.reset([1, 2, 3])
    with pytest.raises(ConfigError, match=r"num_envs must be an integer in \[1, 4096\], got 0"):
        make_batched_env(TWO_GOALS, 0)
    with pytest.raises(ConfigError, match="render nothing"):
        GymnasiumEnvConfig("CartPole-v1", kwargs={"render_mode": "human"})
    foreign = GymnasiumEnvConfig("seqtrojan_no_such_module:Foo-v0")
    with pytest.raises(ConfigError, match=r"not a registered Gymnasium id .* module:Id imports are refused"):
        make_batched_env(foreign, 1, registered_only=True)  # a model card's env: refused before any import
    with pytest.raises(ConfigError, match="cannot be made"):
        make_batched_env(foreign, 1)  # a config one writes may name a module (here one that does not exist)
