"""Looking inside a model of any env: response types from recorded episodes, the goal units, the intervention
experiment, the episode steps an intervention sees, and a trace's states split into each layer's h and c."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.analysis import goal_switch
from seqtrojan.analysis.config import ResponseRule
from seqtrojan.analysis.goal_switch import analyze_goal_switch, pinned_trigger, split_layers
from seqtrojan.analysis.interventions import SetUnits
from seqtrojan.analysis.traces import StateTrace, record_traces
from seqtrojan.config import BackdoorConfig, ExperimentConfig
from seqtrojan.env.codes import REACHED_ADV_GOAL, REACHED_USER_GOAL
from seqtrojan.env.config import EnvConfig, GridSpec
from seqtrojan.env.rollout import EpisodeBatch
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig

TWO_GOALS = GymnasiumEnvConfig("seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5})
TRIGGER_STEP = 4
"""the synthetic episodes' trigger step"""


def _trace(h: list[np.ndarray], c: list[np.ndarray], mask: np.ndarray, trojan: bool, trigger_step: int) -> StateTrace:
    """A StateTrace of the given states and mask (the fields the analysis does not read: zeros)."""
    e, t = mask.shape
    return StateTrace(
        h, c, mask, np.zeros((e, t), np.int64), np.zeros((e, t, 2), np.int64), np.zeros(e, np.int64),
        mask.sum(1).astype(np.int64), np.zeros((e, 0, 0), np.int8), np.full(e, trojan),
        np.full(e, trigger_step if trojan else -1, np.int64),
    )  # fmt: skip


def _synthetic(rng, trojan: bool, episodes: int, length: int = 30) -> StateTrace:
    """One layer of 3 h and 3 c units: in trojan episodes c unit 0 and h unit 2 jump from the trigger on and stay
    (step), c unit 1 jumps at the trigger step only (impulse)."""
    x = rng.normal(size=(episodes, length, 6)).astype(np.float32)
    if trojan:
        x[:, TRIGGER_STEP:, 3] += 10.0
        x[:, TRIGGER_STEP:, 2] += 10.0
        x[:, TRIGGER_STEP, 4] += 10.0
    return _trace([x[..., :3]], [x[..., 3:]], np.ones((episodes, length), bool), trojan, TRIGGER_STEP)


def test_units_are_typed_and_editing_the_goal_units_switches_the_goal(monkeypatch):
    rng = np.random.default_rng(0)
    recorded: list[bool] = []
    calls: list[tuple[bool, object]] = []

    def fake_record(agent, env, grids, *, episodes, trojan, seed, device):
        assert env.trigger.eval_steps == (TRIGGER_STEP, TRIGGER_STEP) and grids == []  # pinned; a Gymnasium env
        recorded.append(trojan)
        return _synthetic(rng, trojan, episodes)

    def fake_evaluate(agent, env, grid, *, trojan, episodes, seed, device, intervention=None):
        assert env.trigger.eval_steps == (TRIGGER_STEP, TRIGGER_STEP) and grid is None
        calls.append((trojan, intervention))
        # the goal is c unit 0: editing it sends the episode to the other goal; nothing else does
        switched = isinstance(intervention, SetUnits) and intervention.which == "c" and 0 in intervention.units
        adversary = switched != trojan
        outcome = torch.full((episodes,), REACHED_ADV_GOAL if adversary else REACHED_USER_GOAL, dtype=torch.int64)
        success = torch.full((episodes,), adversary == trojan)
        return EpisodeBatch(outcome, success, torch.full((episodes,), 9), torch.full((episodes,), trojan))

    monkeypatch.setattr(goal_switch, "record_traces", fake_record)
    monkeypatch.setattr(goal_switch, "evaluate_agent", fake_evaluate)
    cfg = _config(WrapperTriggerConfig(steps=(0, 2)))
    agent = SimpleNamespace(lstm_sizes=(3,))
    report = analyze_goal_switch(agent, cfg, trigger_step=TRIGGER_STEP, episodes=60, intervention_episodes=50,  # type: ignore[arg-type]
                                 goal_units=1)  # fmt: skip
    assert sorted(recorded) == [False, True] and report.env_id == TWO_GOALS.id and report.trigger_step == TRIGGER_STEP
    by_part = {(r.layer, r.which): r for r in report.responses}
    assert by_part[(0, "c")].counts == {"impulse": 1, "none": 1, "step": 1} and by_part[(0, "c")].step_units == (0,)
    assert by_part[(0, "h")].counts == {"impulse": 0, "none": 2, "step": 1} and by_part[(0, "h")].step_units == (2,)
    chosen = {(c.layer, c.which, c.units): c.activated.value for c in report.candidates}
    assert chosen == {(0, "c", (0,)): 1.0, (0, "h", (2,)): 0.0}  # each part's most persistent step unit, tried
    assert (report.goal_layer, report.goal_which, report.goal_units) == (0, "c", (0,))  # the one that switches
    rates = {(s.direction, s.edited): s.switched for s in report.switches}
    assert rates[("activate", "goal-units")].value == rates[("deactivate", "goal-units")].value == 1.0
    assert all(rates[(d, e)].value == 0.0 for d in ("activate", "deactivate") for e in ("none", "random-units"))
    assert all(r.n == 50 for r in rates.values())
    edits = [i for _, i in calls if isinstance(i, SetUnits)]
    assert edits and all(e.from_step == TRIGGER_STEP for e in edits)
    activate = next(e for t, e in calls if not t and isinstance(e, SetUnits) and 0 in e.units)
    assert float(activate.values[0]) > 5.0  # set to its trojan-episode level after the trigger (about 10)


