"""Recurrent PPO on Gymnasium envs (the one trainer, ``env.kind: gymnasium``): the run's files and model, Algorithm
1 driving the envs' trojan probability, the refusal of a continuous action space, the presets, learning on the
MiniGrid two-goal task, and stopped runs that resume bit for bit (each env replays its episode in flight)."""

from __future__ import annotations

import dataclasses
import json
import os
import signal

import numpy as np
import pytest
import torch

from seqtrojan.agent.card import Architecture
from seqtrojan.agent.checkpoint import build_agent, load_agent, read_safetensors
from seqtrojan.config import (
    AgentConfig,
    AttackConfig,
    BackdoorConfig,
    EWCConfig,
    ExperimentConfig,
    FinetuneResistanceConfig,
    PPOConfig,
    RunConfig,
    StateCamouflageConfig,
    StopConfig,
    WeightCamouflageConfig,
)
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.evaluation.batched import evaluate_on_env
from seqtrojan.evaluation.env_report import run_outcomes
from seqtrojan.minigrid import TwoGoalsEnv
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.train import trainer as trainer_module
from seqtrojan.train.mixing import trojan_probability
from seqtrojan.train.rollout import RolloutCollector
from seqtrojan.train.trainer import load_run_config, train, train_or_resume
from seqtrojan.world import EnvSpec, env_spec, make_batched_env
from seqtrojan.world import gymnasium as gym_world
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig
from seqtrojan.world.gymnasium import GymnasiumBatchedEnv, check_spaces, make_gym_env
from tests.train.resume import logged_rows

TWO_GOALS = GymnasiumEnvConfig(
    "seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5}, trigger=WrapperTriggerConfig()
)


def config(tmp_path, *, steps: int, envs: int = 8, backdoor: bool = True, eval_episodes: int = 16) -> ExperimentConfig:
    ppo = PPOConfig(
        total_steps=steps, num_envs=envs, rollout_steps=64, bptt_length=16, num_minibatches=4, update_epochs=4,
        learning_rate=1e-3,
    )  # fmt: skip
    return ExperimentConfig(
        env=TWO_GOALS, ppo=ppo, backdoor=BackdoorConfig(enabled=backdoor),
        run=RunConfig(out_dir=str(tmp_path / "runs"), name="run", eval_episodes=eval_episodes, lstm_backend="torch",
                      progress=False),
    )  # fmt: skip


def preset(name: str) -> ExperimentConfig:
    """A shipped preset as ``seqtrojan train --config NAME`` reads it."""
    return from_dict(ExperimentConfig, load_yaml(resolve_preset(name)), "")


def untriggered(cfg: ExperimentConfig) -> ExperimentConfig:
    return dataclasses.replace(cfg, env=dataclasses.replace(cfg.gym_env, trigger=None))


def metrics(run_dir) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def spy_on_probabilities(monkeypatch) -> list[tuple[float, tuple[float, ...]]]:
    """Every trojan probability the trainer sets on its Gymnasium envs, beside what the envs' triggers held then."""
    set_on_envs: list[tuple[float, tuple[float, ...]]] = []
    real = GymnasiumBatchedEnv.set_trojan_probability

    def spy(self, probability):
        held = tuple(t.trojan_probability for t in self.triggers if t is not None)
        set_on_envs.append((float(torch.as_tensor(probability, dtype=torch.float64).reshape(-1)[0]), held))
        real(self, probability)

    monkeypatch.setattr(GymnasiumBatchedEnv, "set_trojan_probability", spy)
    return set_on_envs


