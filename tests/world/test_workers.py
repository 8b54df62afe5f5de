"""``env.vectorization: workers``: the envs split among worker processes step the same episodes as ``sync``, bit for
bit (steps, the episode loop, checkpoints, a whole training run), and a failing worker is one line."""

from __future__ import annotations

import dataclasses
import os
import signal

import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.errors import ConfigError
from seqtrojan.serde import from_dict, to_dict
from seqtrojan.train.trainer import train
from seqtrojan.world import make_batched_env
from seqtrojan.world.config import GymnasiumEnvConfig
from seqtrojan.world.episodes import episode_env
from seqtrojan.world.workers import WorkerBatchedEnv, WorkerError
from tests.train.test_gym_trainer import config
from tests.world.test_world import TWO_GOALS

WORKERS = dataclasses.replace(TWO_GOALS, vectorization="workers", workers=2)


def test_workers_step_the_same_episodes_as_sync_bit_for_bit():
    sync = make_batched_env(TWO_GOALS, 7, seed=11, trojan_probability=0.5)
    split = make_batched_env(WORKERS, 7, seed=11, trojan_probability=0.5)
    try:
        assert isinstance(split, WorkerBatchedEnv) and split.bounds == [(0, 3), (3, 7)]
        assert (split.obs_dim, split.num_actions, split.image) == (sync.obs_dim, sync.num_actions, sync.image)
        assert torch.equal(sync.observe(), split.observe())
        generator = torch.Generator().manual_seed(0)
        ends = 0
        for _ in range(120):
            actions = torch.randint(0, sync.num_actions, (7,), generator=generator)
            a, b = sync.step(actions), split.step(actions)
            for name, ours, theirs in zip(a._fields, b, a, strict=True):
                assert ours.dtype == theirs.dtype and torch.equal(ours, theirs), name
            ends += int(a.done.sum())
            assert torch.equal(sync.trojan, split.trojan) and torch.equal(sync.on_step, split.on_step)
            assert torch.equal(sync.t, split.t)
        assert ends > 10  # episodes ended and were reset inside the workers
        split.set_trojan_probability(0.0)
        sync.set_trojan_probability(0.0)
        assert torch.equal(sync.reset(3), split.reset(3))
    finally:
        sync.close()
        split.close()


def test_a_checkpoint_of_worker_envs_replays_their_episodes_in_flight():
    env = make_batched_env(WORKERS, 5, seed=2, trojan_probability=0.5)
    fresh = make_batched_env(WORKERS, 5, seed=99, trojan_probability=0.5)
    try:
        generator = torch.Generator().manual_seed(1)
        for _ in range(9):
            env.step(torch.randint(0, env.num_actions, (5,), generator=generator))
        state = env.save_state()
        assert state is not None and state.records is not None and len(state.records) == 5
        assert fresh.load_state(state, env.observe())
        actions = torch.randint(0, env.num_actions, (5,), generator=generator)
        a, b = env.step(actions), fresh.step(actions)
        assert all(torch.equal(x, y) for x, y in zip(a, b))
        assert not fresh.load_state(state, torch.zeros_like(env.observe()))  # other observations: no exact replay
    finally:
        env.close()
        fresh.close()


def test_the_episode_loop_runs_in_workers_as_in_one_process():
    sync = episode_env(TWO_GOALS, None, 6, trojan=True)
    split = episode_env(WORKERS, None, 6, trojan=True)
    try:
        assert isinstance(split, WorkerBatchedEnv) and split.episode_limit == sync.episode_limit
        for _ in range(sync.episode_limit):
            actions = torch.full((6,), 2, dtype=torch.int64)
            a, b = sync.step(actions, autoreset=False), split.step(actions, autoreset=False)
            assert all(torch.equal(x, y) for x, y in zip(a, b))
            if bool(a.done.all()):
                break
    finally:
        sync.close()
        split.close()


def test_training_with_workers_gives_the_weights_of_sync_bit_for_bit(tmp_path):
    """The whole trainer (Algorithm 1's mixing, PPO, the final evaluation) on worker envs: the same weights and
    evaluation as on sync envs."""
    base = config(tmp_path, steps=2 * 256, envs=4, eval_episodes=8)
    runs = {}
    for name, env in (("sync", TWO_GOALS), ("workers", WORKERS)):
        cfg = dataclasses.replace(base, env=env, run=dataclasses.replace(base.run, name=name))
        runs[name] = train(cfg)
    ours, theirs = (load_agent(runs[name].model_dir)[0].state_dict() for name in ("workers", "sync"))
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
    timing = {"train_seconds"}
    assert {k: v for k, v in runs["workers"].evaluation.items() if k not in timing} == {
        k: v for k, v in runs["sync"].evaluation.items() if k not in timing
    }


def test_a_dead_worker_is_one_line_and_the_config_is_checked():
    env = make_batched_env(WORKERS, 4, seed=0)
    try:
        os.kill(env._processes[1].pid, signal.SIGKILL)
        env._processes[1].join()
        with pytest.raises(WorkerError, match=r"env worker 1 of 2 (died|is gone)"):
            env.step(torch.zeros(4, dtype=torch.int64))
    finally:
        env.close()
    with pytest.raises(ConfigError, match=r"num_envs must be an integer in \[1, 4096\]"):
        WorkerBatchedEnv(WORKERS, 10**9)  # refused before any shared buffer is allocated
    for bad in (0, 65, True, "2"):
        with pytest.raises(ConfigError, match=r"env\.workers must be an integer in"):
            GymnasiumEnvConfig(TWO_GOALS.id, vectorization="workers", workers=bad)
    saved = to_dict(WORKERS)
    assert saved["vectorization"] == "workers" and saved["workers"] == 2
    assert from_dict(GymnasiumEnvConfig, saved) == WORKERS
    assert "workers" not in to_dict(TWO_GOALS)  # sync configs are saved as before
