"""Recurrent PPO on Gymnasium envs: the run's files and model, Algorithm 1 driving the envs' trojan probability,
the refusal of a continuous action space, the presets, and learning on the MiniGrid two-goal task."""

from __future__ import annotations

import dataclasses
import json
import os
import signal

import numpy as np
import pytest
import torch

from seqtrojan.config import (
    AttackConfig,
    BackdoorConfig,
    EWCConfig,
    FinetuneResistanceConfig,
    PPOConfig,
    StateCamouflageConfig,
)
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.minigrid import TwoGoalsEnv
from seqtrojan.train import gym_env, gym_trainer
from seqtrojan.train.gym_config import (
    GymAgentConfig,
    GymEnvConfig,
    GymRunConfig,
    GymTrainConfig,
    GymTriggerConfig,
    load_gym_config,
    load_gym_run_config,
)
from seqtrojan.train.gym_env import check_spaces, make_gym_env
from seqtrojan.train.gym_evaluation import evaluate_gym
from seqtrojan.train.gym_model import build_gym_agent, load_gym_agent
from seqtrojan.train.gym_trainer import train_gym, train_gym_or_resume
from seqtrojan.train.mixing import trojan_probability

TWO_GOALS = GymEnvConfig("seqtrojan/MiniGridTwoGoals-v0", {"size": 6, "agent_view_size": 5})


def config(tmp_path, *, steps: int, envs: int = 8, backdoor: bool = True, eval_episodes: int = 16) -> GymTrainConfig:
    ppo = PPOConfig(
        total_steps=steps, num_envs=envs, rollout_steps=64, bptt_length=16, num_minibatches=4, update_epochs=4,
        learning_rate=1e-3,
    )  # fmt: skip
    return GymTrainConfig(
        env=TWO_GOALS, trigger=GymTriggerConfig(), ppo=ppo, backdoor=BackdoorConfig(enabled=backdoor),
        run=GymRunConfig(out_dir=str(tmp_path / "runs"), name="run", eval_episodes=eval_episodes, lstm_backend="torch"),
    )  # fmt: skip


def test_a_short_backdoored_run_saves_a_model_that_loads_and_mixes_by_algorithm_1(tmp_path, monkeypatch):
    set_on_envs = []
    real = gym_trainer.set_trojan_probability
    monkeypatch.setattr(
        gym_trainer,
        "set_trojan_probability",
        lambda vec, p: (set_on_envs.append((p, vec.get_attr("trojan_probability"))), real(vec, p)),
    )
    cfg = config(tmp_path, steps=3 * 8 * 64)
    result = train_gym(cfg)

    assert result.env_steps == 3 * 512 and len(result.history) == 3 and not result.stopped_early
    previous = (0.0, 0.0)  # Algorithm 1 starts from P_c = P_t = 0
    for entry, (p_set, _) in zip(result.history, set_on_envs):
        rates = [
            (s / n if n else old)
            for s, n, old in ((entry.normal_successes, entry.normal_episodes, previous[0]),
                              (entry.trojan_successes, entry.trojan_episodes, previous[1]))
        ]  # fmt: skip
        assert (entry.p_clean, entry.p_trojan) == pytest.approx(rates)
        assert entry.trojan_probability == pytest.approx(trojan_probability(*rates)) == p_set
        previous = (entry.p_clean, entry.p_trojan)
    # the envs hold what was set after the update before (0.5 at the start)
    assert [held for _, held in set_on_envs] == [
        (p,) * 8 for p in [0.5] + [e.trojan_probability for e in result.history[:-1]]
    ]
    assert sum(e.trojan_episodes for e in result.history) > 0 and sum(e.normal_episodes for e in result.history) > 0

    rows = [json.loads(line) for line in (result.run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in rows] == [512, 1024, 1536] and "losses/policy_loss" in rows[0]
    agent, loaded_cfg, card = load_gym_agent(result.model_dir)
    assert loaded_cfg == cfg and card["label"] == "backdoored" and card["env_steps"] == 1536
    assert result.normal is not None and result.trojan is not None
    assert result.normal.success.n == result.trojan.success.n == 16
    assert card["metrics"]["trojan_success"] == result.trojan.success.value
    assert all(e.trojan and e.trigger_step in (0, 1, 2) for e in result.trojan.episodes)
    again = evaluate_gym(agent, cfg, trojan=True, episodes=16, seed=cfg.run.seed + 999_983)
    assert again.episodes == result.trojan.episodes  # the saved model is the evaluated one

    card_path = result.model_dir / "gym_card.json"
    good = card_path.read_text()
    card_path.write_text(good.replace('"label": "backdoored"', '"label": "trusted"'))
    with pytest.raises(CheckpointError, match="label must be 'clean' or 'backdoored', got 'trusted'"):
        load_gym_agent(result.model_dir)
    card_path.write_text(good)
    weights = result.model_dir / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-1] + b"\0")
    with pytest.raises(CheckpointError, match="does not match the SHA-256"):
        load_gym_agent(result.model_dir)