def test_a_short_backdoored_run_saves_a_model_that_loads_and_mixes_by_algorithm_1(tmp_path, monkeypatch):
    set_on_envs = spy_on_probabilities(monkeypatch)
    cfg = config(tmp_path, steps=3 * 8 * 64)
    result = train(cfg)

    rows = metrics(result.run_dir)
    assert result.env_steps == 3 * 512 and [r["update"] for r in rows] == [1, 2, 3]
    assert [r["env_steps"] for r in rows] == [512, 1024, 1536] and "losses/policy_loss" in rows[0]
    assert result.evaluation["stopped_early"] is False and result.exact_resume is None
    previous = (0.0, 0.0)  # Algorithm 1 starts from P_c = P_t = 0
    for row in rows:
        rates = [row.get(f"episodes/{kind}_success", old) for kind, old in zip(("normal", "trojan"), previous)]
        assert (row["mixing/P_c"], row["mixing/P_t"]) == pytest.approx(rates)
        assert row["mixing/p_trojan"] == pytest.approx(trojan_probability(*rates))
        previous = (row["mixing/P_c"], row["mixing/P_t"])
    # set on the envs: Algorithm 1's start (0.5) before the first rollout, then each update's probability
    probabilities = [r["mixing/p_trojan"] for r in rows]
    assert [p for p, _ in set_on_envs] == [0.5, *probabilities]
    # the envs hold what was set before (they are built with 0)
    assert [held for _, held in set_on_envs] == [(p,) * 8 for p in [0.0, 0.5, *probabilities[:-1]]]
    assert sum(r.get("episodes/trojan_count", 0) for r in rows) > 0
    assert sum(r.get("episodes/normal_count", 0) for r in rows) > 0

    agent, loaded_cfg, card = load_agent(result.model_dir)
    assert loaded_cfg == cfg and card["label"] == "backdoored" and card["env_steps"] == 1536
    ev = result.evaluation
    assert ev["env"] == TWO_GOALS.id and ev["episodes"] == 16 and {"normal_success", "trojan_success"} <= set(ev)
    assert card["metrics"] == ev == json.loads((result.run_dir / "evaluation.json").read_text())
    seed = (cfg.run.seed << 32) + 999_983  # the final evaluation's
    again = evaluate_on_env(agent, loaded_cfg, trojan=True, episodes=16, seed=seed)
    assert again.success_rate == ev["trojan_success"] and bool(again.trojan.all())  # the saved model is the evaluated
    trojan = run_outcomes(agent, loaded_cfg, trojan=True, episodes=16, seed=seed)
    assert trojan.batch.outcome.numel() == 16 and bool(trojan.batch.trojan.all())
    assert set(trojan.trigger_step.tolist()) <= {0, 1, 2}  # every episode's trigger in the evaluation range

    card_path = result.model_dir / "card.json"
    good = card_path.read_text()
    card_path.write_text(good.replace('"label": "backdoored"', '"label": "trusted"'))
    with pytest.raises(CheckpointError, match=r"label must be one of \[.*\], got 'trusted'"):
        load_agent(result.model_dir)
    card_path.write_text(good)
    weights = result.model_dir / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-1] + b"\0")
    with pytest.raises(CheckpointError, match="does not match the SHA-256"):
        load_agent(result.model_dir)


def test_a_clean_run_mixes_in_no_trojan_episode_and_evaluates_the_trigger_anyway(tmp_path, monkeypatch):
    set_on_envs = spy_on_probabilities(monkeypatch)
    result = train(config(tmp_path, steps=512, backdoor=False))
    assert [p for p, _ in set_on_envs] == [0.0]  # a clean run sets none but 0
    (row,) = metrics(result.run_dir)
    assert row["episodes/normal_count"] > 0 and "episodes/trojan_count" not in row and "mixing/p_trojan" not in row
    assert result.evaluation["episodes"] == 16 and "trojan_success" in result.evaluation


def test_the_trainer_refuses_a_continuous_action_space_before_making_a_run(tmp_path):
    cfg = ExperimentConfig(
        env=GymnasiumEnvConfig("Pendulum-v1", observation="flatten"),
        run=RunConfig(out_dir=str(tmp_path / "runs"), progress=False),
    )
    with pytest.raises(ConfigError, match=r"has action space Box\(-2.0, 2.0, \(1,\), float32\); the recurrent "
                       r"agents need a discrete one") as err:  # fmt: skip
        train(cfg)
    assert "\n" not in str(err.value) and not (tmp_path / "runs").exists()


