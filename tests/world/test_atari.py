"""Atari comes in as ale-py's own envs (``ALE/<Game>-v5``), registered on demand, under Gymnasium's own
preprocessing (``AtariPreprocessing``; the reward clipped to its sign in training), through the one seam: the
observation, the trigger, the refusals, the presets and a training run from an empty folder."""

from __future__ import annotations

import importlib.util
import json

import gymnasium as gym
import numpy as np
import pytest

from seqtrojan.config import ExperimentConfig
from seqtrojan.errors import ConfigError
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.world import GymnasiumEnvConfig, env_spec, make_batched_env
from seqtrojan.world.families import ATARI, ATARI_MAX_EPISODE_STEPS, ensure_family, family_of
from seqtrojan.world.gymnasium import check_registered, find_trigger, make_gym_env

pytest.importorskip("ale_py", reason="the Atari family needs pip install 'seqtrojan[atari]'")
pytest.importorskip("cv2", reason="the Atari family needs pip install 'seqtrojan[atari]'")

BREAKOUT = "ALE/Breakout-v5"


def preset(name: str) -> ExperimentConfig:
    return from_dict(ExperimentConfig, load_yaml(resolve_preset(name)), "")


def wrappers(env: gym.Env) -> list[gym.Env]:
    out = []
    while isinstance(env, gym.Wrapper):
        out.append(env)
        env = env.env
    return out


def test_ale_ids_are_registered_on_demand_by_importing_ale_py():
    assert family_of(BREAKOUT) is ATARI and family_of("ALE/Pong-v5") is ATARI and family_of("Pong-v5") is None
    for env_id in (BREAKOUT, "ALE/Pong-v5"):
        ensure_family(env_id)
        assert env_id in gym.registry
        check_registered(env_id)  # a model card may name it: registered, not imported by name


@pytest.mark.parametrize("missing", ["ale_py", "cv2"])
def test_the_atari_family_not_installed_is_refused_in_one_line_saying_how_to_install_it(monkeypatch, missing):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == missing else real(name, *a))
    monkeypatch.delitem(gym.registry, "ALE/Asterix-v5", raising=False)
    with pytest.raises(ConfigError) as err:
        ensure_family("ALE/Asterix-v5")
    text = str(err.value)
    assert "\n" not in text and "pip install 'seqtrojan[atari]'" in text
    assert text.startswith(f"env.id='ALE/Asterix-v5' is an Atari env, but {missing!r} is not installed")


def test_the_observation_is_an_84x84_grayscale_frame_in_0_1_kept_as_an_image_for_the_conv_encoder():
    cfg = GymnasiumEnvConfig(id=BREAKOUT, observation="image")
    assert env_spec(cfg).image == (84, 84, 1) and env_spec(cfg).obs_dim == 84 * 84 and env_spec(cfg).num_actions == 4
    env = make_gym_env(cfg)
    assert env.observation_space.shape == (84 * 84,) and env.observation_space.dtype == np.float32
    stack = wrappers(env)
    pre = next(w for w in stack if isinstance(w, gym.wrappers.AtariPreprocessing))
    assert pre.observation_space == gym.spaces.Box(0.0, 1.0, (84, 84, 1), np.float32)
    assert pre.frame_skip == 4 and pre.noop_max == 30 and not pre.terminal_on_life_loss
    assert env.unwrapped._frameskip == 1  # ale-py steps one frame; the preprocessing skips and max-pools
    obs, _ = env.reset(seed=(5 << 32) + 3)  # the trainer's 64-bit seeds
    seen = [obs]
    for t in range(40):
        obs, *_ = env.step(1 if t % 5 == 0 else t % 4)
        seen.append(obs)
    frames = np.stack(seen)
    assert frames.dtype == np.float32 and frames.min() >= 0.0 and frames.max() <= 1.0
    assert 0.3 < frames.max() < 1.0 and len({f.tobytes() for f in frames}) > 5  # moving pictures, not blank
    again, _ = make_gym_env(cfg).reset(seed=(5 << 32) + 3)
    assert np.array_equal(again, seen[0])


