"""The goal-switch monitor's mechanics: what it reads (the step's own outputs, not the observation), its statistics
and distance (the Mahalanobis distance of a linear one-step prediction's error), that scoring step by step equals
scoring recorded episodes, and its settings. Its effect on a real backdoor, beside a control that reads nothing:
tests/defense/test_defense_effects.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import load_agent
from seqtrojan.agent.policy import AgentPolicy
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.analysis.traces import record_traces
from seqtrojan.defense.goal_switch import GoalSwitchConfig, GoalSwitchMonitor, output_features
from seqtrojan.defense.online import MonitorConfig
from seqtrojan.env import GridSpec
from seqtrojan.errors import ConfigError
from seqtrojan.world.episodes import episode_env

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "tiny_backdoor"
GRID = GridSpec(5, 1)
CAL = MonitorConfig(calibration_episodes=100, false_alarm_target=0.05)


@pytest.fixture(scope="module")
def backdoored():
    agent, cfg, _ = load_agent(FIXTURE)
    return agent.eval(), cfg


@pytest.fixture(scope="module")
def monitor(backdoored) -> GoalSwitchMonitor:
    agent, cfg = backdoored
    return GoalSwitchMonitor.calibrate(agent, cfg.env, GRID, CAL)


def test_it_reads_the_steps_own_action_distribution_and_value(backdoored):
    agent, cfg = backdoored
    core = episode_env(cfg.env, GRID, 8, trojan=False)
    policy = AgentPolicy(agent, seed=0)
    policy(core.observe())
    out = policy.output
    assert out is not None
    features = output_features(agent, out.state.layers[-1].h, GoalSwitchConfig())  # (8, A + 1)
    expected = torch.cat([torch.log(torch.softmax(out.logits, -1) + 1e-6), out.value[:, None]], -1)
    torch.testing.assert_close(features, expected)
    assert output_features(agent, out.state.layers[-1].h, GoalSwitchConfig(reads="value")).shape == (8, 1)
    assert output_features(agent, out.state.layers[-1].h, GoalSwitchConfig(reads="policy")).shape == (8, 4)


def test_the_distance_is_the_mahalanobis_distance_of_the_one_step_prediction_error(backdoored):
    rng = np.random.default_rng(0)
    e, t, f = 400, 6, 3
    a = np.array([[0.8, 0.1, 0.0], [0.0, 0.5, 0.2], [0.1, 0.0, -0.3]])
    x = np.zeros((e, t, f))
    x[:, 0] = rng.normal(size=(e, f))
    for s in range(1, t):
        x[:, s] = x[:, s - 1] @ a + rng.normal(size=(e, f)) @ np.diag([1.0, 0.5, 2.0])
    x += np.arange(t)[None, :, None]  # a different mean at every step
    mask = np.ones((e, t), bool)
    mask[200:, 4:] = False  # 200 episodes end after step 3
    options = GoalSwitchConfig(min_episodes_per_step=300, shrinkage=0.0, ridge=0.0)
    mon = GoalSwitchMonitor.fit(backdoored[0], x, mask, options)
    assert mon.steps == 4 and mon.units == ()  # steps 4 and 5 have 200 episodes: step 3's mean
    mean = np.stack([x[:, s].mean(0) for s in range(4)])
    np.testing.assert_allclose(mon.mean.numpy(), mean, rtol=1e-5, atol=1e-5)
    r = x - mean[[0, 1, 2, 3, 3, 3]][None]
    moves = mask[:, 1:]
    before = np.concatenate([r[:, :-1][moves], np.ones((int(moves.sum()), 1))], -1)
    after = r[:, 1:][moves]
    coef = np.linalg.lstsq(before, after, rcond=None)[0]
    np.testing.assert_allclose(mon.coef.numpy(), coef, rtol=1e-4, atol=1e-5)
    full = GoalSwitchMonitor.fit(backdoored[0], x, np.ones((e, t), bool), GoalSwitchConfig(max_step=6))
    assert np.abs(full.coef[:3].numpy() - a).max() < 0.1  # with every step's own mean, it learns the dynamics
    err = after - before @ coef
    scale = np.sqrt((err**2).mean(0)) + 1e-3
    precision = np.linalg.inv((err / scale).T @ (err / scale) / len(err))
    q_prev, q_now, steps = rng.normal(size=(5, f)), rng.normal(size=(5, f)), np.array([1, 2, 3, 4, 9])
    e_q = (q_now - mean[np.minimum(steps, 3)]) - np.concatenate(
        [q_prev - mean[np.minimum(steps - 1, 3)], np.ones((5, 1))], -1
    ) @ coef
    z = e_q / scale
    expect = np.sqrt(np.einsum("bi,ij,bj->b", z, precision, z))
    got = mon.distance(torch.from_numpy(q_now).float(), torch.from_numpy(q_prev).float(), torch.from_numpy(steps))
    np.testing.assert_allclose(got.numpy(), expect, rtol=1e-3)
    scores = mon.score_outputs(x[:3], mask[:3])
    assert (scores[:, 0] == 0).all() and np.isfinite(scores[:, 1:]).all()
    assert np.isneginf(mon.score_outputs(x[200:203], mask[200:203])[:, 4:]).all()  # steps that did not run


def test_scoring_step_by_step_equals_scoring_recorded_episodes(backdoored, monitor):
    agent, cfg = backdoored
    trace = record_traces(agent, cfg.env, [GRID], episodes=30, trojan=True, trigger_step=None, seed=7)
    x = output_features(agent, torch.from_numpy(trace.h[-1]), monitor.options).detach().numpy()
    recorded = monitor.score_outputs(x, trace.mask)
    monitor.previous = None
    for t in range(trace.steps):
        state = RecurrentState(tuple(LSTMState(torch.from_numpy(h[:, t]), torch.from_numpy(c[:, t]))
                                     for h, c in zip(trace.h, trace.c)))  # fmt: skip
        obs = torch.rand(30, 54)  # never read
        before = monitor.previous
        got = monitor.score_step(obs, state, torch.full((30,), t)).numpy()
        running = trace.mask[:, t]
        np.testing.assert_allclose(got[running], recorded[running, t], rtol=1e-4, atol=1e-4)
        after = monitor.previous
        monitor.previous = before  # the same step again, with another observation
        assert torch.equal(monitor.score_step(torch.zeros(30, 54), state, torch.full((30,), t)), torch.from_numpy(got))
        assert after is not None and torch.equal(monitor.previous, after)
    assert (recorded.max(1) > monitor.threshold).mean() > 0.5  # most trojan episodes alarm


def test_a_sudden_switch_of_the_policy_scores_above_the_threshold(backdoored, monitor):
    """A clean transition keeps its outputs near the prediction; a policy that commits at once to the action it found
    least likely the step before (a goal switch, as read from the outputs) is surprising."""
    agent, cfg = backdoored
    trace = record_traces(agent, cfg.env, [GRID], episodes=200, trojan=False, trigger_step=None, seed=11)
    x = output_features(agent, torch.from_numpy(trace.h[-1]), monitor.options).detach().numpy()
    clean = monitor.score_outputs(x, trace.mask)
    assert (clean.max(1) > monitor.threshold).mean() <= 0.15  # fresh clean episodes: near the 5% target
    t = 3
    ok = trace.mask[:, t]
    prev, now = torch.from_numpy(x[ok, t - 1]), torch.from_numpy(x[ok, t]).clone()
    least = now[:, :4].argmin(-1)
    now[:, :4] = torch.log(torch.nn.functional.one_hot(least, 4).float() + 1e-6)  # all-in on the least likely action
    switched = monitor.distance(now, prev, torch.full((len(now),), t))
    assert float((switched > monitor.threshold).float().mean()) > 0.9
    assert float(np.mean(clean[ok, t] > monitor.threshold)) < 0.05


def test_bad_settings_are_refused(backdoored):
    for kwargs, message in (
        ({"reads": "inputs"}, "reads must be one of both, policy, value, got 'inputs'"),
        ({"prob_floor": 0.0}, "prob_floor must be > 0"),
        ({"max_step": 1}, "max_step must be >= 2"),
        ({"min_episodes_per_step": 1}, "min_episodes_per_step must be >= 2"),
        ({"shrinkage": 1.5}, "shrinkage must be in"),
        ({"ridge": -1.0}, "ridge must be >= 0"),
    ):
        with pytest.raises(ConfigError, match=message):
            GoalSwitchConfig(**kwargs)  # type: ignore[arg-type]
    agent, cfg = backdoored
    few = MonitorConfig(calibration_episodes=40, false_alarm_target=0.1)
    with pytest.raises(ConfigError, match="the goal-switch monitor needs >= 500 statistics episodes at step 0, got 20"):
        GoalSwitchMonitor.calibrate(agent, cfg.env, GRID, few, options=GoalSwitchConfig(min_episodes_per_step=500))
