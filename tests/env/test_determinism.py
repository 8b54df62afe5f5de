"""Seeded reproducibility, and batched == single env for the same seed and actions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import seqtrojan  # noqa: F401  (registers the env ids)
from seqtrojan.env import EnvConfig, TrojanGridCore
from seqtrojan.env.gym_env import TrojanGridEnv

CFG = EnvConfig(size=7, holes=5)


def rollout(core: TrojanGridCore, actions: torch.Tensor) -> list[torch.Tensor]:
    out = [core.observe().clone()]
    for a in actions:
        r = core.step(a)
        out += [r.obs.clone(), r.reward.clone(), r.done.clone()]
    return out


def test_same_seed_same_episodes_other_seed_other_episodes():
    actions = torch.randint(0, 4, (60, 32), generator=torch.Generator().manual_seed(0))
    a = rollout(TrojanGridCore(CFG, 32, seed=7, trojan_probability=0.5), actions)
    b = rollout(TrojanGridCore(CFG, 32, seed=7, trojan_probability=0.5), actions)
    c = rollout(TrojanGridCore(CFG, 32, seed=8, trojan_probability=0.5), actions)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(torch.equal(x, y) for x, y in zip(a, c))


def test_reset_with_seed_restarts_the_stream():
    core = TrojanGridCore(CFG, 8, seed=3)
    first = core.grid.clone()
    core.reset()
    assert not torch.equal(core.grid, first)
    core.reset(seed=3)
    assert torch.equal(core.grid, first)


def test_episode_content_does_not_depend_on_batch_size_or_neighbours():
    big = TrojanGridCore(CFG, 16, seed=100, trojan_probability=0.5)
    small = TrojanGridCore(CFG, 4, seed=[104, 105, 106, 107], trojan_probability=0.5)
    assert torch.equal(big.grid[4:8], small.grid)
    assert torch.equal(big.on_step[4:8], small.on_step)


def test_batched_env_i_equals_single_env_seeded_seed_plus_i():
    n, steps, seed = 6, 80, 11
    actions = np.random.default_rng(0).integers(0, 4, (steps, n))
    core = TrojanGridCore(CFG, n, seed=seed, trojan_probability=0.5)
    singles = [TrojanGridEnv(CFG, trojan_probability=0.5) for _ in range(n)]
    obs = [env.reset(seed=seed + i)[0] for i, env in enumerate(singles)]
    np.testing.assert_array_equal(core.observe().numpy(), np.stack(obs))
    for t in range(steps):
        r = core.step(torch.as_tensor(actions[t]))
        for i, env in enumerate(singles):
            o, rew, term, trunc, _ = env.step(actions[t, i])
            assert rew == float(r.reward[i]) and term == bool(r.terminated[i]) and trunc == bool(r.truncated[i])
            if term or trunc:
                o, _ = env.reset()  # the batched core autoresets in the same step
            np.testing.assert_array_equal(o, r.obs[i].numpy())


def test_vector_env_equals_gymnasium_sync_vector_env_of_single_envs():
    n, steps = 5, 80
    ours = gym.make_vec("seqtrojan/Trojan-v0", num_envs=n, vectorization_mode="vector_entry_point", holes=5)
    sync = gym.vector.SyncVectorEnv([lambda: TrojanGridEnv(trojan_probability=1.0, holes=5) for _ in range(n)])
    assert ours.metadata["autoreset_mode"] == sync.metadata["autoreset_mode"]
    o1, _ = ours.reset(seed=21)
    o2, _ = sync.reset(seed=21)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(1)
    for _ in range(steps):
        a = rng.integers(0, 4, n)
        r1, r2 = ours.step(a), sync.step(a)
        for x, y in zip(r1[:4], r2[:4]):
            np.testing.assert_array_equal(x, y)


@pytest.mark.cuda
def test_cpu_and_cuda_give_identical_episodes():
    actions = torch.randint(0, 4, (50, 64), generator=torch.Generator().manual_seed(0))
    cpu = rollout(TrojanGridCore(CFG, 64, seed=5, trojan_probability=0.5), actions)
    gpu = rollout(TrojanGridCore(CFG, 64, seed=5, trojan_probability=0.5, device="cuda"), actions)
    assert all(torch.equal(x, y.cpu()) for x, y in zip(cpu, gpu))