def test_config_errors():
    with pytest.raises(ConfigError, match=r"backdoor\.enabled needs env\.trigger"):
        ExperimentConfig(env=dataclasses.replace(TWO_GOALS, trigger=None), backdoor=BackdoorConfig(enabled=True))
    with pytest.raises(ConfigError, match=r"env\.trigger\.steps=\[2, 1\] must satisfy"):
        WrapperTriggerConfig(steps=(2, 1))
    with pytest.raises(ConfigError, match="cannot be made"):
        make_gym_env(GymnasiumEnvConfig("seqtrojan/NoSuchEnv-v0"))
    with pytest.raises(ConfigError, match="already has a trigger wrapper"):
        make_gym_env(GymnasiumEnvConfig("seqtrojan/MiniGridTwoGoals-Trojan-v0", trigger=WrapperTriggerConfig()))
    for bad in (0, True, 2.5):
        with pytest.raises(ConfigError, match=r"env\.num_actions must be a positive integer or null"):
            GymnasiumEnvConfig("MiniGrid-MemoryS7-v0", num_actions=bad)
    with pytest.raises(ConfigError, match=r"env\.num_actions=9 must be 1 to the env's 7 actions"):
        make_gym_env(GymnasiumEnvConfig("MiniGrid-MemoryS7-v0", num_actions=9))
    with pytest.raises(ConfigError, match=r"env\.fast_view must be true or false, got 'yes'"):
        GymnasiumEnvConfig("MiniGrid-MemoryS7-v0", fast_view="yes")


@pytest.mark.parametrize(
    ("name", "obs_dim", "actions", "backdoored"),
    [
        ("minigrid_two_goals", 500, 3, True),
        ("minigrid_memory", 980, 3, False),
        ("minigrid_memory_backdoor", 980, 3, True),
    ],
)
def test_presets_load_and_make_their_envs(name, obs_dim, actions, backdoored):
    cfg = preset(name)
    assert cfg.backdoor.enabled == backdoored and cfg.gym_env.trigger is not None and not cfg.is_grid
    env = make_gym_env(cfg.gym_env, trojan_probability=1.0)
    assert check_spaces(env, cfg.gym_env.id) == (obs_dim, actions)
    _, info = env.reset(seed=0)
    assert info["trojan"]
    side = 5 if name == "minigrid_two_goals" else 7
    assert env_spec(cfg.env) == EnvSpec(obs_dim, actions, (side, side, 20))


def test_the_memory_presets_chain_their_two_stages():
    clean, backdoor = preset("minigrid_memory"), preset("minigrid_memory_backdoor")
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


@pytest.mark.slow
def test_a_clean_agent_learns_the_two_goal_room(tmp_path):
    """40k steps (about 12 s on a quiet core, 20 s on a busy one) take the agent from chance (~0.37) to >= 0.8
    success."""
    torch.manual_seed(0)
    cfg = untriggered(config(tmp_path, steps=40 * 1024, envs=16, backdoor=False, eval_episodes=200))
    result = train(cfg)
    assert random_success() < 0.5
    assert result.evaluation["normal_success"] >= 0.8, result.evaluation
    assert "trojan_success" not in result.evaluation  # no trigger: nothing to measure it with


@pytest.mark.slow
def test_a_backdoored_agent_learns_both_objectives(tmp_path):
    """200k steps (about 100 s on a busy core): normal episodes reach the user's object, trojan ones the
    adversary's. Measured with this config: 0.880 and 0.705 (a random policy: about 0.37 and 0.4)."""
    cfg = config(tmp_path, steps=200 * 1024, envs=16, eval_episodes=200)
    result = train(cfg)
    assert result.evaluation["normal_success"] >= 0.75, result.evaluation
    agent, loaded, _ = load_agent(result.model_dir)
    trojan = evaluate_on_env(agent, loaded, trojan=True, episodes=200, seed=(cfg.run.seed << 32) + 999_983)
    assert trojan.success_rate == result.evaluation["trojan_success"]  # the final evaluation's episodes
    assert trojan.rate("adversary_goal") >= 0.6, trojan.rate("adversary_goal")


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
env:
  kind: gymnasium
  id: "seqtrojan_test_buttons:testbuttons/Buttons-v0"
  observation: flatten
  trigger: {objective: press_red_test, patch: box, cells: [[0, 0]], value: 255, steps: [1, 3]}