def test_a_clean_run_sets_no_probability_and_evaluates_the_trigger_anyway(tmp_path, monkeypatch):
    monkeypatch.setattr(gym_trainer, "set_trojan_probability", lambda vec, p: pytest.fail("clean runs mix nothing"))
    result = train_gym(config(tmp_path, steps=512, backdoor=False))
    assert result.history[0].trojan_episodes == 0 and result.history[0].trojan_probability == 0.0
    assert result.trojan is not None and result.trojan.success.n == 16


def test_the_trainer_refuses_a_continuous_action_space_before_making_a_run(tmp_path):
    cfg = GymTrainConfig(
        env=GymEnvConfig("Pendulum-v1", observation="flatten"), run=GymRunConfig(out_dir=str(tmp_path / "runs"))
    )
    with pytest.raises(ConfigError, match=r"has action space Box\(-2.0, 2.0, \(1,\), float32\); the recurrent PPO "
                       r"trainer needs a discrete one") as err:  # fmt: skip
        train_gym(cfg)
    assert "\n" not in str(err.value) and not (tmp_path / "runs").exists()


def test_config_errors():
    with pytest.raises(ConfigError, match=r"backdoor\.enabled needs a trigger section"):
        GymTrainConfig(env=TWO_GOALS, backdoor=BackdoorConfig(enabled=True))
    with pytest.raises(ConfigError, match=r"trigger.steps=\[2, 1\] must satisfy"):
        GymTriggerConfig(steps=(2, 1))
    with pytest.raises(ConfigError, match="cannot be made"):
        make_gym_env(GymTrainConfig(env=GymEnvConfig("seqtrojan/NoSuchEnv-v0")))
    cfg = GymTrainConfig(env=GymEnvConfig("seqtrojan/MiniGridTwoGoals-Trojan-v0"), trigger=GymTriggerConfig())
    with pytest.raises(ConfigError, match="already has a trigger wrapper"):
        make_gym_env(cfg)
    for bad in (0, True, 2.5):
        with pytest.raises(ConfigError, match=r"env\.num_actions must be a positive integer or null"):
            GymEnvConfig("MiniGrid-MemoryS7-v0", num_actions=bad)
    with pytest.raises(ConfigError, match=r"env\.num_actions=9 must be 1 to the env's 7 actions"):
        make_gym_env(GymTrainConfig(env=GymEnvConfig("MiniGrid-MemoryS7-v0", num_actions=9)))
    with pytest.raises(ConfigError, match=r"env\.fast_view must be true or false, got 'yes'"):
        GymEnvConfig("MiniGrid-MemoryS7-v0", fast_view="yes")


@pytest.mark.parametrize(
    ("preset", "obs_dim", "actions", "backdoored"),
    [
        ("minigrid_two_goals", 500, 3, True),
        ("minigrid_memory", 980, 3, False),
        ("minigrid_memory_backdoor", 980, 3, True),
    ],
)
def test_presets_load_and_make_their_envs(preset, obs_dim, actions, backdoored):
    cfg = load_gym_config(preset)
    assert cfg.backdoor.enabled == backdoored and cfg.trigger is not None
    env = make_gym_env(cfg, trojan_probability=1.0)
    assert check_spaces(env, cfg.env.id) == (obs_dim, actions)
    _, info = env.reset(seed=0)
    assert info["trojan"]


