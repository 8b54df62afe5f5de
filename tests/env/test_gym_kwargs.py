"""gym.make and the vector env take any EnvConfig field as a keyword argument, as docs/getting_started.md says."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import pytest

import seqtrojan  # noqa: F401  (registers the ids)
from seqtrojan.env import EnvConfig
from seqtrojan.env.config import RewardConfig, TriggerConfig
from seqtrojan.errors import ConfigError


def test_every_env_config_field_is_a_keyword_argument():
    values = {
        "size": 11, "holes": 11, "max_steps": 30, "view_size": 5, "actions": "eight", "max_layout_tries": 50,
        "rewards": {"hole": -2.0}, "trigger": {"duration": 2, "cells": [[0, 0], [1, 1]]},
    }  # fmt: skip
    assert set(values) == {f.name for f in dataclasses.fields(EnvConfig)}  # a new field needs a case here
    env = gym.make("seqtrojan/Trojan-v0", **values).unwrapped
    cfg = env.config
    assert (cfg.size, cfg.holes, cfg.max_steps, cfg.view_size, cfg.actions) == (11, 11, 30, 5, "eight")
    assert cfg.max_layout_tries == 50 and cfg.rewards == RewardConfig(hole=-2.0)
    assert cfg.trigger == TriggerConfig(duration=2, cells=((0, 0), (1, 1)))
    obs, _ = env.reset(seed=0)
    assert obs.shape == (5 * 5 * 6,)
    venv = gym.make_vec("seqtrojan/Normal-v0", num_envs=2, vectorization_mode="vector_entry_point",
                        rewards=RewardConfig(timeout=0.0), config={"size": 9})  # fmt: skip
    assert venv.unwrapped.config.size == 9 and venv.unwrapped.config.rewards.timeout == 0.0


def test_bad_keyword_values_are_checked_like_config_files():
    with pytest.raises(ConfigError, match=r"unknown config key\(s\) \['durration'\] in env.trigger"):
        gym.make("seqtrojan/Trojan-v0", trigger={"durration": 2})
    with pytest.raises(ConfigError, match="max_layout_tries must be >= 1"):
        gym.make("seqtrojan/Trojan-v0", max_layout_tries=0)