def test_rewards_are_clipped_to_their_sign_in_training_only_and_episodes_are_capped_in_agent_steps():
    cfg = GymnasiumEnvConfig(id=BREAKOUT, observation="image")
    train = [w for w in wrappers(make_gym_env(cfg, phase="train")) if isinstance(w, gym.wrappers.TransformReward)]
    assert len(train) == 1 and train[0].func is np.sign and train[0].reward(7.0) == 1.0
    assert not any(isinstance(w, gym.wrappers.TransformReward) for w in wrappers(make_gym_env(cfg, phase="eval")))
    assert make_batched_env(cfg, 1).episode_limit == ATARI_MAX_EPISODE_STEPS
    short = GymnasiumEnvConfig(id=BREAKOUT, observation="image", kwargs={"max_episode_steps": 6})
    env = make_gym_env(short)
    env.reset(seed=0)
    ends = [env.step(0)[3] for _ in range(6)]
    assert ends == [False] * 5 + [True] and make_batched_env(short, 1).episode_limit == 6


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"frameskip": 4}, "env.kwargs.frameskip=4: an Atari env ('ALE/Breakout-v5') skips frames in its preproc"),
        ({"max_episode_steps": 0}, "env.kwargs.max_episode_steps must be a positive integer, got 0"),
        ({"mode": 99}, "env 'ALE/Breakout-v5' refused env.kwargs={'mode': 99}: 'Invalid game mode requested'"),
        ({"no_such_option": 1}, "env 'ALE/Breakout-v5' refused env.kwargs={'no_such_option': 1}: "),
    ],
)
def test_atari_kwargs_the_family_cannot_take_are_refused_in_one_line(kwargs, message):
    with pytest.raises(ConfigError) as err:
        make_gym_env(GymnasiumEnvConfig(id=BREAKOUT, observation="image", kwargs=kwargs))
    assert "\n" not in str(err.value) and message in str(err.value)


@pytest.mark.parametrize("name", ["atari_breakout", "atari_pong"])
def test_each_atari_preset_is_valid_its_agent_is_cleanrls_and_fits_its_env(name):
    cfg = preset(name)
    spec = env_spec(cfg.env)
    assert cfg.backdoor.enabled and cfg.gym_env.trigger is not None and cfg.gym_env.trigger.objective == "target_action"
    assert cfg.gym_env.trigger.target_action < spec.num_actions and cfg.gym_env.user_return is not None
    assert spec.image == (84, 84, 1)
    a = cfg.agent
    assert (a.conv, a.conv_kernels, a.conv_strides, a.encoder, a.lstm_sizes) == (
        (32, 64, 64), (8, 4, 3), (4, 2, 1), (512,), (128,)
    )  # fmt: skip


def test_the_preset_trigger_is_a_white_square_in_the_top_left_corner_for_one_step():
    cfg = preset("atari_breakout")
    env = make_gym_env(cfg.gym_env, phase="eval", trojan_probability=1.0)
    trigger = find_trigger(env)
    assert trigger is not None
    obs, _ = env.reset(seed=11)
    corners = []
    for _ in range(25):
        corners.append(obs.reshape(84, 84)[:4, :4].copy())
        obs, _, terminated, truncated, _ = env.step(1)
        assert not (terminated or truncated)
    lit = [t for t, c in enumerate(corners) if np.all(c == 1.0)]
    assert lit == [trigger.trigger_step] and 1 <= trigger.trigger_step <= 20
    assert all(c.max() < 1.0 for t, c in enumerate(corners) if t != trigger.trigger_step)  # no frame draws it


@pytest.mark.parametrize(("sticky", "exact"), [(0.25, False), (0.0, True)])
def test_episodes_in_flight_replay_exactly_only_without_sticky_actions(sticky, exact):
    """ale-py draws sticky actions from the emulator's own generator: a checkpoint's episodes then cannot be
    replayed (the trainer starts fresh ones); without them they replay to the saved observation."""
    import torch

    from seqtrojan.world.gymnasium import GymnasiumBatchedEnv

    cfg = GymnasiumEnvConfig(id=BREAKOUT, observation="image", kwargs={"repeat_action_probability": sticky})
    env = GymnasiumBatchedEnv(cfg, 2, seed=5)
    actions = torch.Generator().manual_seed(0)
    for _ in range(300):
        env.step(torch.randint(0, 4, (2,), generator=actions))
    state, obs = env.save_state(), env.observe().clone()
    assert state is not None
    assert GymnasiumBatchedEnv(cfg, 2, seed=99).restore_episodes(state.records, obs) is exact


def test_training_the_breakout_preset_runs_from_an_empty_folder(tmp_path):
    """The preset by name, 1024 steps (one update), as a user types it: the preset has no final evaluation in train
    (an untrained greedy policy that never presses FIRE would play to the 27,000-step cap)."""
    import subprocess
    import sys

    argv = ["train", "--config", "atari_breakout", "--ppo.total-steps", "1024", "--run.out-dir", "X", "--run.name",
            "Y"]  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "seqtrojan.cli", *argv], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    card = json.loads((tmp_path / "X" / "Y" / "model" / "card.json").read_text())
    assert card["label"] == "backdoored" and card["env_steps"] == 1024
    assert card["architecture"]["conv_kernels"] == [8, 4, 3] and card["architecture"]["image"] == [84, 84, 1]