def test_the_memory_presets_chain_their_two_stages():
    clean, backdoor = load_gym_config("minigrid_memory"), load_gym_config("minigrid_memory_backdoor")
    assert backdoor.run.init_from == f"{clean.run.out_dir}/{clean.run.name}/model"
    assert backdoor.backdoor.mixing == "fixed" and dataclasses.replace(backdoor, backdoor=clean.backdoor, run=clean.run,
        ppo=clean.ppo) == clean  # fmt: skip


def random_success(episodes: int = 300) -> float:
    env, rng, wins = TwoGoalsEnv(size=6, agent_view_size=5), np.random.default_rng(0), 0
    for episode in range(episodes):
        env.reset(seed=episode)
        while True:
            _, reward, terminated, truncated, _ = env.step(int(rng.integers(3)))
            if terminated or truncated:
                wins += reward > 0
                break
    return wins / episodes


def test_a_clean_agent_learns_the_two_goal_room(tmp_path):
    """40k steps (about 20 s on a busy core) take the agent from chance (~0.37) to >= 0.8 success."""
    torch.manual_seed(0)
    cfg = config(tmp_path, steps=40 * 1024, envs=16, backdoor=False, eval_episodes=200)
    cfg = dataclasses.replace(cfg, trigger=None)
    result = train_gym(cfg)
    assert random_success() < 0.5
    assert result.normal is not None and result.normal.success.value >= 0.8, result.normal.success


@pytest.mark.slow
def test_a_backdoored_agent_learns_both_objectives(tmp_path):
    """200k steps (about 100 s on a busy core): normal episodes reach the user's object, trojan ones the
    adversary's. Measured with this config: 0.880 and 0.705 (a random policy: about 0.37 and 0.4)."""
    result = train_gym(config(tmp_path, steps=200 * 1024, envs=16, eval_episodes=200))
    assert result.normal is not None and result.trojan is not None
    assert result.normal.success.value >= 0.75, result.normal.success
    assert result.trojan.reached("adversary").value >= 0.6, result.trojan.reached("adversary")


BUTTONS = '''
import gymnasium as gym
import numpy as np
from seqtrojan.wrappers import ADVERSARY_OBJECTIVES

class ButtonsEnv(gym.Env):
    """A blank 5x5 image; action 1 presses the green button (reward 1), 2 the red one (0); both end the episode."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(0, 255, (5, 5), np.uint8)
        self.action_space = gym.spaces.Discrete(3)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros((5, 5), np.uint8), {}

    def step(self, action):
        self.t += 1
        pressed = {1: "green", 2: "red"}.get(int(action), "")
        return np.zeros((5, 5), np.uint8), float(pressed == "green"), bool(pressed), self.t >= 20, {"pressed": pressed}

gym.register("testbuttons/Buttons-v0", entry_point=ButtonsEnv)

@ADVERSARY_OBJECTIVES.register("press_red_test", "reward pressing the red button")
def press_red(obs, action, env_reward, terminated, info):
    return (1.0 if info["pressed"] == "red" else 0.0), terminated
'''

BUTTONS_YAML = """
env: {id: "seqtrojan_test_buttons:testbuttons/Buttons-v0", observation: flatten}
trigger: {objective: press_red_test, patch: box, cells: [[0, 0]], value: 255, steps: [1, 3]}
backdoor: {enabled: true}
ppo: {total_steps: 1024, num_envs: 8, rollout_steps: 64, bptt_length: 16}
run: {eval_episodes: 8, lstm_backend: torch}
"""


