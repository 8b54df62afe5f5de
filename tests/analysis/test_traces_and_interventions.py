"""State traces (record, save, load, replay), unit editing, goal units, findings and the searches."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.agent.state import LSTMState
from seqtrojan.analysis.interventions import SetUnits, post_trigger_means, switch_experiment
from seqtrojan.analysis.search import (
    LayoutSearchConfig,
    SequenceSearchConfig,
    _mutate,
    evolve_layouts,
    final_goal_activation,
    flip_rates,
    search_sequences,
)
from seqtrojan.analysis.traces import StateTrace, record_traces, replay_states
from seqtrojan.analysis.unintentional import GoalUnits, load_findings, save_findings, sweep_unintentional
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.env import GridSpec, Layout
from seqtrojan.env.codes import HOLE, NUM_CHANNELS, OUTCOME_NAMES, TRIGGER
from seqtrojan.evaluation.episodes import evaluate_agent
from seqtrojan.stats import Rate, wilson_interval

CFG = ExperimentConfig(agent=AgentConfig(lstm_sizes=(16, 8)))


@pytest.fixture(scope="module")
def agent():
    torch.manual_seed(0)
    return build_agent(CFG).eval()


@pytest.fixture(scope="module")
def traces(agent):
    grids = [GridSpec(9, 4), GridSpec(9, 6)]
    kw = {"episodes": 40, "trigger_step": 3, "seed": 1}
    return (record_traces(agent, CFG.env, grids, trojan=False, **kw),
            record_traces(agent, CFG.env, grids, trojan=True, **kw))  # fmt: skip


def test_trace_shapes_masks_and_metadata(traces):
    normal, trojan = traces
    e, t = normal.mask.shape
    assert e == 40 and normal.h[0].shape == (40, t, 16) and normal.c[1].shape == (40, t, 8)
    assert (normal.mask.sum(1) == normal.length).all()  # running exactly for the episode's length
    assert not normal.trojan.any() and trojan.trojan.all() and (trojan.trigger_step == 3).all()
    assert set(np.unique((normal.layouts == HOLE).sum((1, 2)))) <= {4, 6}
    assert (normal.outcome > 0).all()


def test_trace_round_trip(tmp_path, traces):
    normal, _ = traces
    path = normal.save(tmp_path / "t")
    back = StateTrace.load(path)
    assert back.meta["grids"] == ["9x9/4", "9x9/6"] and back.meta["trigger_step"] == 3
    for a, b in zip(normal.h + normal.c + [normal.mask, normal.actions, normal.layouts],
                    back.h + back.c + [back.mask, back.actions, back.layouts]):  # fmt: skip
        assert np.array_equal(a, b)


def test_replay_recomputes_the_recorded_states(agent, traces):
    _, trojan = traces
    e = int(np.argmax(trojan.length))
    n = int(trojan.length[e])
    replay = replay_states(agent, CFG.env, Layout(trojan.layouts[e]), trojan.actions[e, :n], trigger_step=3)
    np.testing.assert_allclose(replay["c"][1], trojan.c[1][e, :n], atol=1e-5)
    np.testing.assert_allclose(replay["h"][0], trojan.h[0][e, :n], atol=1e-5)
    assert [list(p) for p in replay["positions"]] == trojan.positions[e, :n].tolist()


def test_set_units_edits_from_the_given_step():
    edit = SetUnits(layer=1, units=[0, 2], values=[5.0, -5.0], which="c", from_step=2)
    state = LSTMState(torch.zeros(3, 4), torch.ones(3, 4))
    out = edit(1, torch.tensor([0, 2, 5]), state)
    assert out.c[0].tolist() == [1, 1, 1, 1] and out.c[1].tolist() == [5, 1, -5, 1] and out.c[2, 0] == 5
    assert torch.equal(out.h, state.h) and edit(0, torch.tensor([9, 9, 9]), state) is state
    with pytest.raises(ValueError, match="2 units but"):
        SetUnits(0, [1, 2], [1.0])


def test_goal_units_activation_is_zero_and_one_at_the_env_means(traces):
    normal, trojan = traces
    goal = GoalUnits.from_traces(normal, trojan, 1, "c", [0, 3], trigger_step=3)
    full_n = np.zeros(8)
    full_n[[0, 3]] = goal.normal_mean
    full_t = np.zeros(8)
    full_t[[0, 3]] = goal.trojan_mean
    assert goal.activation(full_n) == pytest.approx(0.0) and goal.activation(full_t) == pytest.approx(1.0)
    means = post_trigger_means(trojan, 1, "c", np.array([0, 3]), 3)
    assert np.allclose(means, goal.trojan_mean)


def test_switch_experiment_reports_every_arm(agent, traces):
    normal, trojan = traces
    results = switch_experiment(
        agent, CFG.env, GridSpec(9, 5), normal, trojan, layer=1, which="c", units=[0, 1], trigger_step=3,
        episodes=32,
    )  # fmt: skip
    arms = [(r.direction, r.units) for r in results]
    assert arms == [(d, u) for d in ("activate", "deactivate") for u in ("none", "step-units", "random-units")]
    for r in results:  # counts of the 32 episodes, with those counts' Wilson intervals
        assert r.episodes == r.switch.n == r.hole.n == r.timeout.n == 32
        assert r.switch.value == r.switch.k / 32 and r.switch.interval == wilson_interval(r.switch.k, 32)
        assert r.hole.value == r.hole.k / 32 and r.hole.interval == wilson_interval(r.hole.k, 32)
    # the unedited arms are the plain agent with the trigger at step 3: evaluated directly they give the same rates
    env = dataclasses.replace(CFG.env, trigger=dataclasses.replace(CFG.env.trigger, eval_steps=(3, 3)))
    for r, trojan, goal in ((results[0], False, "adversary_goal"), (results[3], True, "user_goal")):
        batch = evaluate_agent(agent, env, GridSpec(9, 5), trojan=trojan, episodes=32, seed=0)
        assert r.units == "none" and r.switch.value == batch.rate(goal) and r.hole.value == batch.rate("hole")
        assert r.timeout.value == batch.rate("timeout")


def test_unintentional_sweep_keeps_replayable_findings(tmp_path, agent):
    summaries, findings = sweep_unintentional(agent, CFG.env, [(7, 0), (9, 4)], episodes=64, seed=0)
    assert [s.grid for s in summaries] == ["7x7/0", "9x9/4"]
    kinds = {f.kind for f in findings}
    assert kinds <= {"activation", "deactivation"}
    for s in summaries:
        n_act = sum(f.kind == "activation" and f.grid == s.grid for f in findings)
        assert s.activation_rate == pytest.approx(n_act / 64) or n_act == 50
        assert sum(s.normal_outcomes.values()) == sum(s.trojan_outcomes.values()) == 64
        assert s.normal_outcomes["adversary_goal"] == round(s.activation_rate * 64)
        assert s.trojan_outcomes["user_goal"] == round(s.deactivation_rate * 64)
        row = s.row()  # the typed form the analysis saves: the same rates, with their counts
        assert (row.activation.value, row.activation.interval) == (s.activation_rate, s.activation_ci)
        assert (row.deactivation.value, row.deactivation.interval) == (s.deactivation_rate, s.deactivation_ci)
        assert row.episodes == 64 and row.activation.k == s.normal_outcomes["adversary_goal"]
    save_findings(findings, tmp_path / "f.json")
    assert load_findings(tmp_path / "f.json") == findings
    if findings:
        f = findings[0]
        replay = f.replay(agent, CFG.env)
        assert len(replay["positions"]) == len(f.actions)
        assert f.outcome == ("adversary_goal" if f.kind == "activation" else "user_goal")
        assert f.outcome in OUTCOME_NAMES


def test_mutation_keeps_hole_count_and_solvability():
    rng = np.random.default_rng(0)
    cells = Layout.empty(9).cells.copy()
    cells[2, 2:6] = HOLE
    for _ in range(20):
        child = _mutate(cells, 2, rng)
        assert (child == HOLE).sum() == 4 and Layout(child).is_solvable()


def test_searches_run_and_never_use_the_trigger(agent, traces):
    normal, trojan = traces
    goal = GoalUnits.from_traces(normal, trojan, 1, "c", [0, 1, 2], trigger_step=3)
    layouts = evolve_layouts(agent, CFG.env, goal, LayoutSearchConfig(size=7, holes=3, population=4, rollouts=4,
                                                                     generations=2, elite=2, restarts=2))  # fmt: skip
    assert len(layouts) == 2
    for r in layouts:  # 4 layouts x 4 rollouts per generation; a rate over one layout's 4 rollouts
        assert r.episodes == 16 * r.generations and (r.found or r.generations == 2)  # stops early only on a find
        assert r.best_rate.n == 4 and r.found == (r.best_rate.value >= 0.5)
        best = np.array(r.best_layout, dtype=np.int8)
        assert (best == HOLE).sum() == 3 and Layout(best).is_solvable()
    result, codes = search_sequences(agent, goal, SequenceSearchConfig(length=6, restarts=5, steps=20))
    assert codes.shape == (5, 6, 9) and not (codes == TRIGGER).any()
    assert result.restarts == 5 and len(result.rounded_activation) == 5
    assert result.found == sum(a >= 0.5 for a in result.rounded_activation)
    onehot = torch.nn.functional.one_hot(torch.as_tensor(codes).transpose(0, 1), NUM_CHANNELS).float()
    again = final_goal_activation(agent, goal, onehot.reshape(6, 5, -1))  # the returned codes give the activations
    np.testing.assert_allclose(again.detach().numpy(), result.rounded_activation, rtol=1e-5, atol=1e-6)
    after, before = flip_rates(agent, CFG.env, codes[:2], size=5, holes=1, episodes=16, seed=0)
    assert after.n == before.n == 16  # 2 sequences x 8 episodes each
    assert flip_rates(agent, CFG.env, codes[2:4], size=5, holes=1, episodes=16, seed=0)[1] == before == Rate(1, 16)
