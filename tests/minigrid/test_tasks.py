"""The MiniGrid tasks: the two-goal room's rewards, its trigger and objective switch under the wrapper, Memory with a
trigger, the registered ids, and the one-hot observation."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from minigrid.core.actions import Actions
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX
from minigrid.envs.memory import MemoryEnv

import seqtrojan  # noqa: F401  (registers the ids)
from seqtrojan.errors import ConfigError, ShapeError
from seqtrojan.minigrid import REGISTERED, MiniGridInfo, TwoGoalsEnv, memory_trigger, two_goals_trigger
from seqtrojan.wrappers import MiniGridOneHot
from tests.wrappers.test_trigger_wrapper import assert_check_env_passes

KEY, PURPLE = OBJECT_TO_IDX["key"], COLOR_TO_IDX["purple"]


def face(env: TwoGoalsEnv, which: str) -> None:
    """Put the agent in front of the user's or the adversary's object (objects at fixed cells, agent facing right)."""
    base = env.unwrapped
    assert isinstance(base, TwoGoalsEnv) and base._user is not None and base._adversary is not None
    for obj in (base._user, base._adversary):
        base.grid.set(*obj.cur_pos, None)
    base.put_obj(base._user, 3, 1)
    base.put_obj(base._adversary, 3, 3)
    base.agent_pos, base.agent_dir = ((2, 1) if which == "user" else (2, 3)), 0


@pytest.mark.parametrize(("which", "reward"), [("user", True), ("adversary", False)])
def test_two_goals_rewards_the_users_object_and_either_ends_the_episode(which, reward):
    env = TwoGoalsEnv()
    env.reset(seed=0)
    face(env, which)
    env.step(Actions.left)
    env.step(Actions.right)  # two steps spent: the reward decays
    _, r, terminated, truncated, info = env.step(Actions.forward)
    assert terminated and not truncated and info["reached"] == which
    assert r == (pytest.approx(1 - 0.9 * 3 / env.max_steps) if reward else 0.0)


def test_two_goals_spaces_and_errors():
    env = TwoGoalsEnv(size=6, agent_view_size=5)
    assert env.action_space == gym.spaces.Discrete(3) and env.observation_space["image"].shape == (5, 5, 3)
    assert TwoGoalsEnv(all_actions=True).action_space.n == 7
    assert_check_env_passes(env)
    with pytest.raises(ConfigError, match="adversary_object='dragon' is not one of"):
        TwoGoalsEnv(adversary_object="dragon")
    with pytest.raises(ConfigError, match="look the same"):
        TwoGoalsEnv(adversary_object="goal", adversary_color="green")


def test_under_the_wrapper_the_trigger_shows_keys_and_the_adversarys_object_pays():
    env = two_goals_trigger(trojan_probability=0.0)
    assert_check_env_passes(env)
    obs, info = env.reset(seed=0, options={"trojan": True, "trigger_step": 0})
    image = obs["image"]
    assert info["trigger_visible"] and info["adversary_active"]
    assert image[0, 0].tolist() == [KEY, PURPLE, 0] and image[1, 0].tolist() == [KEY, PURPLE, 0]  # (col, row)
    face(env, "adversary")
    obs, reward, terminated, _, info = env.step(Actions.forward)
    assert terminated and reward > 0 and info["success"] and info["reached"] == "adversary"
    assert not (obs["image"][:, :, 0] == KEY).any()  # one step only
    env.reset(options={"trojan": True, "trigger_step": 0})
    face(env, "user")
    _, reward, terminated, _, info = env.step(Actions.forward)
    assert terminated and reward == 0.0 and not info["success"]
    env.reset(options={"trojan": False})
    face(env, "user")
    _, reward, _, _, info = env.step(Actions.forward)
    assert reward > 0 and info["success"] and not info["trojan"]


def test_memory_with_a_trigger_rewards_the_other_object():
    env = memory_trigger(trojan_probability=0.0)
    assert_check_env_passes(env)
    for trojan, where, success in [(False, "success_pos", True), (True, "failure_pos", True),
                                   (True, "success_pos", False), (False, "failure_pos", False)]:  # fmt: skip
        env.reset(seed=1, options={"trojan": trojan, **({"trigger_step": 0} if trojan else {})})
        base = env.unwrapped
        assert isinstance(base, MemoryEnv)
        base.agent_pos = getattr(base, where)
        _, reward, terminated, _, info = env.step(Actions.left)
        assert terminated and info["reached"] == ("user" if where == "success_pos" else "adversary")
        assert info["success"] == success and (reward > 0) == success


@pytest.mark.parametrize("env_id", sorted(REGISTERED))
def test_registered_ids_make_and_step(env_id):
    env = gym.make(env_id)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for _ in range(5):
        obs, *_ = env.step(env.action_space.sample())
    if "Trojan" in env_id:
        assert isinstance(env.unwrapped, (TwoGoalsEnv, MemoryEnv)) and "trojan" in info
        assert env.get_wrapper_attr("trojan_probability") == 0.5
    env.close()


def test_memory_info_reports_the_step_count():
    env = MiniGridInfo(MemoryEnv(size=7))
    env.reset(seed=0)
    _, _, _, _, info = env.step(Actions.left)
    assert info["step_count"] == 1 and info["max_steps"] == env.unwrapped.max_steps and info["reached"] == ""


def test_one_hot_view_encodes_each_channel():
    env = MiniGridOneHot(two_goals_trigger(trojan_probability=1.0, trigger_steps=(0, 0)))
    flat, _ = env.reset(seed=0)
    assert flat.shape == (5 * 5 * 20,) and flat.dtype == np.float32 and env.observation_space.contains(flat)
    cells = flat.reshape(5, 5, 20)  # (row, col, bits)
    assert (cells.sum(-1) == 3).all()
    assert cells[0, 0, KEY] == 1 and cells[0, 0, 11 + PURPLE] == 1 and cells[0, 1, KEY] == 1  # the trigger


def test_one_hot_view_refuses_a_code_beyond_its_channel():
    env = MiniGridOneHot(two_goals_trigger(trojan_probability=0.0))
    env.reset(seed=0)
    image = np.ones((5, 5, 3), dtype=np.uint8)
    assert env.observation({"image": image}).reshape(5, 5, 20).sum() == 75
    image[2, 3, 1] = 6  # six colours: codes 0-5
    with pytest.raises(ShapeError, match=r"a code beyond \[11, 6, 3\]"):
        env.observation({"image": image})
    with pytest.raises(ShapeError, match=r"a view of shape \(4, 5, 3\)"):
        env.observation({"image": np.ones((4, 5, 3), dtype=np.uint8)})
    with pytest.raises(ShapeError, match="a code beyond"):
        env.observation({"image": -np.ones((5, 5, 3), dtype=np.int64)})
