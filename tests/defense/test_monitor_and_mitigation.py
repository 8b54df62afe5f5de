"""The online monitor and the mitigations on tiny untrained agents (mechanics, not effect sizes)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from seqtrojan.agent.card import read_card
from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.analysis.traces import record_traces
from seqtrojan.cell_types import cell_names
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.defense.mitigation import MitigationConfig, least_active, least_active_units, prune_units, run_mitigation
from seqtrojan.defense.monitor import (
    MonitorConfig,
    MonitoredPolicy,
    StateMonitor,
    conformal_threshold,
    measure_monitor,
)
from seqtrojan.env import EnvConfig, GridSpec, TrojanGridCore
from seqtrojan.errors import ConfigError
from seqtrojan.stats import Rate, wilson_interval
from seqtrojan.world import episodes as episodes_module

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


def test_calibration_sets_a_threshold_from_clean_episodes(agent, monitor):
    assert [m.numel() for m in monitor.mean] == [32, 16]  # h and c of each layer
    trace = record_traces(agent, CFG.env, [GRID], episodes=100, trojan=False, trigger_step=None, seed=SMALL.seed)
    for layer in range(2):  # statistics from the first 50 episodes' running steps
        rows = np.concatenate([trace.h[layer][:50], trace.c[layer][:50]], -1)[trace.mask[:50]]
        np.testing.assert_allclose(monitor.mean[layer].numpy(), rows.mean(0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(monitor.std[layer].numpy(), rows.std(0) + 1e-3, rtol=1e-5)
    peaks = []  # the other 50 episodes' peak scores, by the monitor's own (torch) score of each step's state
    for e in range(50, 100):
        run = trace.mask[e]
        layers = tuple(
            LSTMState(torch.from_numpy(h[e][run]), torch.from_numpy(c[e][run])) for h, c in zip(trace.h, trace.c)
        )
        peaks.append(float(monitor.score(RecurrentState(layers)).max()))
    assert monitor.threshold == pytest.approx(sorted(peaks)[48], rel=1e-5)  # ceil(51 * 0.95) = 49th of 50


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
    rates = {}  # every rate of the result, by dotted name
    for f in dataclasses.fields(out):
        value = getattr(out, f.name)
        if isinstance(value, Rate):
            rates[f.name] = value
        elif dataclasses.is_dataclass(value):
            rates |= {f"{f.name}.{g.name}": getattr(value, g.name) for g in dataclasses.fields(value)
                      if isinstance(getattr(value, g.name), Rate)}  # fmt: skip
    assert len(rates) == 2 * 2 + 2 * 4 + 2  # normal: success, false alarm; trojan: 4 each; 2 undefended
    for name, v in rates.items():  # each a count of the 64 episodes, with that count's Wilson interval
        assert v.n == 64 and v.value == v.k / 64 and v.interval == wilson_interval(v.k, 64), name
    assert (out.grid, out.episodes, out.threshold) == (GRID.label, 64, monitor.threshold)
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
    assert (np.delete(trace.h[1], units, axis=-1)[trace.mask] != 0).all()  # the others still work at every step
    assert not torch.equal(agent.cells[1].weight_hh, pruned.cells[1].weight_hh)


def test_least_active_picks_exactly_the_units_made_least_active():
    """Activations built so that three units are the least active by mean |h| over the running steps, whatever
    their sign, and the loudest at the steps that did not run; a unit always at -5 is the most active."""
    rng = np.random.default_rng(0)
    e, t, u = 6, 10, 12
    h = rng.uniform(0.5, 1.0, size=(e, t, u)) * rng.choice([-1.0, 1.0], size=(e, t, u))  # (E, T, units)
    quiet = [9, 2, 5]  # mean |h| 0.01, 0.02, 0.03: least active first
    for rank, unit in enumerate(quiet):
        h[..., unit] = (rank + 1) * 0.01 * rng.choice([-1.0, 1.0], size=(e, t))
    h[..., 7] = -5.0
    mask = np.ones((e, t), bool)
    mask[:, 6:] = False  # steps 6-9 did not run: there the quiet units are the loudest of all
    h[:, 6:, quiet] = 100.0
    assert least_active(h, mask, 0.25).tolist() == quiet  # 3 of 12, in order
    assert least_active(h, mask, 0.01).tolist() == quiet[:1]  # at least one
    assert 7 not in least_active(h, mask, 11 / 12).tolist()  # all but the most active


def test_least_active_units_finds_the_units_silenced_in_an_agent(agent):
    """On the agent's own clean episodes: two last-layer units pruned beforehand (h = 0 at every step) are exactly
    the quarter that least_active_units picks."""
    silenced = prune_units(agent, 1, np.array([6, 1]))
    assert sorted(least_active_units(silenced, CFG, GRID, episodes=40, fraction=0.25, seed=0).tolist()) == [1, 6]


def test_mitigation_measures_before_and_after(tmp_path, agent):
    mcfg = MitigationConfig(finetune_steps=2048, calibration_episodes=32, eval_episodes=32)
    # the card says backdoored though the config plants nothing (a model itself fine-tuned from a backdoored one):
    # the fine-tuned models inherit the card's label
    result = run_mitigation(agent, CFG, GRID, mcfg, tmp_path, label="backdoored")
    for arm in ("fine_tuning", "fine_pruning"):
        for folder in (tmp_path / arm / "start", tmp_path / arm / "finetune" / "model"):
            assert read_card(folder).label == "backdoored", folder
    # no oracle without goal units
    assert list(result) == ["before", "pruned", "fine_pruned", "fine_tuned", "state_bounds"]
    assert all(arm.clean_success.n == arm.attack_success.n == 32 for arm in result.values())
    assert len(result["pruned"].units) == 2  # a quarter of the last layer's 8 units
    assert result["pruned"].title == "pruned 2 least-active units" and result["before"].units == ()


class _RecordingCore(TrojanGridCore):
    """An env core that remembers which of its episodes have ended (measure_monitor keeps stepping finished envs
    until all have ended) and their lengths. Every core built is appended to ``made``."""

    made: list[_RecordingCore] = []

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        _RecordingCore.made.append(self)

    def reset(self, seed=None):
        self.ended = torch.zeros(self.num_envs, dtype=torch.bool)
        self.lengths = torch.zeros(self.num_envs, dtype=torch.int64)
        return super().reset(seed)

    def step(self, actions, autoreset=True, check=True):
        result = super().step(actions, autoreset, check)
        done = result.done.cpu()
        self.lengths = torch.where(done & ~self.ended, result.length.cpu(), self.lengths)
        self.ended |= done
        return result


class _ScriptedMonitor(StateMonitor):
    """Scores 2.0 (threshold 1.0) every step taken after the env's episode has ended and, with ``in_episode_step``,
    that step of every episode; 0.0 otherwise. Reads the newest _RecordingCore; counts the after-end alarms."""

    def __init__(self, in_episode_step: int | None) -> None:
        super().__init__([np.zeros(32), np.zeros(16)], [np.ones(32), np.ones(16)], threshold=1.0)
        self.in_episode_step = in_episode_step
        self.after_end_alarms = 0

    def score(self, state):
        core = _RecordingCore.made[-1]
        alarm = core.ended.clone()
        self.after_end_alarms += int(alarm.sum())
        if self.in_episode_step is not None:
            alarm |= core.t.cpu() == self.in_episode_step
        return alarm.float() * 2.0


def test_alarms_after_an_episode_ended_do_not_count(agent, monitor, monkeypatch):
    monkeypatch.setattr(episodes_module, "TrojanGridCore", _RecordingCore)  # the one episode source builds it
    cfg = dataclasses.replace(SMALL, eval_episodes=64)
    keys = ("normal_alarm", "normal_reset", "trojan_alarm", "trojan_reset")  # the order measure_monitor runs them

    _RecordingCore.made.clear()
    after_end_only = _ScriptedMonitor(in_episode_step=None)
    out = measure_monitor(agent, CFG.env, GRID, after_end_only, cfg)
    # the four monitored arms, then the two undefended runs (the same episode source builds every env)
    assert len(_RecordingCore.made) == 6 and after_end_only.after_end_alarms > 0  # alarms fired, all after the end
    for key in keys[:2]:
        assert getattr(out, key).false_alarm.value == 0.0, key
    for key in keys[2:]:
        arm = getattr(out, key)
        assert arm.detected.value == 0.0 and arm.alarm_before_trigger.value == 0.0, key
        assert arm.median_steps_to_detect is None, key

    # Control: an alarm at step k of each episode counts exactly where that episode was still running at step k.
    _RecordingCore.made.clear()
    k = 4
    out = measure_monitor(agent, CFG.env, GRID, _ScriptedMonitor(in_episode_step=k), cfg)
    for key, core in zip(keys, _RecordingCore.made[:4], strict=True):
        running = (core.lengths > k).numpy()
        assert 0 < running.sum() < len(running), key  # some episodes ended before step k: the case is not empty
        arm = getattr(out, key)
        if key.startswith("normal"):
            assert arm.false_alarm.value == running.mean(), key
            continue
        trigger = core.on_step.cpu().numpy()
        detected = running & (trigger <= k)
        assert arm.detected.value == detected.mean(), key
        assert arm.alarm_before_trigger.value == (running & (trigger > k)).mean(), key
        median = float(np.median(k - trigger[detected])) if detected.any() else None
        assert arm.median_steps_to_detect == median, key

    calibrated = measure_monitor(agent, CFG.env, GRID, monitor, dataclasses.replace(SMALL, eval_episodes=200))
    assert calibrated.normal_alarm.false_alarm.value < 0.15  # calibrated for 5%; small-sample slack


def test_conformal_threshold_is_the_finite_sample_quantile():
    peaks = np.arange(1.0, 100.0)  # 99 held-out peaks 1..99
    assert conformal_threshold(peaks, 0.01) == 99.0  # ceil(100 * 0.99) = 99th smallest
    assert conformal_threshold(peaks, 0.1) == 90.0  # ceil(100 * 0.9) = 90th
    with pytest.raises(ConfigError, match="98 held-out"):
        conformal_threshold(peaks[:-1], 0.01)
    rng = np.random.default_rng(0)  # the guarantee: over calibrations, P(fresh peak > threshold) <= target
    rates = [(rng.normal(size=1000) > conformal_threshold(rng.normal(size=199), 0.05)).mean() for _ in range(300)]
    assert np.mean(rates) <= 0.05 + 0.005


@pytest.mark.parametrize("cell", cell_names())
def test_pruned_units_stay_at_zero_in_every_cell(cell):
    torch.manual_seed(0)
    net = RecurrentActorCritic(54, 4, (12, 8), cell=cell, window=3)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.3 * torch.randn_like(p))
    pruned = prune_units(net, 1, np.array([0, 3, 5]))
    out = pruned.unroll(torch.randn(10, 4, 54), pruned.initial_state(4), torch.zeros(10, 4, dtype=torch.bool),
                        return_states=True)  # fmt: skip
    assert out.states is not None
    h = out.states[1].h
    assert h[..., [0, 3, 5]].abs().max() == 0 and h[..., [1, 2]].abs().max() > 0.1
