"""The online monitor and the mitigations on tiny untrained agents (mechanics, not effect sizes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.analysis.traces import record_traces
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.defense.mitigation import MitigationConfig, least_active_units, prune_units, run_mitigation
from seqtrojan.defense.monitor import (
    MonitorConfig,
    MonitoredPolicy,
    StateMonitor,
    conformal_threshold,
    measure_monitor,
)
from seqtrojan.env import EnvConfig, GridSpec, TrojanGridCore
from seqtrojan.errors import ConfigError

CFG = ExperimentConfig(env=EnvConfig(size=7, holes=3), agent=AgentConfig(lstm_sizes=(16, 8)))
GRID = GridSpec(7, 3)

SMALL = MonitorConfig(calibration_episodes=100, false_alarm_target=0.05)  # 50 held out: enough for 5%


@pytest.fixture(scope="module")
def agent():
    torch.manual_seed(0)
    return build_agent(CFG).eval()


@pytest.fixture(scope="module")
def monitor(agent):
    return StateMonitor.calibrate(agent, CFG.env, GRID, SMALL)


def test_calibration_sets_a_threshold_from_clean_episodes(monitor):
    assert np.isfinite(monitor.threshold) and monitor.threshold > 0
    assert [m.numel() for m in monitor.mean] == [32, 16]  # h and c of each layer


def test_far_states_score_above_the_threshold_and_are_reset(agent, monitor):
    near = RecurrentState(tuple(LSTMState(m[: m.numel() // 2][None].clone(), m[m.numel() // 2 :][None].clone())
                                for m in monitor.mean))  # fmt: skip
    far = RecurrentState(tuple(LSTMState(s.h + 50.0, s.c) for s in near.layers))
    assert float(monitor.score(near)[0]) < 1e-4 and float(monitor.score(far)[0]) > monitor.threshold
    core = TrojanGridCore(CFG.env, 2, seed=0)
    policy = MonitoredPolicy(agent, monitor, core, reset=True)
    policy.reset(2)
    monitor_strict = StateMonitor([m.numpy() for m in monitor.mean], [s.numpy() for s in monitor.std], threshold=-1.0)
    policy.monitor = monitor_strict  # every state alarms: every state is reset
    policy(core.observe())
    assert all(float(s.h.abs().sum()) == 0.0 for s in policy.state.layers)
    assert policy.first_alarm.tolist() == [0, 0] and policy.alarms.tolist() == [1, 1]


def test_measurement_reports_every_rate(agent, monitor):
    out = measure_monitor(agent, CFG.env, GRID, monitor, dataclasses.replace(SMALL, eval_episodes=64))
    for key in ("normal_alarm", "normal_reset", "trojan_alarm", "trojan_reset", "normal_undefended",
                "trojan_undefended"):  # fmt: skip
        assert key in out
    detected = out["trojan_alarm"]["detected"]
    assert 0 <= detected["rate"] <= 1 and detected["ci95"][0] <= detected["rate"] <= detected["ci95"][1]
    with pytest.raises(ConfigError, match="false_alarm_target"):
        MonitorConfig(false_alarm_target=1.5)
    with pytest.raises(ConfigError, match=r"too few for false_alarm_target=0\.01"):
        MonitorConfig(calibration_episodes=100, false_alarm_target=0.01)


def test_pruned_units_stay_silent(agent):
    units = least_active_units(agent, CFG, GRID, episodes=40, fraction=0.25, seed=0)
    assert len(units) == 2
    pruned = prune_units(agent, 1, units)
    trace = record_traces(pruned, CFG.env, [GRID], episodes=20, trojan=True, trigger_step=2)
    assert np.abs(trace.h[1][..., units]).max() == 0 and np.abs(trace.c[1][..., units]).max() == 0
    assert np.abs(trace.h[1]).max() > 0  # the others still work
    assert not torch.equal(agent.cells[1].weight_hh, pruned.cells[1].weight_hh)


def test_mitigation_measures_before_and_after(tmp_path, agent):
    result = run_mitigation(
        agent, CFG, GRID, MitigationConfig(finetune_steps=2048, calibration_episodes=32, eval_episodes=32), tmp_path
    )
    for key in ("before", "pruned", "fine_pruned", "fine_tuned"):
        assert set(result[key]) == {"clean_success", "attack_success"}


def test_alarms_after_an_episode_ended_do_not_count(agent, monitor):
    strict = StateMonitor([m.numpy() for m in monitor.mean], [s.numpy() for s in monitor.std], threshold=1e9)
    out = measure_monitor(agent, CFG.env, GRID, strict, dataclasses.replace(SMALL, eval_episodes=32))
    assert out["normal_alarm"]["false_alarm"]["rate"] == 0.0  # nothing ever crosses an infinite threshold
    calibrated = measure_monitor(agent, CFG.env, GRID, monitor, dataclasses.replace(SMALL, eval_episodes=200))
    assert calibrated["normal_alarm"]["false_alarm"]["rate"] < 0.15  # calibrated for 5%; small-sample slack


def test_conformal_threshold_is_the_finite_sample_quantile():
    peaks = np.arange(1.0, 100.0)  # 99 held-out peaks 1..99
    assert conformal_threshold(peaks, 0.01) == 99.0  # ceil(100 * 0.99) = 99th smallest
    assert conformal_threshold(peaks, 0.1) == 90.0  # ceil(100 * 0.9) = 90th
    with pytest.raises(ConfigError, match="98 held-out"):
        conformal_threshold(peaks[:-1], 0.01)
    rng = np.random.default_rng(0)  # the guarantee: over calibrations, P(fresh peak > threshold) <= target
    rates = [(rng.normal(size=1000) > conformal_threshold(rng.normal(size=199), 0.05)).mean() for _ in range(300)]
    assert np.mean(rates) <= 0.05 + 0.005