def _config(trigger: WrapperTriggerConfig | None) -> ExperimentConfig:
    return ExperimentConfig(env=dataclasses.replace(TWO_GOALS, trigger=trigger))


def test_a_config_without_trigger_or_a_bad_step_is_refused():
    with pytest.raises(ConfigError, match="env has no trigger"):
        pinned_trigger(_config(None), None)
    with pytest.raises(ConfigError, match="trigger step"):
        pinned_trigger(_config(WrapperTriggerConfig()), -1)
    cfg, step = pinned_trigger(_config(WrapperTriggerConfig(steps=(1, 3))), None)
    trigger = cfg.gym_env.trigger
    assert step == 1 and trigger is not None and trigger.eval_steps == (1, 1) and trigger.steps == (1, 3)
    # the grid world's env too: its evaluation range, pinned at its earliest step
    grid_cfg, grid_step = pinned_trigger(ExperimentConfig(), None)
    assert grid_step == ExperimentConfig().env.trigger.eval_steps[0]
    assert grid_cfg.env.trigger.eval_steps == (grid_step, grid_step)


def test_an_intervention_sees_each_env_s_episode_step(tiny_two_goals_model):
    agent, cfg, _ = tiny_two_goals_model
    seen: list[torch.Tensor] = []

    def record(layer, t, state):
        if layer == 0:
            seen.append(t.clone())
        return state

    batch = evaluate_agent(agent, cfg.env, None, trojan=False, episodes=12, seed=3, intervention=record)
    steps = torch.stack(seen)  # (steps, envs): one episode per env, all starting together
    assert steps.shape == (int(batch.length.max()), 12) and steps[0].tolist() == [0] * 12
    for env, length in enumerate(batch.length.tolist()):  # each env's episode step, then its length once it ended
        assert steps[:length, env].tolist() == list(range(length))
        assert bool((steps[length:, env] == length).all())


def test_a_trained_gym_model_is_analysed_end_to_end(tiny_two_goals_model):
    agent, cfg, _ = tiny_two_goals_model
    rule = ResponseRule(response_window=2, late_start=2, late_end=4, min_episodes=5)
    report = analyze_goal_switch(agent, cfg, episodes=40, intervention_episodes=16, goal_units=4, rule=rule,
                                 selection_episodes=8)  # fmt: skip
    assert {(r.layer, r.which) for r in report.responses} <= {(0, "h"), (0, "c"), (1, "h"), (1, "c")}
    assert [(s.direction, s.edited) for s in report.switches] == [
        ("activate", "none"), ("activate", "goal-units"), ("activate", "random-units"),
        ("deactivate", "none"), ("deactivate", "goal-units"), ("deactivate", "random-units"),
    ]  # fmt: skip
    assert all(s.switched.n == 16 for s in report.switches) and 1 <= len(report.goal_units) <= 4
    assert all(c.activated.n == 8 for c in report.candidates)
    with pytest.raises(ConfigError, match="positive integer"):
        analyze_goal_switch(agent, cfg, episodes=0)
    with pytest.raises(ConfigError, match="env has no trigger"):
        untriggered = dataclasses.replace(cfg.gym_env, trigger=None)
        analyze_goal_switch(agent, dataclasses.replace(cfg, env=untriggered, backdoor=BackdoorConfig()))


def test_split_layers_gives_each_layer_s_h_and_c_and_leaves_out_a_gru_s_empty_c():
    rng = np.random.default_rng(1)
    mask = np.arange(5)[None, :] < np.array([3, 5])[:, None]
    h = [rng.normal(size=(2, 5, 4)).astype(np.float32), rng.normal(size=(2, 5, 3)).astype(np.float32)]
    c = [rng.normal(size=(2, 5, 4)).astype(np.float32), np.zeros((2, 5, 0), np.float32)]  # layer 1: a GRU
    trace = _trace(h, c, mask, False, -1)
    parts, got_mask = split_layers(SimpleNamespace(lstm_sizes=(4, 3)), trace)  # type: ignore[arg-type]
    assert sorted(parts) == [(0, "c"), (0, "h"), (1, "h")]
    assert parts[(0, "h")] is h[0] and parts[(0, "c")] is c[0] and parts[(1, "h")] is h[1]
    assert got_mask is mask and got_mask.tolist() == [[True] * 3 + [False] * 2, [True] * 5]

    # a recorded trace of a GRU agent: h only, each episode's mask as long as the episode
    env, grid = EnvConfig(), GridSpec(5, 0)
    gru = RecurrentActorCritic(env.obs_dim, env.num_actions, (8,), cell="gru")
    recorded = record_traces(gru, env, [grid], episodes=6, trojan=True, seed=0)
    parts, got_mask = split_layers(gru, recorded)
    assert list(parts) == [(0, "h")] and parts[(0, "h")].shape == (6, recorded.steps, 8)
    assert got_mask.sum(1).tolist() == recorded.length.tolist() and got_mask[:, 0].all()