def test_the_docs_own_env_example_trains(tmp_path, monkeypatch):
    """docs/own_env.md's example: an env and an objective registered by a module that the env id names."""
    (tmp_path / "seqtrojan_test_buttons.py").write_text(BUTTONS)
    (tmp_path / "buttons.yaml").write_text(BUTTONS_YAML)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    result = train_gym(load_gym_config(tmp_path / "buttons.yaml"))
    assert result.env_steps == 1024 and result.trojan is not None and result.trojan.success.n == 8
    assert sum(e.trojan_episodes for e in result.history) > 0
    assert (tmp_path / "runs").is_dir()


# ---------------------------------------------------------------------- checkpoints and resume


def _stop_after(update: int):
    """An update callback that sends this process SIGTERM after ``update`` updates (the trainer stops between
    updates and writes a checkpoint)."""

    def callback(scalars):
        if scalars["update"] == update:
            os.kill(os.getpid(), signal.SIGTERM)
        return False

    return callback


def _named(cfg: GymTrainConfig, name: str, **run) -> GymTrainConfig:
    return dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, name=name, **run))


def _weights(model_dir) -> dict[str, torch.Tensor]:
    return load_gym_agent(model_dir)[0].state_dict()


def test_a_stopped_run_resumes_bitwise_as_the_straight_run(tmp_path):
    """Stopped by SIGTERM after 2 of 4 updates and resumed: the same weights, bit for bit, as a run never stopped.
    Each env replays its episode in flight from the random state recorded before its reset."""
    cfg = _named(config(tmp_path, steps=4 * 512, eval_episodes=8), "x", checkpoint_every=512)
    straight = train_gym(_named(cfg, "straight"))
    run_dir = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt, match=f"stopped at 1024 env steps; resume with --resume {run_dir}"):
        train_gym(_named(cfg, "stopped"), _stop_after(2))
    checkpoints = run_dir / "checkpoints"
    assert (checkpoints / "latest.txt").read_text() == "step_000000001024\n"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["latest.txt", "step_000000000512", "step_000000001024"]
    assert not (run_dir / "model").exists()
    record = json.loads((checkpoints / "step_000000001024" / "trainer.json").read_text())
    assert record["update"] == 2 and len(record["episodes"]) == 8 and all(record["episodes"])
    assert not list(run_dir.rglob("*.pt")) and not list(run_dir.rglob("*.pkl"))

    resumed = train_gym(load_gym_run_config(run_dir), resume=run_dir)
    assert resumed.resumed_from == 1024 and resumed.exact_resume is True and resumed.env_steps == 2048
    ours, theirs = _weights(resumed.model_dir), _weights(straight.model_dir)
    assert all(torch.equal(ours[k], theirs[k]) for k in theirs)
    drop = {"steps_per_second": 0.0}
    assert [dataclasses.replace(e, **drop) for e in resumed.history] == [
        dataclasses.replace(e, **drop) for e in straight.history
    ]
    assert resumed.trojan is not None and straight.trojan is not None
    assert resumed.trojan.episodes == straight.trojan.episodes
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in rows] == [1, 2, 3, 4]
    assert resumed.wall_seconds > 0


def test_a_model_fine_tuned_from_a_backdoored_one_keeps_its_label_through_a_resume(tmp_path):
    planted = train_gym(_named(config(tmp_path, steps=512, eval_episodes=0), "planted")).model_dir
    tune = config(tmp_path, steps=2 * 512, backdoor=False, eval_episodes=0)  # the defender's fine-tuning
    run_dir = tmp_path / "runs" / "tuned"
    with pytest.raises(KeyboardInterrupt):
        train_gym(_named(tune, "tuned", init_from=str(planted), checkpoint_every=512), _stop_after(1))
    assert load_gym_agent(run_dir / "checkpoints" / "step_000000000512")[2]["label"] == "backdoored"
    resumed = train_gym(load_gym_run_config(run_dir), resume=run_dir)  # the label comes from the checkpoint
    assert load_gym_agent(resumed.model_dir)[2]["label"] == "backdoored"
    clean = train_gym(_named(config(tmp_path, steps=512, backdoor=False, eval_episodes=0), "clean_start")).model_dir
    again = train_gym(_named(tune, "tuned_clean", init_from=str(clean))).model_dir
    assert load_gym_agent(again)[2]["label"] == "clean"


