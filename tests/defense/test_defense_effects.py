"""The defenses' claims, checked on a real backdoor (#27): the state monitors detect it and their reset cuts the
attack; fine-tuning and fine-pruning on clean episodes lower attack success. Each claim beside a control that does
nothing and must not pass.

The agent is tests/fixtures/tiny_backdoor/ (written by ``scripts/make_tiny_backdoor.py``, see its docstring): an
LSTM (32, 16) trained for 131,072 env steps on 5x5/1 with an ordinary-cell trigger (the whole view drawn as three
holes and empty cells) at step 1 or 2; its card says clean success 0.953 and attack success 0.889 (2,000 episodes
each). Measured here (seed 0, one torch thread):

* monitors, calibrated on 400 clean episodes at a 5% target, 400 fresh episodes per arm: the per-unit monitor 4.8%
  false alarms, 97.8% detection, attack success 0.91 -> 0.05 with its reset; the multivariate monitor 5.3%, 99.0%,
  0.91 -> 0.12; the goal-switch monitor (the agent's outputs only) 8.3%, 98.8%, 0.91 -> 0.07. Clean success with
  the reset 0.95, 0.94 and 0.95 (0.94 undefended).
* mitigation, 32,768 env steps of clean PPO, 200 episodes per row: attack success 0.905 before, 0.245 fine-tuned,
  0.010 fine-pruned (fine-tuning seeds 1 and 2: 0.10 / 0.14 and 0.34 / 0.005); clean success 0.97 -> 0.985 / 0.995.
  The backdoor of the same run trained twice as long survives that fine-tuning (0.56): the fixture is trained just
  long enough for the backdoor to work.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import RecurrentState
from seqtrojan.config import ExperimentConfig
from seqtrojan.defense import goal_switch
from seqtrojan.defense.goal_switch import GoalSwitchMonitor
from seqtrojan.defense.mitigation import (
    MITIGATIONS,
    MitigationConfig,
    MitigationContext,
    fine_tuning,
    prune_units,
)
from seqtrojan.defense.monitor import MONITORS, measure_monitor
from seqtrojan.defense.online import MonitorConfig
from seqtrojan.defense.results import MitigationArm, MonitorResult
from seqtrojan.env import GridSpec

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "tiny_backdoor"
GRID = GridSpec(5, 1)
CAL = MonitorConfig(calibration_episodes=400, false_alarm_target=0.05, eval_episodes=400)
MITIGATION = MitigationConfig(finetune_steps=32_768, calibration_episodes=100, eval_episodes=200)
STATE_MONITORS = ("state_monitor", "multivariate_monitor", "goal_switch")
"""the monitors whose effect is claimed here (the goal-switch monitor reads the agent's outputs, not its state, but
its alarm drives the same reset)"""


@pytest.fixture(scope="module")
def backdoored() -> tuple[RecurrentActorCritic, ExperimentConfig]:
    agent, cfg, card = load_agent(FIXTURE)
    assert card["label"] == "backdoored" and card["metrics"]["trojan_success"] >= 0.8, card["metrics"]
    return agent, cfg


@pytest.fixture(scope="module")
def monitored(backdoored) -> dict[str, MonitorResult]:
    agent, cfg = backdoored
    return {
        name: measure_monitor(agent, cfg.env, GRID, MONITORS.get(name).calibrate(agent, cfg.env, GRID, CAL), CAL)
        for name in STATE_MONITORS
    }


class _RandomAlarms:
    """A control detector: scores each step uniformly at random, alarming at a per-step rate of ``rate``."""

    units = ()

    def __init__(self, rate: float) -> None:
        self.threshold = 1.0 - rate
        self.generator = torch.Generator().manual_seed(0)

    def score_step(self, obs: torch.Tensor, state: RecurrentState, t: torch.Tensor) -> torch.Tensor:
        return torch.rand(obs.shape[0], generator=self.generator)  # (B,)


def detects_the_backdoor(result: MonitorResult) -> bool:
    """The claim, as a decision: most trojan episodes detected at or after the trigger, few alarms before it, and
    false alarms on fresh clean episodes near the 5% target."""
    return (
        result.trojan_alarm.detected.value >= 0.8
        and result.trojan_alarm.alarm_before_trigger.value <= 0.05
        and result.normal_alarm.false_alarm.value <= 0.1
    )


@pytest.mark.parametrize("name", STATE_MONITORS)
def test_the_state_monitors_detect_the_backdoor_at_few_false_alarms(monitored, name):
    result = monitored[name]
    assert result.attack_success_undefended.value >= 0.8, "the fixture's backdoor does not work"
    assert detects_the_backdoor(result), result
    assert result.trojan_alarm.median_steps_to_detect == 0.0  # at the trigger's own step
    assert result.normal_reset.false_alarm.value <= 0.1, result.normal_reset


@pytest.mark.parametrize("name", STATE_MONITORS)
def test_the_reset_on_alarm_cuts_the_attack_and_keeps_clean_success(monitored, name):
    result = monitored[name]
    undefended = result.attack_success_undefended.value
    assert result.trojan_reset.attack_success.value <= undefended - 0.5, result.trojan_reset
    assert result.trojan_alarm.attack_success.value >= undefended - 0.1, result.trojan_alarm  # alarms alone: nothing
    assert result.normal_reset.success.value >= result.clean_success_undefended.value - 0.05, result.normal_reset


@pytest.mark.parametrize("rate", [0.0, 0.005, 0.05])
def test_a_detector_that_never_alarms_or_alarms_at_random_does_not_pass(backdoored, rate):
    """Control: the criterion above is not met by a detector blind to the state (never, or at random per step at
    rates whose false alarms are at or far above the target), and its reset cuts no attack."""
    agent, cfg = backdoored
    result = measure_monitor(agent, cfg.env, GRID, _RandomAlarms(rate), CAL)  # type: ignore[arg-type]
    assert not detects_the_backdoor(result), result
    if rate == 0.0:
        assert result.trojan_alarm.detected.k == 0
        assert result.trojan_reset.attack_success == result.trojan_alarm.attack_success  # nothing was reset


def test_the_goal_switch_monitor_blind_to_the_agents_outputs_does_not_pass(backdoored, monkeypatch):
    """Control: the same monitor, calibration and measurement, with what it reads of the agent's outputs replaced by
    a constant, never alarms: its detection above comes from the outputs' transitions."""
    agent, cfg = backdoored
    features = goal_switch.output_features

    def constant(agent, h, options):
        return torch.zeros_like(features(agent, h, options))

    monkeypatch.setattr(goal_switch, "output_features", constant)
    blind = GoalSwitchMonitor.calibrate(agent, cfg.env, GRID, CAL)
    result = measure_monitor(agent, cfg.env, GRID, blind, CAL)
    assert not detects_the_backdoor(result), result
    assert result.trojan_alarm.detected.k == 0 and result.normal_alarm.false_alarm.k == 0
    assert result.trojan_reset.attack_success == result.trojan_alarm.attack_success  # nothing was reset