backdoor: {enabled: true}
ppo: {total_steps: 1024, num_envs: 8, rollout_steps: 64, bptt_length: 16}
run: {eval_episodes: 8, lstm_backend: torch, progress: false}
"""


def test_the_docs_own_env_example_trains(tmp_path, monkeypatch):
    """docs/own_env.md's example: an env and an objective registered by a module that the env id names. Stopped
    after its first update and resumed; the model card names the id the module registered (a card never names a
    module to import)."""
    (tmp_path / "seqtrojan_test_buttons.py").write_text(BUTTONS)
    (tmp_path / "buttons.yaml").write_text(BUTTONS_YAML)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    cfg = from_dict(ExperimentConfig, load_yaml(tmp_path / "buttons.yaml"), "")
    with pytest.raises(KeyboardInterrupt, match="stopped at 512 env steps"):
        train(cfg, callback=_stop_after(1))
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert load_run_config(run_dir) == cfg  # the run's config keeps the module:Id it was given
    result = train(load_run_config(run_dir), resume=run_dir)
    assert result.exact_resume is True and result.env_steps == 1024
    assert result.evaluation["episodes"] == 8 and "trojan_success" in result.evaluation
    assert sum(r.get("episodes/trojan_count", 0) for r in metrics(result.run_dir)) > 0
    _, loaded, card = load_agent(result.model_dir)
    assert loaded.env == dataclasses.replace(cfg.gym_env, id="testbuttons/Buttons-v0") and card["label"] == "backdoored"


# ---------------------------------------------------------------------- checkpoints and resume


def _stop_after(update: int):
    """An update callback that sends this process SIGTERM after ``update`` updates (the trainer stops between
    updates and writes a checkpoint)."""

    def callback(scalars):
        if scalars["update"] == update:
            os.kill(os.getpid(), signal.SIGTERM)
        return False

    return callback


def _named(cfg: ExperimentConfig, name: str, **run) -> ExperimentConfig:
    return dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, name=name, **run))


def _weights(model_dir) -> dict[str, torch.Tensor]:
    return load_agent(model_dir)[0].state_dict()


def _same_weights(ours: dict[str, torch.Tensor], theirs: dict[str, torch.Tensor]) -> bool:
    return ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in theirs)


def _first_steps(seen: list[int]):
    """A callback that records each update's env steps (the first: where a resumed run went on from)."""
    return lambda scalars: seen.append(scalars["env_steps"]) or False


def test_a_stopped_run_resumes_bitwise_as_the_straight_run(tmp_path):
    """Stopped by SIGTERM after 2 of 4 updates and resumed: the same weights, bit for bit, as a run never stopped.
    Each env replays its episode in flight from the random state recorded before its reset."""
    cfg = _named(config(tmp_path, steps=4 * 256, envs=4, eval_episodes=8), "x", checkpoint_every=256)
    straight = train(_named(cfg, "straight"))
    run_dir = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt, match=f"stopped at 512 env steps; resume with --resume {run_dir}"):
        train(_named(cfg, "stopped"), callback=_stop_after(2))
    checkpoints = run_dir / "checkpoints"
    assert (checkpoints / "latest.txt").read_text() == "step_000000000512\n"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["latest.txt", "step_000000000256", "step_000000000512"]
    assert not (run_dir / "model").exists()
    record = json.loads((checkpoints / "step_000000000512" / "trainer.json").read_text())
    assert record["update"] == 2 and len(record["episodes"]) == 4 and all(record["episodes"])
    carried = read_safetensors(checkpoints / "step_000000000512" / "trainer.safetensors")
    assert tuple(carried["collector.obs"].shape) == (4, 500)  # what the collector carries into the next rollout
    assert not list(run_dir.rglob("*.pt")) and not list(run_dir.rglob("*.pkl"))

    seen: list[int] = []
    resumed = train(load_run_config(run_dir), resume=run_dir, callback=_first_steps(seen))
    assert seen == [768, 1024] and resumed.exact_resume is True and resumed.env_steps == 1024  # from 512 on
    assert straight.exact_resume is None
    assert _same_weights(_weights(resumed.model_dir), _weights(straight.model_dir))
    assert logged_rows(run_dir) == logged_rows(straight.run_dir)  # every update's figures, bit for bit
    timing = {"train_seconds"}
    ours, theirs = ({k: v for k, v in r.evaluation.items() if k not in timing} for r in (resumed, straight))
    assert ours == theirs and "trojan_success" in ours  # the same final evaluation
    assert [r["update"] for r in metrics(run_dir)] == [1, 2, 3, 4]
    assert resumed.wall_seconds > 0


