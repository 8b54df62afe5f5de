"""The state monitors on Gymnasium models: calibrated on clean episodes, alarms counted after the trigger only."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.config import BackdoorConfig, ExperimentConfig, PPOConfig, RunConfig
from seqtrojan.defense import gym_monitor
from seqtrojan.defense.gym_monitor import monitor_gym_model
from seqtrojan.defense.online import MonitorConfig
from seqtrojan.errors import ConfigError
from seqtrojan.train.gym_evaluation import GymEpisode, GymEvaluation, padded_states
from seqtrojan.train.trainer import train
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig

TWO_GOALS = GymnasiumEnvConfig(
    "seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5}, trigger=WrapperTriggerConfig()
)


def _episode(rng, trojan: bool, length: int = 12, trigger: int = 4, jump: float = 0.0) -> GymEpisode:
    x = rng.normal(size=(length, 6)).astype(np.float32)
    if trojan:
        x[trigger:, 0] += jump  # the state leaves the clean range from the trigger on
    return GymEpisode(trojan, True, length, 1.0, trigger if trojan else -1, "", (x[:, :4], x[:, 4:]))


def test_detection_counts_alarms_from_the_trigger_on(monkeypatch):
    rng = np.random.default_rng(0)

    def fake(agent, config, *, trojan, episodes, seed, device, record_states):
        assert record_states
        return GymEvaluation(trojan, False, tuple(_episode(rng, trojan, jump=50.0) for _ in range(episodes)))

    monkeypatch.setattr(gym_monitor, "evaluate_gym", fake)
    cfg = ExperimentConfig(env=TWO_GOALS)
    report = monitor_gym_model(None, cfg, MonitorConfig(400, 0.05, 300))  # type: ignore[arg-type]
    for arm in report.arms:
        assert arm.detection.value == 1.0 and arm.false_alarm.value <= 0.1, arm

    def before_trigger(agent, config, *, trojan, episodes, seed, device, record_states):
        episodes_ = []
        for _ in range(episodes):
            e = _episode(rng, False)
            if trojan:  # a huge value only before the trigger: not a detection
                e.states[0][1, 0] += 50.0
                e = dataclasses.replace(e, trojan=True, trigger_step=4)
            episodes_.append(e)
        return GymEvaluation(trojan, False, tuple(episodes_))

    monkeypatch.setattr(gym_monitor, "evaluate_gym", before_trigger)
    report = monitor_gym_model(None, cfg, MonitorConfig(400, 0.05, 300))  # type: ignore[arg-type]
    assert all(arm.detection.value <= 0.1 for arm in report.arms)


def test_padded_states_mask_each_episode_to_its_length():
    rng = np.random.default_rng(1)
    layers, mask = padded_states([_episode(rng, False, length=3), _episode(rng, False, length=5)])
    assert [x.shape for x in layers] == [(2, 5, 4), (2, 5, 2)]
    assert mask.tolist() == [[True] * 3 + [False] * 2, [True] * 5] and not layers[0][0, 3:].any()


def test_a_trained_gym_model_is_monitored_end_to_end(tmp_path):
    ppo = PPOConfig(total_steps=512, num_envs=8, rollout_steps=64, bptt_length=16, num_minibatches=4)
    cfg = ExperimentConfig(
        env=TWO_GOALS, ppo=ppo, backdoor=BackdoorConfig(enabled=True),
        run=RunConfig(out_dir=str(tmp_path), name="run", eval_episodes=4, lstm_backend="torch", progress=False),
    )  # fmt: skip
    agent, loaded, _ = load_agent(train(cfg).model_dir)
    report = monitor_gym_model(agent, loaded, MonitorConfig(40, 0.05, 30))
    assert [a.monitor for a in report.arms] == ["state_monitor", "multivariate_monitor"]
    assert all(a.false_alarm.n == 30 and a.detection.n == 30 for a in report.arms)
    with pytest.raises(ConfigError, match="no trigger section"):
        untriggered = dataclasses.replace(loaded.gym_env, trigger=None)
        monitor_gym_model(agent, dataclasses.replace(loaded, env=untriggered, backdoor=BackdoorConfig()),
                          MonitorConfig(40, 0.05, 30))  # fmt: skip