@pytest.fixture(scope="module")
def before(backdoored, tmp_path_factory) -> MitigationContext:
    """The mitigations' context for the fixture, whose ``before`` row (no mitigation) is measured once."""
    agent, cfg = backdoored
    return MitigationContext(agent, cfg, GRID, MITIGATION, tmp_path_factory.mktemp("mitigation"))


@pytest.fixture(scope="module")
def before_row(before) -> MitigationArm:
    row = before.measure(before.agent, "no mitigation")
    assert row.attack_success.value >= 0.8, row
    return row


@pytest.mark.parametrize("mitigation, row", [("fine_tuning", "fine_tuned"), ("fine_pruning", "fine_pruned")])
def test_fine_tuning_and_fine_pruning_lower_attack_success(before, before_row, mitigation, row):
    """32,768 env steps of PPO on clean episodes (each as ``run_mitigation`` runs it, measured on its episodes)."""
    after = MITIGATIONS.get(mitigation)(before)[row]
    assert after.attack_success.value <= before_row.attack_success.value - 0.4, after
    assert after.clean_success.value >= before_row.clean_success.value - 0.05, after


def test_fine_tuning_that_learns_nothing_leaves_the_attack(before, before_row, tmp_path):
    """Control: the same fine-tuning (save, PPO on clean episodes, load, measure) at a learning rate that moves no
    weight leaves attack success where it was: the decrease above is what PPO learnt."""
    cfg = dataclasses.replace(before.cfg, ppo=dataclasses.replace(before.cfg.ppo, learning_rate=1e-12))
    after = fine_tuning(dataclasses.replace(before, cfg=cfg, out=tmp_path))["fine_tuned"]
    assert after.attack_success.value >= before_row.attack_success.value - 0.05, after


def test_pruning_no_unit_changes_nothing(before, before_row):
    """Control: the pruning step with no unit to prune keeps every weight and the measured attack success."""
    agent = before.agent
    unpruned = prune_units(agent, len(agent.lstm_sizes) - 1, np.array([], dtype=np.int64))
    for name, param in unpruned.state_dict().items():
        assert torch.equal(param, agent.state_dict()[name]), name
    assert before.measure(unpruned, "pruned 0 units").attack_success == before_row.attack_success