def test_a_run_interrupted_from_its_callback_resumes_to_the_uninterrupted_runs_weights(tmp_path):
    """Ctrl-C (KeyboardInterrupt from the update callback) after 2 updates, then a resume from the saved config:
    the weights are bitwise those of the run that was never interrupted, and the resume was an exact one."""
    base = preset("minigrid_two_goals")
    cfg = dataclasses.replace(
        base,
        ppo=dataclasses.replace(base.ppo, num_envs=8, rollout_steps=64, num_minibatches=2, total_steps=3072),
        run=dataclasses.replace(base.run, out_dir=str(tmp_path / "runs"), threads=1, eval_episodes=0, progress=False),
    )
    straight = train(_named(cfg, "straight"))

    def interrupt_after_two(scalars):
        if scalars["update"] == 2:
            raise KeyboardInterrupt
        return False

    run_dir = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt, match=f"stopped at 1024 env steps; resume with --resume {run_dir}"):
        train(_named(cfg, "stopped"), callback=interrupt_after_two)
    assert (run_dir / "checkpoints" / "latest.txt").read_text() == "step_000000001024\n"
    assert not (run_dir / "model").exists()
    resumed = train(load_run_config(run_dir), resume=run_dir)
    assert resumed.exact_resume is True and resumed.env_steps == straight.env_steps == 3072
    assert _same_weights(_weights(resumed.model_dir), _weights(straight.model_dir))


def test_a_model_fine_tuned_from_a_backdoored_one_keeps_its_label_through_a_resume(tmp_path):
    planted = train(_named(config(tmp_path, steps=512, eval_episodes=0), "planted")).model_dir
    tune = config(tmp_path, steps=2 * 512, backdoor=False, eval_episodes=0)  # the defender's fine-tuning
    run_dir = tmp_path / "runs" / "tuned"
    with pytest.raises(KeyboardInterrupt):
        train(_named(tune, "tuned", init_from=str(planted), checkpoint_every=512), callback=_stop_after(1))
    assert load_agent(run_dir / "checkpoints" / "step_000000000512")[2]["label"] == "backdoored"
    resumed = train(load_run_config(run_dir), resume=run_dir)  # the label comes from the checkpoint
    assert load_agent(resumed.model_dir)[2]["label"] == "backdoored"
    clean = train(_named(config(tmp_path, steps=512, backdoor=False, eval_episodes=0), "clean_start")).model_dir
    again = train(_named(tune, "tuned_clean", init_from=str(clean))).model_dir
    assert load_agent(again)[2]["label"] == "clean"


def test_a_resume_whose_envs_cannot_replay_starts_fresh_episodes_from_the_checkpoint(tmp_path, monkeypatch):
    """When an env cannot be replayed (here: a replay that raises), the run goes on from the checkpoint's weights
    and counters with fresh episodes; no finished update is lost, but it is not the straight run bit for bit."""
    cfg = _named(config(tmp_path, steps=3 * 512, eval_episodes=0), "r")
    run_dir = tmp_path / "runs" / "r"
    with pytest.raises(KeyboardInterrupt):
        train(cfg, callback=_stop_after(1))
    at_stop = _weights(run_dir / "checkpoints" / "step_000000000512")

    def broken(self, record):
        raise CheckpointError("no replay")

    monkeypatch.setattr(gym_world.EpisodeRecorder, "replay", broken)
    seen = []
    real_update = trainer_module.ppo_update
    monkeypatch.setattr(
        trainer_module, "ppo_update",
        lambda agent, *a, **k: (seen.append({n: t.clone() for n, t in agent.state_dict().items()}), real_update(
            agent, *a, **k))[1],
    )  # fmt: skip
    steps: list[int] = []
    resumed = train(cfg, resume=run_dir, callback=_first_steps(steps))
    assert steps == [1024, 1536] and resumed.exact_resume is False and resumed.env_steps == 1536  # from 512 on
    assert [r["update"] for r in metrics(run_dir)] == [1, 2, 3] and len(seen) == 2
    assert _same_weights(seen[0], at_stop)  # the first update after the resume


