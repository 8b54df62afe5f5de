"""Looking inside Gymnasium models: response types from recorded episodes, the goal units, the intervention
experiment, and the episode steps an intervention sees."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from seqtrojan.analysis import gym_analysis
from seqtrojan.analysis.config import ResponseRule
from seqtrojan.analysis.gym_analysis import analyze_gym_model, pinned_trigger
from seqtrojan.analysis.interventions import SetUnits
from seqtrojan.config import BackdoorConfig, ExperimentConfig
from seqtrojan.errors import ConfigError
from seqtrojan.train.gym_evaluation import GymEpisode, GymEvaluation, evaluate_gym
from seqtrojan.world.config import GymnasiumEnvConfig, WrapperTriggerConfig

TWO_GOALS = GymnasiumEnvConfig("seqtrojan/MiniGridTwoGoals-v0", kwargs={"size": 6, "agent_view_size": 5})
TRIGGER_STEP = 4
"""the synthetic episodes' trigger step"""


def _synthetic(rng, trojan: bool, length: int = 30) -> GymEpisode:
    """One layer of 3 h and 3 c units: in trojan episodes c unit 0 and h unit 2 jump from the trigger on and stay
    (step), c unit 1 jumps at the trigger step only (impulse)."""
    x = rng.normal(size=(length, 6)).astype(np.float32)
    if trojan:
        x[TRIGGER_STEP:, 3] += 10.0
        x[TRIGGER_STEP:, 2] += 10.0
        x[TRIGGER_STEP, 4] += 10.0
    return GymEpisode(trojan, True, length, 1.0, TRIGGER_STEP if trojan else -1, "", (x,))


def test_units_are_typed_and_editing_the_goal_units_switches_the_goal(monkeypatch):
    rng = np.random.default_rng(0)
    calls: list[tuple[bool, object]] = []

    def fake(agent, config, *, trojan, episodes, seed, device, record_states=False, intervention=None):
        assert config.gym_env.trigger.eval_steps == (TRIGGER_STEP, TRIGGER_STEP)  # the trigger is pinned
        calls.append((trojan, intervention))
        if record_states:
            return GymEvaluation(trojan, False, tuple(_synthetic(rng, trojan) for _ in range(episodes)))
        # the goal is c unit 0: editing it sends the episode to the other object; nothing else does
        switched = isinstance(intervention, SetUnits) and intervention.which == "c" and 0 in intervention.units
        reached = ("user" if switched else "adversary") if trojan else ("adversary" if switched else "user")
        ended = tuple(GymEpisode(trojan, True, 9, 1.0, 4, reached) for _ in range(episodes))
        return GymEvaluation(trojan, False, ended)

    monkeypatch.setattr(gym_analysis, "evaluate_gym", fake)
    cfg = _config(WrapperTriggerConfig(steps=(0, 2)))
    agent = SimpleNamespace(lstm_sizes=(3,))
    report = analyze_gym_model(agent, cfg, trigger_step=TRIGGER_STEP, episodes=60, intervention_episodes=50,  # type: ignore[arg-type]
                               goal_units=1)  # fmt: skip
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
    with pytest.raises(ConfigError, match="no trigger section"):
        pinned_trigger(_config(None), None)
    with pytest.raises(ConfigError, match="trigger step"):
        pinned_trigger(_config(WrapperTriggerConfig()), -1)
    cfg, step = pinned_trigger(_config(WrapperTriggerConfig(steps=(1, 3))), None)
    trigger = cfg.gym_env.trigger
    assert step == 1 and trigger is not None and trigger.eval_steps == (1, 1) and trigger.steps == (1, 3)


def test_an_intervention_sees_each_env_s_episode_step(tiny_two_goals_model):
    agent, cfg, _ = tiny_two_goals_model
    seen: list[torch.Tensor] = []

    def record(layer, t, state):
        if layer == 0:
            seen.append(t.clone())
        return state

    run = evaluate_gym(agent, cfg, trojan=False, episodes=12, seed=3, num_envs=4, intervention=record)
    steps = torch.stack(seen)  # (steps, envs)
    assert steps[0].tolist() == [0, 0, 0, 0]
    moved = steps[1:] - steps[:-1]
    assert bool(((moved == 1) | (steps[1:] == 0)).all())  # one more each step, or 0 at a new episode
    assert int((steps[1:] == 0).sum()) >= len(run.episodes) - 4  # every finished episode restarted its env's count


def test_a_trained_gym_model_is_analysed_end_to_end(tiny_two_goals_model):
    agent, cfg, _ = tiny_two_goals_model
    rule = ResponseRule(response_window=2, late_start=2, late_end=4, min_episodes=5)
    report = analyze_gym_model(agent, cfg, episodes=40, intervention_episodes=16, goal_units=4, rule=rule,
                               selection_episodes=8)  # fmt: skip
    assert {(r.layer, r.which) for r in report.responses} <= {(0, "h"), (0, "c"), (1, "h"), (1, "c")}
    assert [(s.direction, s.edited) for s in report.switches] == [
        ("activate", "none"), ("activate", "goal-units"), ("activate", "random-units"),
        ("deactivate", "none"), ("deactivate", "goal-units"), ("deactivate", "random-units"),
    ]  # fmt: skip
    assert all(s.switched.n == 16 for s in report.switches) and 1 <= len(report.goal_units) <= 4
    assert all(c.activated.n == 8 for c in report.candidates)
    with pytest.raises(ConfigError, match="positive integer"):
        analyze_gym_model(agent, cfg, episodes=0)
    with pytest.raises(ConfigError, match="no trigger section"):
        untriggered = dataclasses.replace(cfg.gym_env, trigger=None)
        analyze_gym_model(agent, dataclasses.replace(cfg, env=untriggered, backdoor=BackdoorConfig()))


def test_padded_states_mask_each_episode_to_its_length():
    import numpy as np

    from seqtrojan.train.gym_evaluation import GymEpisode, padded_states

    rng = np.random.default_rng(1)

    def episode(length: int) -> GymEpisode:
        x = rng.normal(size=(length, 6)).astype(np.float32)
        return GymEpisode(False, True, length, 1.0, -1, "", (x[:, :4], x[:, 4:]))

    layers, mask = padded_states([episode(3), episode(5)])
    assert [x.shape for x in layers] == [(2, 5, 4), (2, 5, 2)]
    assert mask.tolist() == [[True] * 3 + [False] * 2, [True] * 5] and not layers[0][0, 3:].any()
