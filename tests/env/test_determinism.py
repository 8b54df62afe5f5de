"""Seeded reproducibility, and batched == single env for the same seed and actions: the grid core, and a Gymnasium
env behind the batched-env seam (whose episodes in flight a checkpoint restores exactly)."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

import seqtrojan  # noqa: F401  (registers the env ids)
from seqtrojan.env import EnvConfig, TrojanGridCore
from seqtrojan.env.core import EnvState
from seqtrojan.env.gym_env import TrojanGridEnv
from seqtrojan.world import make_batched_env
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig
from seqtrojan.world.gymnasium import make_gym_env

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


# ---------------------------------------------------------------------- a Gymnasium env behind the batched-env seam

TWO_GOALS = GymnasiumEnvConfig(
    "seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5}, trigger=WrapperTriggerConfig()
)


def test_gymnasium_batched_env_i_equals_single_env_seeded_seed_plus_i():
    """The batched env steps each Gymnasium env as a single env seeded seed + i would step, resetting a finished
    episode in the step that ends it (as the grid core does)."""
    n, steps, seed = 4, 200, 11
    batched = make_batched_env(TWO_GOALS, n, seed=seed, trojan_probability=0.5)
    singles = [make_gym_env(TWO_GOALS, "train", 0.5) for _ in range(n)]
    obs = [env.reset(seed=seed + i)[0] for i, env in enumerate(singles)]
    np.testing.assert_array_equal(batched.observe().numpy(), np.stack(obs))
    actions = np.random.default_rng(0).integers(0, 3, (steps, n))
    finished = trojan = 0
    for t in range(steps):
        r = batched.step(torch.as_tensor(actions[t]))
        for i, env in enumerate(singles):
            o, rew, term, trunc, info = env.step(int(actions[t, i]))
            assert np.float32(rew) == float(r.reward[i])  # the batched env's rewards are float32
            assert (term, trunc) == (bool(r.terminated[i]), bool(r.truncated[i]))
            if term or trunc:
                assert bool(r.done[i]) and bool(r.trojan[i]) == info["trojan"] and bool(r.success[i]) == info["success"]
                finished, trojan = finished + 1, trojan + info["trojan"]
                o, _ = env.reset()
            np.testing.assert_array_equal(o, r.obs[i].numpy())
    assert finished > 10 and 0 < trojan < finished  # both kinds of episode were compared


def test_a_gymnasium_batched_env_restores_its_episodes_in_flight_exactly():
    """What a checkpoint keeps of a Gymnasium env (each env's replay record, through JSON) puts a fresh batched env
    exactly where the saved one was: the same steps follow. Records whose replay does not give the saved
    observations are refused."""
    rng = np.random.default_rng(1)
    saved = make_batched_env(TWO_GOALS, 4, seed=3, trojan_probability=0.5)
    for _ in range(30):
        saved.step(torch.as_tensor(rng.integers(0, 3, 4)))
    state = saved.save_state()
    assert state is not None and state.records is not None and all(state.records)
    kept = EnvState(state.tensors, json.loads(json.dumps(state.records)))  # as trainer.json holds them
    obs = saved.observe().clone()
    restored = make_batched_env(TWO_GOALS, 4, seed=99, trojan_probability=0.5)
    assert restored.load_state(kept, obs) and torch.equal(restored.observe(), obs)
    for _ in range(80):
        a = torch.as_tensor(rng.integers(0, 3, 4))
        x, y = saved.step(a), restored.step(a)
        for name in ("obs", "reward", "done", "trojan", "success", "length", "adversary_active"):
            assert torch.equal(getattr(x, name), getattr(y, name)), name
    other = make_batched_env(TWO_GOALS, 4, seed=99, trojan_probability=0.5)
    assert not other.load_state(kept, torch.zeros_like(obs))