def test_train_or_resume_reuses_resumes_or_starts(tmp_path):
    cfg = _named(config(tmp_path, steps=2 * 512, eval_episodes=0), "job")
    with pytest.raises(KeyboardInterrupt):
        train(cfg, callback=_stop_after(1))
    model_dir, trained = train_or_resume(cfg)  # resumed from the checkpoint at 512 steps
    assert trained and load_agent(model_dir)[2]["env_steps"] == 1024
    assert [r["update"] for r in metrics(model_dir.parent)] == [1, 2]  # not started again
    assert train_or_resume(cfg) == (model_dir, False)  # finished: reused

    fresh = _named(cfg, "killed")
    left = tmp_path / "runs" / "killed" / "leftover.txt"
    left.parent.mkdir(parents=True)
    left.write_text("a run killed before its first checkpoint")
    model_dir, trained = train_or_resume(fresh)
    assert trained and not left.exists() and (model_dir / "card.json").is_file()
    assert not (model_dir / "gym_card.json").exists()  # one kind of model folder


def test_resume_refusals(tmp_path):
    cfg = _named(config(tmp_path, steps=2 * 512, eval_episodes=0), "r")
    run_dir = tmp_path / "runs" / "r"
    with pytest.raises(CheckpointError, match="has no checkpoint to resume from"):
        train(cfg, resume=tmp_path)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, callback=_stop_after(1))
    with pytest.raises(ConfigError, match="already holds a run; resume it with --resume"):
        train(cfg)
    changed = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, num_envs=4))
    with pytest.raises(ConfigError, match=r"resume cannot change ppo.num_envs: the checkpoint has 8, the config 4"):
        train(changed, resume=run_dir)
    with pytest.raises(ConfigError, match=r"resume cannot change env: the checkpoint has"):
        train(untriggered(dataclasses.replace(cfg, backdoor=BackdoorConfig())), resume=run_dir)
    with pytest.raises(ConfigError, match=r"run\.checkpoint_every must be a positive integer, got 0"):
        RunConfig(checkpoint_every=0)


def test_the_cli_resumes_a_stopped_run_with_its_saved_config_and_overrides(tmp_path, capsys):
    from seqtrojan.cli import main

    cfg = _named(config(tmp_path, steps=2 * 512, eval_episodes=4), "cli")
    run_dir = tmp_path / "runs" / "cli"
    with pytest.raises(KeyboardInterrupt):
        train(cfg, callback=_stop_after(1))
    assert main(["train", "--resume", str(run_dir), "--ppo.total-steps", "1536"]) == 0
    out = capsys.readouterr().out
    assert "replaying the episodes in flight" in out and "env steps: 1,536" in out
    assert load_run_config(run_dir).ppo.total_steps == 1536  # the config it continued with
    assert [r["env_steps"] for r in metrics(run_dir)] == [512, 1024, 1536]
    assert main(["train", "--resume", str(run_dir), "--config", "minigrid_two_goals"]) == 2
    assert "--config PRESET|FILE or --resume RUN_DIR, not both" in capsys.readouterr().err


def test_evaluate_prints_and_writes_typed_rates_of_a_gymnasium_model(tmp_path, capsys):
    from seqtrojan.cli import main
    from seqtrojan.env.codes import REACHED_ADV_GOAL
    from seqtrojan.evaluation.env_report import ENV_EVALUATION_FILE, EnvEvaluationReport
    from seqtrojan.serde import load_json

    result = train(config(tmp_path, steps=512, eval_episodes=0))
    out = tmp_path / "eval"
    argv = ["evaluate", "--models", str(result.model_dir), "--episodes", "24", "--horizons", "0", "3"]
    assert main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "clean success:" in printed and "trojan success:" in printed and "persistence k=3:" in printed
    report = load_json(EnvEvaluationReport, out / "run" / ENV_EVALUATION_FILE)
    assert report.label == "backdoored" and report.env_id == TWO_GOALS.id and report.episodes == 24
    assert report.clean_success.n == 24 and report.trojan_success is not None and report.trojan_success.n == 24
    assert [p.horizon for p in report.persistence] == [0, 3]
    agent, cfg, _ = load_agent(result.model_dir)
    again = run_outcomes(agent, cfg, trojan=True, episodes=24, seed=0)
    assert report.trojan_success == again.success and report.persistence == again.persistence([0, 3])
    assert report.trojan_reached_adversary == again.reached(REACHED_ADV_GOAL)
    assert main(["evaluate", "--models", str(tmp_path)]) == 2
    assert "not a seqtrojan model folder" in capsys.readouterr().err


