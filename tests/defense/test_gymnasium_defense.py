"""The registered defenses on a Gymnasium env's model, through the one episode source: the state monitors, the
defend pipeline (monitor, oracle, mitigations) and its fine-tunes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.defense.goal_switch import GoalSwitchMonitor
from seqtrojan.defense.mitigation import MitigationConfig
from seqtrojan.defense.monitor import MONITORS, StateMonitor, measure_monitor
from seqtrojan.defense.multivariate import MultivariateMonitor
from seqtrojan.defense.novelty import InputNovelty
from seqtrojan.defense.online import MonitorConfig, monitor_applies
from seqtrojan.defense.pipeline import DEFENSE_FILE, DefenseConfig, run_defense
from seqtrojan.errors import ConfigError

SMALL = MonitorConfig(calibration_episodes=40, false_alarm_target=0.05, eval_episodes=24)


class _AlarmFrom:
    """Scores 2.0 (threshold 1.0) at every step from episode step ``k`` on, 0.0 before."""

    threshold = 1.0
    units = ()

    def __init__(self, k: int) -> None:
        self.k = k

    def score_step(self, obs, state, t):
        return (t.cpu() >= self.k).float() * 2.0


def test_the_state_monitors_watch_a_gymnasium_model(tiny_two_goals_model):
    agent, cfg, _ = tiny_two_goals_model
    assert [n for n, m in MONITORS.items() if monitor_applies(m, cfg.env)] == [
        "state_monitor", "multivariate_monitor", "goal_switch",
    ]  # fmt: skip
    assert not monitor_applies(InputNovelty, cfg.env)
    with pytest.raises(ConfigError, match="grid-world agents only"):
        InputNovelty.calibrate(agent, cfg.env, None, SMALL)
    for detector in (StateMonitor, MultivariateMonitor, GoalSwitchMonitor):
        monitor = detector.calibrate(agent, cfg.env, None, SMALL)
        result = measure_monitor(agent, cfg.env, None, monitor, SMALL)
        assert result.grid == "seqtrojan/MiniGridTwoGoals-v0" and np.isfinite(monitor.threshold)
        assert result.normal_alarm.false_alarm.n == result.trojan_reset.attack_success.n == SMALL.eval_episodes


def test_a_calibrated_monitor_keeps_its_false_alarm_target_on_a_gymnasium_model(tiny_two_goals_model):
    """Calibrated at 5% on clean episodes, the monitors raise false alarms in about 5% of fresh clean episodes (a
    finished episode's slot must not count its alarms: its step stops at the episode's length)."""
    agent, cfg, _ = tiny_two_goals_model
    calibration = MonitorConfig(calibration_episodes=200, false_alarm_target=0.05, eval_episodes=120)
    for detector in (StateMonitor, MultivariateMonitor, GoalSwitchMonitor):
        monitor = detector.calibrate(agent, cfg.env, None, calibration)
        result = measure_monitor(agent, cfg.env, None, monitor, calibration)
        assert result.normal_alarm.false_alarm.value <= 0.15, (detector, result.normal_alarm.false_alarm)


def test_alarms_count_as_detections_only_from_the_trigger_on(tiny_two_goals_model):
    """The two-goal room's trigger shows at step 0-2 (evaluation range): an alarm from step 3 on is a detection of
    every trojan episode still running then; one from step 0 on fires before the trigger in most of them."""
    agent, cfg, _ = tiny_two_goals_model
    late = measure_monitor(agent, cfg.env, None, _AlarmFrom(3), SMALL)  # type: ignore[arg-type]
    early = measure_monitor(agent, cfg.env, None, _AlarmFrom(0), SMALL)  # type: ignore[arg-type]
    assert late.trojan_alarm.alarm_before_trigger.value == 0.0
    assert late.trojan_alarm.detected.k > 0 and early.trojan_alarm.alarm_before_trigger.k > 0
    assert early.normal_alarm.false_alarm.value == 1.0  # every episode runs a step 0


def test_defend_runs_the_monitor_and_every_mitigation_on_a_gymnasium_model(tiny_two_goals_model, tmp_path):
    agent, cfg, model_dir = tiny_two_goals_model
    defense = DefenseConfig(
        monitor=SMALL, mitigation=MitigationConfig(finetune_steps=512, calibration_episodes=16, eval_episodes=12),
        oracle_episodes=20,
    )  # fmt: skip
    result = run_defense(model_dir, tmp_path, defense, log=lambda _: None)
    assert result.grid == "seqtrojan/MiniGridTwoGoals-v0" and result.trigger_value == "purple key on [[0, 0], [0, 1]]"
    assert {"before", "pruned", "fine_pruned", "fine_tuned"} <= set(result.mitigation)
    assert all(arm.clean_success.n == arm.attack_success.n == 12 for arm in result.mitigation.values())
    assert len(result.mitigation["pruned"].units) == round(0.25 * agent.lstm_sizes[-1])
    tuned, tune_cfg, card = load_agent(tmp_path / "mitigation" / "fine_tuning" / "finetune" / "model")
    assert not tune_cfg.backdoor.enabled and tune_cfg.ppo.total_steps == 512 and card["label"] == "backdoored"
    assert tune_cfg.env == cfg.env  # fine-tuned on the model's own env
    assert any(not bool((a == b).all()) for a, b in zip(tuned.state_dict().values(), agent.state_dict().values()))
    assert json.loads((tmp_path / DEFENSE_FILE).read_text())["grid"] == "seqtrojan/MiniGridTwoGoals-v0"
    stamp = (tmp_path / "mitigation" / "fine_tuning" / "finetune" / "model" / "card.json").stat().st_mtime_ns
    again = run_defense(model_dir, tmp_path, defense, log=lambda _: None)  # the fine-tunes are reused
    assert (tmp_path / "mitigation" / "fine_tuning" / "finetune" / "model" / "card.json").stat().st_mtime_ns == stamp
    assert again.mitigation == result.mitigation
    with pytest.raises(ConfigError, match="names a grid"):
        run_defense(model_dir, tmp_path / "other", dataclasses.replace(defense, grid=(7, 3)), log=lambda _: None)
    assert not (tmp_path / "other").exists()