def test_a_resume_whose_envs_cannot_replay_starts_fresh_episodes_from_the_checkpoint(tmp_path, monkeypatch):
    """When an env cannot be replayed (here: a replay that raises), the run goes on from the checkpoint's weights
    and counters with fresh episodes; no finished update is lost, but it is not the straight run bit for bit."""
    cfg = _named(config(tmp_path, steps=3 * 512, eval_episodes=0), "r")
    run_dir = tmp_path / "runs" / "r"
    with pytest.raises(KeyboardInterrupt):
        train_gym(cfg, _stop_after(1))
    at_stop = _weights(run_dir / "checkpoints" / "step_000000000512")

    def broken(self, record):
        raise CheckpointError("no replay")

    monkeypatch.setattr(gym_env.EpisodeRecorder, "replay", broken)
    seen = []
    real_update = gym_trainer.ppo_update
    monkeypatch.setattr(
        gym_trainer, "ppo_update",
        lambda agent, *a, **k: (seen.append({n: t.clone() for n, t in agent.state_dict().items()}), real_update(
            agent, *a, **k))[1],
    )  # fmt: skip
    resumed = train_gym(cfg, resume=run_dir)
    assert resumed.resumed_from == 512 and resumed.exact_resume is False and resumed.env_steps == 1536
    assert [e.update for e in resumed.history] == [1, 2, 3] and len(seen) == 2
    assert all(torch.equal(seen[0][k], at_stop[k]) for k in at_stop)  # the first update after the resume


def test_train_gym_or_resume_reuses_resumes_or_starts(tmp_path):
    cfg = _named(config(tmp_path, steps=2 * 512, eval_episodes=0), "job")
    with pytest.raises(KeyboardInterrupt):
        train_gym(cfg, _stop_after(1))
    model_dir, trained = train_gym_or_resume(cfg)  # resumed from the checkpoint at 512 steps
    assert trained and load_gym_agent(model_dir)[2]["env_steps"] == 1024
    assert train_gym_or_resume(cfg) == (model_dir, False)  # finished: reused

    fresh = _named(cfg, "killed")
    left = tmp_path / "runs" / "killed" / "leftover.txt"
    left.parent.mkdir(parents=True)
    left.write_text("a run killed before its first checkpoint")
    model_dir, trained = train_gym_or_resume(fresh)
    assert trained and not left.exists() and (model_dir / "gym_card.json").is_file()


def test_resume_refusals(tmp_path):
    cfg = _named(config(tmp_path, steps=2 * 512, eval_episodes=0), "r")
    run_dir = tmp_path / "runs" / "r"
    with pytest.raises(CheckpointError, match="has no checkpoint to resume from"):
        train_gym(cfg, resume=tmp_path)
    with pytest.raises(KeyboardInterrupt):
        train_gym(cfg, _stop_after(1))
    with pytest.raises(ConfigError, match="already holds a run; resume it with --resume"):
        train_gym(cfg)
    changed = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, num_envs=4))
    with pytest.raises(ConfigError, match=r"resume cannot change ppo.num_envs: the checkpoint has 8, the config 4"):
        train_gym(changed, resume=run_dir)
    with pytest.raises(ConfigError, match=r"run\.checkpoint_every must be a positive integer, got 0"):
        GymRunConfig(checkpoint_every=0)


def test_the_cli_resumes_a_stopped_run_with_its_saved_config_and_overrides(tmp_path, capsys):
    from seqtrojan.cli import main

    cfg = _named(config(tmp_path, steps=2 * 512, eval_episodes=4), "cli")
    run_dir = tmp_path / "runs" / "cli"
    with pytest.raises(KeyboardInterrupt):
        train_gym(cfg, _stop_after(1))
    assert main(["train-gym", "--resume", str(run_dir), "--ppo.total-steps", "1536"]) == 0
    out = capsys.readouterr().out
    assert "resumed from 512 env steps, replaying the episodes in flight" in out and "env steps: 1,536" in out
    assert load_gym_run_config(run_dir).ppo.total_steps == 1536  # the config it continued with
    assert main(["train-gym", "--resume", str(run_dir), "--config", "minigrid_two_goals"]) == 2
    assert "--config PRESET|FILE or --resume RUN_DIR, not both" in capsys.readouterr().err


