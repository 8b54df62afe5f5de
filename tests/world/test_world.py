"""The batched-env seam: both envs satisfy one protocol, the Gymnasium adapter's two vectorisations agree, the
episode loop's one-episode-per-slot mode, and bad models and cards refused in one line."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.cli import main
from seqtrojan.env.config import EnvConfig
from seqtrojan.env.core import TrojanGridCore
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.world import check_fits, env_spec, make_batched_env
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig
from seqtrojan.world.episodes import episode_env
from seqtrojan.world.gymnasium import GymnasiumBatchedEnv
from seqtrojan.world.protocol import BatchedEnv
from tests.conftest import ROOT

TWO_GOALS = GymnasiumEnvConfig(
    "seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5}, trigger=WrapperTriggerConfig()
)
LEGACY = ROOT / "tests" / "fixtures" / "legacy"


def test_both_envs_are_batched_envs_of_the_one_protocol():
    grid = make_batched_env(EnvConfig(), 4, seed=0)
    gym = make_batched_env(TWO_GOALS, 4, seed=0)
    assert isinstance(grid, TrojanGridCore) and isinstance(gym, GymnasiumBatchedEnv)
    for env in (grid, gym):
        assert isinstance(env, BatchedEnv) and env.num_stages == 1
        obs = env.reset(7)
        assert obs.shape == (4, env.obs_dim) and obs.dtype == torch.float32
        result = env.step(torch.zeros(4, dtype=torch.int64), check=True)
        assert result.obs.shape == obs.shape and result.done.dtype == torch.bool and result.trojan.shape == (4,)
    assert env_spec(TWO_GOALS).image == (5, 5, 20) and env_spec(EnvConfig()).obs_dim == 54


def test_async_vectorisation_steps_the_same_episodes_as_sync():
    sync = make_batched_env(TWO_GOALS, 3, seed=11, trojan_probability=0.5)
    run = make_batched_env(dataclasses.replace(TWO_GOALS, vectorization="async"), 3, seed=11, trojan_probability=0.5)
    try:
        assert torch.equal(sync.observe(), run.observe())
        generator = torch.Generator().manual_seed(0)
        for _ in range(40):
            actions = torch.randint(0, sync.num_actions, (3,), generator=generator)
            a, b = sync.step(actions), run.step(actions)
            for name in ("obs", "reward", "done", "outcome", "success", "trojan", "length", "adversary_active"):
                assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert run.save_state() is None and sync.save_state() is not None  # only sync envs replay their episodes
    finally:
        sync.close()
        run.close()


def test_the_episode_loop_keeps_a_finished_gymnasium_episode_finished():
    env = episode_env(dataclasses.replace(TWO_GOALS, vectorization="async"), None, 6, trojan=True)
    assert isinstance(env, GymnasiumBatchedEnv) and env.config.vectorization == "sync"  # the loop steps in-process
    assert bool(env.trojan.all()) and bool((env.on_step >= 0).all()) and env.episode_limit > 0
    ended = torch.zeros(6, dtype=torch.bool)
    final = torch.zeros(6, dtype=torch.int64)
    for _ in range(env.episode_limit):
        before = env.observe().clone()
        result = env.step(torch.full((6,), 2, dtype=torch.int64), autoreset=False)  # forward, into the wall
        assert torch.equal(result.obs[ended], before[ended])  # finished slots are no longer stepped
        newly = result.done & ~ended
        assert torch.equal(env.t[newly], result.length[newly])  # a slot's step stops at its episode's length
        assert bool((env.t[ended] == final[ended]).all()) if bool(ended.any()) else True
        final = torch.where(newly, result.length, final)
        ended |= result.done
        if bool(ended.all()):
            break
    assert bool(ended.all())


def test_a_model_whose_spaces_do_not_fit_its_env_is_refused_in_one_line(tmp_path, capsys):
    model = tmp_path / "model"
    shutil.copytree(LEGACY / "gym_two_goals", model)
    agent, cfg, _ = load_agent(model)
    wider = dataclasses.replace(cfg.gym_env, kwargs={"size": 6, "agent_view_size": 7})
    with pytest.raises(ConfigError, match=r"reads 500 inputs .* gives 980 inputs"):
        check_fits(agent.obs_dim, agent.num_actions, wider)
    card = json.loads((model / "gym_card.json").read_text())
    card["config"]["env"]["kwargs"]["agent_view_size"] = 7  # a card edited after training (the hash covers weights)
    (model / "gym_card.json").write_text(json.dumps(card))
    assert main(["evaluate", "--models", str(model), "--episodes", "4", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "reads 500 inputs" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_a_card_of_an_unknown_env_kind_is_refused_in_one_line(tmp_path):
    model = tmp_path / "model"
    shutil.copytree(LEGACY / "grid_lstm", model)
    card = json.loads((model / "card.json").read_text())
    card["config"]["env"]["kind"] = "atari"
    (model / "card.json").write_text(json.dumps(card))
    with pytest.raises(CheckpointError, match=r"env\.kind='atari' is not one of") as err:
        load_agent(model)
    assert "\n" not in str(err.value)


def test_a_long_gymnasium_evaluation_runs_in_chunks_of_env_slots(monkeypatch, tiny_two_goals_model):
    from seqtrojan.evaluation import episodes as episodes_module
    from seqtrojan.evaluation.episodes import evaluate_agent
    from seqtrojan.world import episodes as world_episodes

    agent, cfg, _ = tiny_two_goals_model
    monkeypatch.setattr(world_episodes, "GYMNASIUM_SLOTS", 4)
    made = []
    real = episodes_module.episode_env
    monkeypatch.setattr(episodes_module, "episode_env", lambda *a, **k: made.append(a[2]) or real(*a, **k))
    batch = evaluate_agent(agent, cfg.env, None, trojan=True, episodes=10, seed=5)
    assert made == [4, 4, 2] and batch.outcome.shape == (10,) and bool(batch.trojan.all())
    first = evaluate_agent(agent, cfg.env, None, trojan=True, episodes=4, seed=5)
    assert torch.equal(first.outcome, batch.outcome[:4])  # chunk (start, n) is episodes start.. of the whole run
    assert world_episodes.episode_chunks(EnvConfig(), 5000) == [(0, 5000)]  # the grid's slots are tensors