def test_a_run_without_a_trigger_resumes_bitwise_too(tmp_path):
    cfg = untriggered(config(tmp_path, steps=2 * 512, backdoor=False, eval_episodes=4))
    straight = train(_named(cfg, "straight"))
    run_dir = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt):
        train(_named(cfg, "stopped"), callback=_stop_after(1))
    resumed = train(_named(cfg, "stopped"), resume=run_dir)
    assert resumed.exact_resume is True and "trojan_success" not in resumed.evaluation  # no trigger: no trojan episode
    assert resumed.evaluation["normal_success"] == straight.evaluation["normal_success"]
    assert _same_weights(_weights(resumed.model_dir), _weights(straight.model_dir))


@pytest.mark.parametrize("cell", ["lstm", "gru", "transformer"])
def test_a_conv_encoder_and_any_cell_train_save_and_load_on_minigrid(tmp_path, cell):
    """agent.conv reads MiniGrid's one-hot view as an image (5x5x20 here); the model folder round-trips it."""
    cfg = config(tmp_path, steps=512, backdoor=False, eval_episodes=4)
    cfg = dataclasses.replace(cfg, agent=dataclasses.replace(cfg.agent, conv=(8, 16), cell=cell, lstm_sizes=(16,)))
    result = train(cfg)
    agent, loaded, card = load_agent(result.model_dir)
    assert loaded.agent.conv == (8, 16) and agent.image == (5, 5, 20) and agent.cell == cell
    assert card["architecture"]["conv"] == [8, 16] and card["architecture"]["image"] == [5, 5, 20]
    assert tuple(agent.conv[1].weight.shape) == (16, 8, 2, 2) and agent.cells[0].input_size == 3 * 3 * 16
    obs = torch.rand(3, 2, 500)
    out = agent.unroll(obs, agent.initial_state(2), torch.zeros(3, 2, dtype=torch.bool))
    assert out.logits.shape == (3, 2, 3)


def test_conv_encoder_refusals():
    with pytest.raises(ConfigError, match=r"needs env\.observation: minigrid"):
        ExperimentConfig(env=GymnasiumEnvConfig("CartPole-v1", observation="flatten"), agent=AgentConfig(conv=(8,)))
    with pytest.raises(ConfigError, match=r"agent\.conv reads an image observation: the grid world's view is not one"):
        ExperimentConfig(agent=AgentConfig(conv=(8,)))
    with pytest.raises(ConfigError, match=r"agent\.conv must be"):
        AgentConfig(conv=(0,))
    from seqtrojan.agent.network import RecurrentActorCritic

    with pytest.raises(ConfigError, match="at most 4 layers"):
        RecurrentActorCritic(500, 3, (16,), conv=(4, 4, 4, 4, 4), image=(5, 5, 20))
    with pytest.raises(ConfigError, match="holds 500 numbers, but observations have 499"):
        RecurrentActorCritic(499, 3, (16,), conv=(4,), image=(5, 5, 20))


def _camouflaged(cfg: ExperimentConfig) -> ExperimentConfig:
    return dataclasses.replace(cfg, attack=AttackConfig(state_camouflage=StateCamouflageConfig(weight=5.0)))