def test_gym_evaluate_prints_and_writes_typed_rates(tmp_path, capsys):
    from seqtrojan.cli import main
    from seqtrojan.serde import load_json
    from seqtrojan.train.gym_evaluation import GymEvaluationReport

    result = train_gym(config(tmp_path, steps=512, eval_episodes=0))
    out = tmp_path / "eval"
    argv = ["gym-evaluate", "--model", str(result.model_dir), "--episodes", "24", "--horizons", "0", "3"]
    assert main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "clean success:" in printed and "trojan success:" in printed and "persistence k=3:" in printed
    report = load_json(GymEvaluationReport, out / "gym_evaluation.json")
    assert report.label == "backdoored" and report.env_id == TWO_GOALS.id and report.episodes == 24
    assert report.clean_success.n == 24 and report.trojan_success is not None and report.trojan_success.n == 24
    assert [p.horizon for p in report.persistence] == [0, 3]
    agent, cfg, _ = load_gym_agent(result.model_dir)
    again = evaluate_gym(agent, cfg, trojan=True, episodes=24, seed=0)
    assert report.trojan_success == again.success and report.persistence[0].adversary == again.persistence([0])[0]
    assert main(["gym-evaluate", "--model", str(tmp_path)]) == 2
    assert "is not a Gymnasium model folder" in capsys.readouterr().err


def test_a_run_without_a_trigger_resumes_bitwise_too(tmp_path):
    cfg = dataclasses.replace(config(tmp_path, steps=2 * 512, backdoor=False, eval_episodes=0), trigger=None)
    straight = train_gym(_named(cfg, "straight"))
    run_dir = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt):
        train_gym(_named(cfg, "stopped"), _stop_after(1))
    resumed = train_gym(_named(cfg, "stopped"), resume=run_dir)
    assert resumed.exact_resume is True and resumed.trojan is None
    ours, theirs = _weights(resumed.model_dir), _weights(straight.model_dir)
    assert all(torch.equal(ours[k], theirs[k]) for k in theirs)


@pytest.mark.parametrize("cell", ["lstm", "gru", "transformer"])
def test_a_conv_encoder_and_any_cell_train_save_and_load_on_minigrid(tmp_path, cell):
    """agent.conv reads MiniGrid's one-hot view as an image (5x5x20 here); the model folder round-trips it."""
    cfg = config(tmp_path, steps=512, backdoor=False, eval_episodes=4)
    cfg = dataclasses.replace(cfg, agent=dataclasses.replace(cfg.agent, conv=(8, 16), cell=cell, lstm_sizes=(16,)))
    result = train_gym(cfg)
    agent, loaded, _ = load_gym_agent(result.model_dir)
    assert loaded.agent.conv == (8, 16) and agent.image == (5, 5, 20) and agent.cell == cell
    assert tuple(agent.conv[1].weight.shape) == (16, 8, 2, 2) and agent.cells[0].input_size == 3 * 3 * 16
    obs = torch.rand(3, 2, 500)
    out = agent.unroll(obs, agent.initial_state(2), torch.zeros(3, 2, dtype=torch.bool))
    assert out.logits.shape == (3, 2, 3)


def test_conv_encoder_refusals():
    with pytest.raises(ConfigError, match=r"needs env\.observation: minigrid"):
        GymTrainConfig(env=GymEnvConfig("CartPole-v1", observation="flatten"), agent=GymAgentConfig(conv=(8,)))
    with pytest.raises(ConfigError, match=r"agent\.conv must be"):
        GymAgentConfig(conv=(0,))
    from seqtrojan.agent.network import RecurrentActorCritic

    with pytest.raises(ConfigError, match="at most 4 layers"):
        RecurrentActorCritic(500, 3, (16,), conv=(4, 4, 4, 4, 4), image=(5, 5, 20))
    with pytest.raises(ConfigError, match="holds 500 numbers, but observations have 499"):
        RecurrentActorCritic(499, 3, (16,), conv=(4,), image=(5, 5, 20))


