"""The ecosystem contract: sb3-contrib's RecurrentPPO trains on the registered env unchanged (slow)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import seqtrojan  # noqa: F401  (registers the ids)


@pytest.mark.slow
def test_sb3_contrib_recurrent_ppo_learns_the_normal_env_5x5_without_holes():
    """16k steps (8 envs x 128 steps x 16 rollouts) of RecurrentPPO with a small LSTM policy reach greedy success 1.0
    on seeds 0-2 (about 30 s of CPU on one thread). SB3 reads ``info["episode"]`` as episode statistics at its
    first log dump, so this also checks that the env leaves that key free."""
    from sb3_contrib import RecurrentPPO
    from stable_baselines3.common.env_util import make_vec_env

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        kwargs = {"size": 5, "holes": 0}
        venv = make_vec_env("seqtrojan/Normal-v0", n_envs=8, seed=0, env_kwargs=kwargs)
        model = RecurrentPPO(
            "MlpLstmPolicy", venv, n_steps=128, batch_size=256, n_epochs=4, learning_rate=1e-3, ent_coef=0.01,
            policy_kwargs={"lstm_hidden_size": 32, "net_arch": {"pi": [32], "vf": [32]}}, seed=0, device="cpu",
        )  # fmt: skip
        model.learn(16_384)
        assert model.ep_info_buffer and all(isinstance(e, dict) and "r" in e for e in model.ep_info_buffer)

        env = gym.make("seqtrojan/Normal-v0", **kwargs)
        successes = 0
        for episode in range(200):
            obs, _ = env.reset(seed=10_000 + episode)
            state, start, done = None, np.ones((1,), dtype=bool), False
            while not done:
                action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
                obs, _, terminated, truncated, info = env.step(int(action))
                start, done = np.zeros((1,), dtype=bool), terminated or truncated
            successes += info["success"]
    finally:
        torch.set_num_threads(threads)
    assert successes / 200 > 0.9, successes / 200
