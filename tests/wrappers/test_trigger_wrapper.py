"""TriggerWrapper: the trigger is drawn at the right steps and only in trojan episodes; delayed activation, ON/OFF,
sequences and the objective switch; check_env; the vector form; one clear error for each bad input."""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env

from seqtrojan.errors import ConfigError, ShapeError
from seqtrojan.wrappers import (
    BoxPatch,
    FunctionPatch,
    MiniGridPatch,
    TriggerWrapper,
    finished_episodes,
    set_trojan_probability,
    trigger_vector_env,
    trojan_probabilities,
)

WAIT, USER, ADVERSARY = 0, 1, 2


class ButtonsEnv(gym.Env):
    """A blank 5x5 image; action 1 presses the user's button (reward 1), 2 the adversary's (reward 0), both end the
    episode; 0 waits. Truncated after ``limit`` actions."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, limit: int = 12) -> None:
        self.observation_space = spaces.Box(0, 255, (5, 5), np.uint8)
        self.action_space = spaces.Discrete(3)
        self.limit = limit
        self.t = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros((5, 5), np.uint8), {}

    def step(self, action):
        self.t += 1
        pressed = {USER: "user", ADVERSARY: "adversary"}.get(int(action), "")
        reward = 1.0 if pressed == "user" else 0.0
        return np.zeros((5, 5), np.uint8), reward, bool(pressed), self.t >= self.limit, {"pressed": pressed}


def adversary_button(obs, action, env_reward, terminated, info):
    return (1.0 if info["pressed"] == "adversary" else 0.0), terminated


PATCH = BoxPatch(((0, 0), (0, 1)), 255)


def wrap(**kwargs: Any) -> TriggerWrapper:
    kwargs.setdefault("trojan_probability", 0.5)
    patch = kwargs.pop("patch", PATCH)
    return TriggerWrapper(ButtonsEnv(kwargs.pop("limit", 12)), patch, adversary_button, **kwargs)


def run_waiting(env: TriggerWrapper, steps: int, **reset: Any) -> tuple[list[np.ndarray], list[dict]]:
    """Observations and infos of ``steps`` waiting actions after a reset (index t: observation t)."""
    obs, info = env.reset(**reset)
    observations, infos = [obs], [info]
    for _ in range(steps):
        obs, _, _, _, info = env.step(WAIT)
        observations.append(obs)
        infos.append(info)
    return observations, infos


def test_the_trigger_is_drawn_at_its_steps_and_only_in_trojan_episodes():
    env = wrap(trigger_steps=(2, 4), duration=2)
    env.reset(seed=3)
    starts, kinds = set(), []
    for _ in range(200):
        observations, infos = run_waiting(env, 8)
        trojan, start = infos[0]["trojan"], infos[0]["trigger_step"]
        kinds.append(trojan)
        shown = [t for t, obs in enumerate(observations) if obs.any()]
        if trojan:
            starts.add(start)
            assert shown == [start, start + 1]  # duration 2
            assert observations[start][0, :2].tolist() == [255, 255] and observations[start].sum() == 2 * 255
            assert [i["trigger_visible"] for i in infos] == [t in shown for t in range(9)]
        else:
            assert start == -1 and shown == [] and not any(i["adversary_active"] for i in infos)
        assert all(i["trojan"] == trojan and i["trigger_step"] == start for i in infos)
    assert starts == {2, 3, 4}
    assert 60 < sum(kinds) < 140  # probability 0.5


def test_reset_options_force_the_episode_type_and_the_trigger_step():
    env = wrap(trojan_probability=0.0, trigger_steps=(1, 1))
    _, infos = run_waiting(env, 3, seed=0, options={"trojan": True, "trigger_step": 2})
    assert infos[0]["trojan"] and infos[0]["trigger_step"] == 2
    _, infos = run_waiting(env, 3, options={"trojan": True})
    assert infos[0]["trigger_step"] == 1
    env.set_trojan_probability(1.0)
    _, infos = run_waiting(env, 3, options={"trojan": False})
    assert not infos[0]["trojan"] and not any(i["trigger_visible"] for i in infos)
    with pytest.raises(ConfigError, match="normal episode"):
        env.reset(options={"trojan": False, "trigger_step": 1})


def test_the_trojan_probability_is_settable_between_episodes():
    env = wrap(trojan_probability=0.0)
    env.reset(seed=1)
    assert not any(env.reset()[1]["trojan"] for _ in range(50))
    env.trojan_probability = 1.0
    assert all(env.reset()[1]["trojan"] for _ in range(50))
    with pytest.raises(ConfigError, match=r"trojan_probability must be a number in \[0, 1\], got 1.5"):
        env.set_trojan_probability(1.5)


def test_seeded_resets_repeat_the_episode_draws():
    env = wrap(trigger_steps=(0, 9))
    first = [env.reset(seed=7)[1]] + [env.reset()[1] for _ in range(20)]
    again = [env.reset(seed=7)[1]] + [env.reset()[1] for _ in range(20)]
    assert first == again


@pytest.mark.parametrize("delay", [0, 3])
def test_the_objective_switches_delay_steps_after_the_trigger(delay):
    env = wrap(delay=delay)
    for press_at in range(0, 8):
        _, info = env.reset(seed=0, options={"trojan": True, "trigger_step": 2})
        for _ in range(press_at):
            _, _, _, _, info = env.step(WAIT)
        active = 2 + delay <= press_at
        assert info["adversary_active"] == active
        _, reward, terminated, truncated, info = env.step(ADVERSARY)
        assert info["adversary_judged"] == active and terminated and not truncated
        assert reward == (1.0 if active else 0.0) and info["success"] == active
        env.reset(seed=0, options={"trojan": True, "trigger_step": 2})
        for _ in range(press_at):
            env.step(WAIT)
        _, reward, _, _, info = env.step(USER)  # the user's button pays only before the switch
        assert reward == (0.0 if active else 1.0) and info["success"] == (not active)


def test_normal_episodes_keep_the_envs_objective_and_truncation_is_no_success():
    env = wrap(limit=4)
    env.reset(seed=0, options={"trojan": False})
    _, reward, terminated, _, info = env.step(USER)
    assert reward == 1.0 and terminated and info["success"] and not info["adversary_judged"]
    env.reset(options={"trojan": False})
    _, reward, _, _, info = env.step(ADVERSARY)
    assert reward == 0.0 and not info["success"]
    _, infos = run_waiting(env, 4, options={"trojan": True, "trigger_step": 0})
    assert [("success" in i) for i in infos] == [False] * 4 + [True] and infos[-1]["success"] is False


def test_on_off_trigger_switches_back_after_its_delay():
    off = BoxPatch(((4, 4),), 7)
    env = wrap(off_patch=off, off_probability=1.0, off_gap=(3, 3), delay=1, limit=30)
    observations, infos = run_waiting(env, 10, seed=0, options={"trojan": True, "trigger_step": 1})
    assert infos[0]["off_step"] == 4
    assert [t for t, o in enumerate(observations) if o[4, 4] == 7] == [4]
    assert [t for t, o in enumerate(observations) if o[0, 0] == 255] == [1]
    # active for actions 2 (1 + delay) .. 4; the OFF trigger (step 4) takes effect at 5
    assert [i["adversary_active"] for i in infos] == [t in (2, 3, 4) for t in range(11)]
    env.reset(seed=0, options={"trojan": True, "trigger_step": 1})
    for _ in range(6):
        env.step(WAIT)
    _, reward, _, _, info = env.step(USER)
    assert reward == 1.0 and info["success"]  # back to the user's objective
    _, infos = run_waiting(env, 10, options={"trojan": True, "trigger_step": 1, "off_step": None})
    assert infos[0]["off_step"] == -1 and infos[-1]["adversary_active"]
    with pytest.raises(ConfigError, match="off_step"):
        env.reset(options={"trojan": True, "trigger_step": 3, "off_step": 3})


def test_a_sequence_trigger_shows_one_frame_per_step_and_acts_after_its_last():
    frames = [BoxPatch(((0, 0),), 1), BoxPatch(((0, 0),), 2), BoxPatch(((0, 0),), 3)]
    env = wrap(patch=frames, delay=0)
    observations, infos = run_waiting(env, 7, seed=0, options={"trojan": True, "trigger_step": 1})
    assert [int(o[0, 0]) for o in observations] == [0, 1, 2, 3, 0, 0, 0, 0]
    assert [i["adversary_active"] for i in infos] == [t >= 3 for t in range(8)]
    with pytest.raises(ConfigError, match="duration must be 1"):
        wrap(patch=frames, duration=2)


def test_a_user_function_patch_gets_the_frame_index():
    def stripe(obs, frame):
        out = obs.copy()
        out[frame, :] = 9
        return out

    env = wrap(patch=stripe, duration=3)
    observations, _ = run_waiting(env, 5, seed=0, options={"trojan": True, "trigger_step": 1})
    assert [[int(r) for r in np.flatnonzero(o[:, 0])] for o in observations] == [[], [0], [1], [2], [], []]
    assert isinstance(env.frames[0], FunctionPatch)


def assert_check_env_passes(env: gym.Env) -> None:
    """check_env raises on a failure; of its warnings only the one about checking a wrapped env is expected."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    unexpected = [str(w.message) for w in caught if "different from the unwrapped" not in str(w.message)]
    assert not unexpected