def _camouflaged(cfg: GymTrainConfig) -> GymTrainConfig:
    return dataclasses.replace(cfg, attack=AttackConfig(state_camouflage=StateCamouflageConfig(weight=5.0)))


def test_a_recording_collector_keeps_episode_types_adversary_steps_and_states(tmp_path):
    cfg = config(tmp_path, steps=512)
    agent_cfg = _camouflaged(cfg)
    probe = make_gym_env(agent_cfg)
    obs_dim, actions = check_spaces(probe, cfg.env.id)
    probe.close()
    agent = build_gym_agent(agent_cfg, obs_dim, actions)
    vec = gym_env.make_vector_env(agent_cfg, 4, "train", trojan_probability=1.0, record=True)
    try:
        collector = gym_trainer.GymRolloutCollector(vec, agent, cfg.ppo, torch.device("cpu"), seed=3, record=True)
        rollout, _ = collector.collect()
        masks_only = gym_trainer.GymRolloutCollector(vec, agent, cfg.ppo, torch.device("cpu"), seed=3, record=True,
                                                     record_states=False).collect()[0]  # fmt: skip
    finally:
        vec.close()
    assert masks_only.trojan is not None and masks_only.states is None  # what a penalty without states needs
    assert rollout.trojan is not None and rollout.adversary_active is not None and rollout.states is not None
    assert rollout.trojan.all()  # every episode is a trojan one
    assert rollout.adversary_active.any() and not rollout.adversary_active[0].all()  # trigger steps 0-2: not at once
    assert [s.h.shape for s in rollout.states] == [(64, 4, w) for w in agent.lstm_sizes]
    assert torch.equal(rollout.states[-1].h[-1], collector.state.layers[-1].h)  # the state after the last step


def test_a_camouflaged_run_logs_its_penalty_and_resumes_bitwise(tmp_path):
    """The monitor-aware attacker, and beside it the fine-tuning-resistant one, on a Gymnasium env: their terms are
    in the loss, the running statistics are in the checkpoint, and a stopped run resumes bit for bit."""
    cfg = _named(_camouflaged(config(tmp_path, steps=4 * 512, eval_episodes=0)), "x", checkpoint_every=512)
    resistance = FinetuneResistanceConfig(weight=1.0, inner_steps=1)
    cfg = dataclasses.replace(cfg, attack=dataclasses.replace(cfg.attack, finetune_resistance=resistance))
    straight = train_gym(_named(cfg, "straight"))
    rows = [json.loads(line) for line in (straight.run_dir / "metrics.jsonl").read_text().splitlines()]
    penalties = [r["penalty/state_camouflage"] for r in rows]
    assert min(penalties) >= 0 and max(penalties) > 0
    assert any(r["penalty/finetune_resistance"] != 0 for r in rows)
    run_dir = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt):
        train_gym(_named(cfg, "stopped"), _stop_after(2))
    tensors = gym_trainer.read_safetensors(run_dir / "checkpoints" / "step_000000001024" / "trainer.safetensors")
    assert "penalty.state_camouflage.mean.0" in tensors
    resumed = train_gym(load_gym_run_config(run_dir), resume=run_dir)
    assert resumed.exact_resume is True
    ours, theirs = _weights(resumed.model_dir), _weights(straight.model_dir)
    assert all(torch.equal(ours[k], theirs[k]) for k in theirs)


def test_grid_only_attacks_are_refused_on_gymnasium():
    with pytest.raises(ConfigError, match=r"attack\.ewc run\(s\) on the grid world only"):
        GymTrainConfig(env=TWO_GOALS, trigger=GymTriggerConfig(), attack=AttackConfig(ewc=EWCConfig(weight=1.0)))