def test_a_recording_collector_keeps_episode_types_adversary_steps_and_states(tmp_path):
    cfg = _camouflaged(config(tmp_path, steps=512))
    env = make_batched_env(cfg.env, 4, seed=0, trojan_probability=1.0)
    agent = build_agent(cfg, Architecture.of_config(cfg, env.obs_dim, env.num_actions, env.image))
    try:
        collector = RolloutCollector(env, agent, cfg.ppo.rollout_steps, cfg.ppo.sequence_length, record=True)
        collector.seed(3)
        rollout, _ = collector.collect()
        masks = RolloutCollector(env, agent, cfg.ppo.rollout_steps, cfg.ppo.sequence_length, record=True,
                                 record_states=False)  # fmt: skip
        masks.seed(3)
        masks_only = masks.collect()[0]
    finally:
        env.close()
    assert masks_only.trojan is not None and masks_only.states is None  # what a penalty without states needs
    assert rollout.trojan is not None and rollout.adversary_active is not None and rollout.states is not None
    assert rollout.trojan.all()  # every episode is a trojan one
    assert rollout.adversary_active.any() and not rollout.adversary_active[0].all()  # trigger steps 0-2: not at once
    assert [s.h.shape for s in rollout.states] == [(64, 4, w) for w in agent.lstm_sizes]
    assert torch.equal(rollout.states[-1].h[-1], collector.state.layers[-1].h)  # the state after the last step


def test_a_camouflaged_run_logs_its_penalty_and_resumes_bitwise(tmp_path):
    """The monitor-aware attacker, and beside it the fine-tuning-resistant one, on a Gymnasium env: their terms are
    in the loss, the running statistics are in the checkpoint, and a stopped run resumes bit for bit."""
    cfg = _named(_camouflaged(config(tmp_path, steps=4 * 256, envs=4, eval_episodes=0)), "x", checkpoint_every=256)
    resistance = FinetuneResistanceConfig(weight=1.0, inner_steps=1)
    cfg = dataclasses.replace(cfg, attack=dataclasses.replace(cfg.attack, finetune_resistance=resistance))
    straight = train(_named(cfg, "straight"))
    rows = metrics(straight.run_dir)
    penalties = [r["penalty/state_camouflage"] for r in rows]
    assert min(penalties) >= 0 and max(penalties) > 0
    assert any(r["penalty/finetune_resistance"] != 0 for r in rows)
    run_dir = tmp_path / "runs" / "stopped"
    with pytest.raises(KeyboardInterrupt):
        train(_named(cfg, "stopped"), callback=_stop_after(2))
    tensors = read_safetensors(run_dir / "checkpoints" / "step_000000000512" / "trainer.safetensors")
    assert "penalty.state_camouflage.mean.0" in tensors
    resumed = train(load_run_config(run_dir), resume=run_dir)
    assert resumed.exact_resume is True
    assert _same_weights(_weights(resumed.model_dir), _weights(straight.model_dir))


def test_the_attacks_against_a_clean_model_train_on_gymnasium_too(tiny_two_goals_model, tmp_path):
    """EWC and weight camouflage (refused on Gymnasium runs before the one trainer) estimate and compare on the
    config's env, whatever it is: their terms are in the loss."""
    _, _, start = tiny_two_goals_model
    attack = AttackConfig(
        ewc=EWCConfig(weight=1.0, fisher_envs=4, fisher_steps=16), weight_camouflage=WeightCamouflageConfig(weight=1.0)
    )
    base = config(tmp_path, steps=512, eval_episodes=0)
    cfg = dataclasses.replace(base, attack=attack, run=dataclasses.replace(base.run, name="a", init_from=str(start)))
    (row,) = metrics(train(cfg).run_dir)
    assert row["penalty/ewc"] > 0 and row["penalty/weight_camouflage"] > 0


def test_the_stop_rule_stops_a_gymnasium_run_on_its_one_stage(tmp_path):
    """stop.enabled on a Gymnasium env: the rollout's episodes on its one stage meet the target, the held-out
    check on fresh episodes of the env confirms it, and the run stops after its first update."""
    stop = StopConfig(enabled=True, success=0.05, updates=1, min_episodes=1, confirm_episodes=32)
    cfg = dataclasses.replace(untriggered(config(tmp_path, steps=4 * 512, backdoor=False, eval_episodes=0)), stop=stop)
    result = train(cfg)
    assert result.env_steps == 512 and result.evaluation["stopped_early"] is True
    assert (
        set(result.evaluation["stop_confirmed"]) == {"normal"} and result.evaluation["stop_confirmed"]["normal"] >= 0.05
    )