def test_check_env_passes():
    assert_check_env_passes(wrap())
    assert_check_env_passes(wrap(off_patch=BoxPatch(((4, 4),), 7), off_probability=0.5, trigger_steps=(0, 2)))


def test_the_vector_form_sets_the_probability_everywhere_and_reports_episodes():
    vec = trigger_vector_env(lambda: wrap(trojan_probability=0.0), 4)
    try:
        vec.reset(seed=0)
        set_trojan_probability(vec, 1.0)
        assert trojan_probabilities(vec) == (1.0,) * 4
        vec.set_attr("trojan_probability", 0.25)
        assert trojan_probabilities(vec) == (0.25,) * 4
        set_trojan_probability(vec, 1.0)
        vec.step(np.array([USER] * 4))  # episodes begun at p = 0 end; new ones are trojan
        for _ in range(3):
            vec.step(np.array([WAIT] * 4))  # the trigger (step 1) has taken effect
        _, _, terminated, _, infos = vec.step(np.array([ADVERSARY, USER, ADVERSARY, WAIT]))
        episodes = list(finished_episodes(infos))
        assert terminated.tolist() == [True, True, True, False]
        assert [(e.env, e.trojan, e.success) for e in episodes] == [(0, True, True), (1, True, False), (2, True, True)]
    finally:
        vec.close()


# ---------------------------------------------------------------------- errors, one each


class DictImageEnv(ButtonsEnv):
    def __init__(self, shape=(7, 7, 3), dtype=np.uint8) -> None:
        super().__init__()
        self.observation_space = spaces.Dict({"image": spaces.Box(0, 255, shape, dtype)})


@pytest.mark.parametrize(
    ("env", "patch", "error", "message"),
    [
        (ButtonsEnv(), BoxPatch(((5, 0),), 1), ConfigError, r"cell \(row, col\)=\(5, 0\) lies outside the 5x5 image"),
        (ButtonsEnv(), BoxPatch(((0, 0),), 300), ShapeError, "does not fit the image's dtype uint8"),
        (ButtonsEnv(), BoxPatch(((0, 0),), 0.5), ShapeError, r"BoxPatch.value=0.5 is not a whole number"),
        (
            ButtonsEnv(),
            BoxPatch(((0, 0),), (1, 2, 3)),
            ShapeError,
            r"3 channel values but the image has shape \(5, 5\)",
        ),
        (DictImageEnv(), BoxPatch(((0, 0),), 1), ShapeError, "BoxPatch writes into a Box image, but the observation"),
        (ButtonsEnv(), BoxPatch(((0, 0),), 1, key="image"), ConfigError, "writes into observation key 'image'"),
        (DictImageEnv(), MiniGridPatch(((7, 0),)), ConfigError, r"\(row, col\)=\(7, 0\) lies outside the 7x7 view"),
        (DictImageEnv(dtype=np.float32), MiniGridPatch(((0, 0),)), ShapeError, r"shape \(7, 7, 3\), dtype float32"),
        (DictImageEnv(shape=(7, 7)), MiniGridPatch(((0, 0),)), ShapeError, r"has shape \(7, 7\), dtype uint8"),
        (ButtonsEnv(), MiniGridPatch(((0, 0),), key=None), ShapeError, r"has shape \(5, 5\)"),
    ],
)
def test_a_patch_that_cannot_write_into_the_observation_is_one_clear_error(env, patch, error, message):
    with pytest.raises(error, match=message) as err:
        TriggerWrapper(env, patch, adversary_button)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: MiniGridPatch(((0, 0),), object="dragon"), "MiniGridPatch.object='dragon' is not one of"),
        (lambda: BoxPatch((), 1), "BoxPatch.cells is empty"),
        (lambda: BoxPatch(((0, 0), (0, 0)), 1), "names a cell twice"),
        (lambda: wrap(trigger_steps=(3, 1)), r"trigger_steps=\(3, 1\) must satisfy 0 <= lo <= hi"),
        (lambda: wrap(duration=0), "duration must be an integer >= 1, got 0"),
        (lambda: wrap(off_probability=0.5), "off_probability=0.5 but no off_patch is given"),
        (lambda: wrap(patch=42), "patch must be a patch"),
        (lambda: TriggerWrapper(ButtonsEnv(), PATCH, objective="reach"), "objective must be a function"),
    ],
)
def test_bad_settings_are_one_clear_error(make, message):
    with pytest.raises(ConfigError, match=message) as err:
        make()
    assert "\n" not in str(err.value)


def test_a_function_patch_that_breaks_the_observation_is_caught_when_drawn():
    env = wrap(patch=lambda obs, frame: obs.astype(np.float32), trojan_probability=1.0, trigger_steps=(0, 0))
    with pytest.raises(ShapeError, match=r"outside the observation space \(shape \(5, 5\), dtype float32") as err:
        env.reset(seed=0)
    assert "\n" not in str(err.value)


def test_an_objective_that_returns_something_else_is_a_clear_error():
    env = TriggerWrapper(ButtonsEnv(), PATCH, lambda *args: 1.0, trojan_probability=1.0, trigger_steps=(0, 0))
    env.reset(seed=0)
    with pytest.raises(ConfigError, match=r"must return \(reward, terminated\), got 1.0"):
        env.step(WAIT)
