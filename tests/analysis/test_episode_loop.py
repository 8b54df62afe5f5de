"""One episode loop (seqtrojan.env.rollout.run_episodes with recorders) under traces, replays and the monitor, and
one per-step policy call under training's collector: each gives exactly (bitwise) what a plain loop written out
here gives, the loops these modules had before they shared one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.analysis.interventions import SetUnits
from seqtrojan.analysis.traces import record_traces, replay_states
from seqtrojan.config import AgentConfig, ExperimentConfig
from seqtrojan.defense.monitor import MonitoredPolicy, StateMonitor
from seqtrojan.env import EnvConfig, GridSpec, Layout, TrojanGridCore
from seqtrojan.env.rollout import EpisodeBatch, EpisodeStep, run_episodes
from seqtrojan.errors import ShapeError
from seqtrojan.train.rollout import RolloutCollector

ENV = EnvConfig(size=7, holes=3)
CFG = ExperimentConfig(env=ENV, agent=AgentConfig(lstm_sizes=(16, 8)))
GRIDS = [GridSpec(9, 4), GridSpec(9, 6, 30)]


@pytest.fixture(scope="module")
def agent():
    torch.manual_seed(0)
    return build_agent(CFG).eval()


def _gumbel(logits: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    u = torch.rand(logits.shape, device=logits.device, generator=generator).clamp_(min=1e-20)
    return (logits - torch.log(-torch.log(u))).argmax(-1)


@torch.no_grad()
def _reference_traces(agent, grids, *, episodes, trojan, trigger_step, seed, greedy, intervention):
    """Every step written out: network step, action, record, env step, until every episode has ended."""
    trig = dataclasses.replace(ENV.trigger, eval_steps=(trigger_step, trigger_step))
    env = dataclasses.replace(ENV, size=grids[0].size, holes=grids[0].holes, trigger=trig)
    core = TrojanGridCore(env, episodes, seed=seed, grids=grids, trojan_probability=float(trojan), phase="eval")
    generator = torch.Generator().manual_seed(seed)
    state = agent.initial_state(episodes)
    obs, running = core.observe(), torch.ones(episodes, dtype=torch.bool)
    r = core.view_size // 2
    rows: dict[str, list] = {"h": [], "c": [], "mask": [], "actions": [], "positions": []}
    outcome, length = np.zeros(episodes, np.int64), np.zeros(episodes, np.int64)
    for t in range(max(g.time_limit for g in core.grids)):
        out = agent.step(obs, state, t=core.t, intervention=intervention)
        state = out.state
        action = out.logits.argmax(-1) if greedy else _gumbel(out.logits, generator)
        rows["mask"].append(running.numpy().copy())
        rows["h"].append([layer.h.numpy() for layer in state.layers])
        rows["c"].append([layer.c.numpy() for layer in state.layers])
        rows["actions"].append(action.numpy())
        rows["positions"].append(np.stack([core.pos.numpy() // core.side - r, core.pos.numpy() % core.side - r], -1))
        result = core.step(action, autoreset=False)
        ended = (result.done & running).numpy()
        outcome[ended], length[ended] = result.outcome.numpy()[ended], t + 1
        running &= ~result.done
        obs = result.obs
        if not running.any():
            break
    layers = len(agent.lstm_sizes)
    return {
        "h": [np.stack([x[i] for x in rows["h"]], 1) for i in range(layers)],
        "c": [np.stack([x[i] for x in rows["c"]], 1) for i in range(layers)],
        "mask": np.stack(rows["mask"], 1),
        "actions": np.stack(rows["actions"], 1),
        "positions": np.stack(rows["positions"], 1),
        "outcome": outcome,
        "length": length,
    }


def _assert_same(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize(
    ("trojan", "greedy", "edit"), [(False, False, False), (True, False, True), (True, True, False)]
)
def test_traces_equal_the_plain_loop(agent, trojan, greedy, edit):
    intervention = SetUnits(layer=1, units=[0, 3], values=[2.0, -1.0], which="c", from_step=2) if edit else None
    kw = {"episodes": 24, "trojan": trojan, "trigger_step": 3, "seed": 5, "greedy": greedy}
    trace = record_traces(agent, ENV, GRIDS, intervention=intervention, **kw)
    ref = _reference_traces(agent, GRIDS, intervention=intervention, **kw)
    for i in range(2):
        _assert_same(trace.h[i], ref["h"][i])
        _assert_same(trace.c[i], ref["c"][i])
    for name in ("mask", "actions", "positions", "outcome", "length"):
        _assert_same(getattr(trace, name), ref[name])
    assert trace.steps == ref["mask"].shape[1] and (trace.mask.sum(1) == trace.length).all()


@torch.no_grad()
def _reference_replay(agent, layout, actions, trigger_step, intervention):
    core = TrojanGridCore(dataclasses.replace(ENV, size=layout.size, holes=0), 1, phase="eval")
    core.set_episode(0, layout, on_step=trigger_step)
    state, obs = agent.initial_state(1), core.observe()
    hs, cs, prefs, positions = [], [], [], []
    for a in actions:
        positions.append(core.snapshot(0).agent)
        out = agent.step(obs, state, t=core.t, intervention=intervention)
        state = out.state
        hs.append([layer.h[0].numpy().copy() for layer in state.layers])
        cs.append([layer.c[0].numpy().copy() for layer in state.layers])
        prefs.append(torch.softmax(out.logits[0], -1).numpy())
        result = core.step(torch.tensor([int(a)]), autoreset=False)
        obs = result.obs
        if bool(result.done[0]):
            break
    return hs, cs, np.stack(prefs), positions


def test_replays_equal_the_plain_loop(agent):
    trace = record_traces(agent, ENV, [GridSpec(7, 3)], episodes=8, trojan=True, trigger_step=2, seed=1)
    intervention = SetUnits(layer=0, units=[1], values=[3.0], which="h", from_step=1)
    for e in range(4):
        n = int(trace.length[e])
        layout = Layout(trace.layouts[e])
        # the whole episode, a cut one (open loop stops when the actions run out), and extra actions past its end
        for actions in (trace.actions[e, :n], trace.actions[e, : max(1, n - 2)], [*trace.actions[e, :n], 0, 1]):
            for edit in (None, intervention):
                got = replay_states(agent, ENV, layout, actions, trigger_step=2, intervention=edit)
                hs, cs, prefs, positions = _reference_replay(agent, layout, actions, 2, edit)
                assert got["positions"] == positions
                _assert_same(got["policy"], prefs)
                for i in range(2):
                    _assert_same(got["h"][i], np.stack([x[i] for x in hs]))
                    _assert_same(got["c"][i], np.stack([x[i] for x in cs]))
        assert got["positions"][:n] == [tuple(p) for p in trace.positions[e, :n].tolist()]


def test_a_replay_refuses_actions_the_env_does_not_have(agent):
    with pytest.raises(ShapeError, match="out of range"):
        replay_states(agent, ENV, Layout.empty(7), [0, 9], trigger_step=None)


class _ReferenceMonitoredPolicy:
    """The monitor's policy as it was written before it shared AgentPolicy's step and sampler."""

    def __init__(self, agent, monitor, core, reset, seed=0):
        self.agent, self.monitor, self.core, self.reset_on_alarm = agent, monitor, core, reset
        self.generator = torch.Generator().manual_seed(seed)
        self.state = None
        self.first_alarm = torch.full((core.num_envs,), -1, dtype=torch.int64)
        self.alarms = torch.zeros(core.num_envs, dtype=torch.int64)

    def reset(self, num_envs):
        self.state = self.agent.initial_state(num_envs)
        self.first_alarm.fill_(-1)
        self.alarms.zero_()

    @torch.no_grad()
    def __call__(self, obs):
        out = self.agent.step(obs, self.state)
        state = out.state
        alarm = self.monitor.score(state) > self.monitor.threshold
        self.first_alarm = torch.where(alarm & (self.first_alarm < 0), self.core.t, self.first_alarm)
        self.alarms += alarm.long()
        if self.reset_on_alarm and bool(alarm.any()):
            keep = (~alarm).float()[:, None]
            state = RecurrentState(tuple(LSTMState(s.h * keep, s.c * keep) for s in state.layers))
        self.state = state
        return _gumbel(out.logits, self.generator)


@pytest.mark.parametrize("reset", [False, True])
def test_the_monitored_policy_equals_the_plain_one(agent, reset):
    trace = record_traces(agent, ENV, [GridSpec(7, 3)], episodes=40, trojan=False, seed=2)
    rows = [np.concatenate([h, c], -1)[trace.mask] for h, c in zip(trace.h, trace.c)]
    mean, std = [r.mean(0) for r in rows], [r.std(0) + 1e-3 for r in rows]
    monitor = StateMonitor(mean, std, threshold=4.0)  # low enough that many steps alarm (and reset)
    results = []
    for make in (MonitoredPolicy, _ReferenceMonitoredPolicy):
        core = TrojanGridCore(ENV, 48, phase="eval", trojan_probability=1.0)
        policy = make(agent, monitor, core, reset=reset, seed=3)
        batch = run_episodes(core, policy, seed=11)
        results.append((batch, policy.first_alarm.clone(), policy.alarms.clone()))
    (batch, first, alarms), (ref_batch, ref_first, ref_alarms) = results
    for name in ("outcome", "success", "length", "trojan"):
        assert torch.equal(getattr(batch, name), getattr(ref_batch, name))
    assert torch.equal(first, ref_first) and torch.equal(alarms, ref_alarms)
    assert int((alarms > 0).sum()) > 5  # the monitor did act in these episodes


def test_the_collector_equals_the_plain_loop(agent):
    def make_core():
        return TrojanGridCore(ENV, 16, seed=4, trojan_probability=0.5)

    collector = RolloutCollector(make_core(), agent, steps=32, sequence_length=8)
    collector.seed(11)
    rollouts = [collector.collect()[0] for _ in range(2)]
    core, generator = make_core(), torch.Generator().manual_seed(11)
    state, obs, start = agent.initial_state(16), core.observe(), torch.ones(16)
    with torch.no_grad():
        for rollout in rollouts:
            for t in range(32):
                out = agent.step(obs, state, start)
                state = out.state
                action = _gumbel(out.logits, generator)
                logprob = torch.log_softmax(out.logits, -1)[torch.arange(16), action]
                result = core.step(action, check=False)
                assert torch.equal(rollout.actions[t], action) and torch.equal(rollout.logprobs[t], logprob)
                assert torch.equal(rollout.values[t], out.value) and torch.equal(rollout.rewards[t], result.reward)
                obs, start = result.obs, result.done.float()


class _Log:
    def __init__(self) -> None:
        self.steps: list[EpisodeStep] = []
        self.ended: list[EpisodeBatch] = []

    def on_step(self, step: EpisodeStep) -> None:
        self.steps.append(step)

    def on_end(self, batch: EpisodeBatch) -> None:
        self.ended.append(batch)


def test_recorders_see_every_step_and_the_outcomes(agent):
    from seqtrojan.agent.policy import AgentPolicy

    core = TrojanGridCore(ENV, 12, phase="eval", trojan_probability=0.5)
    log, other = _Log(), _Log()
    batch = run_episodes(core, AgentPolicy(agent, seed=1), seed=3, recorders=[log, other])
    assert log.ended == [batch] and other.ended == [batch] and len(other.steps) == len(log.steps)
    assert [s.t for s in log.steps] == list(range(len(log.steps))) == list(range(int(batch.length.max())))
    running = torch.stack([s.running for s in log.steps], 1)  # (B, T)
    assert torch.equal(running.sum(1), batch.length)  # running exactly for each episode's length
    assert all(s.state is not None and s.logits.shape == (12, ENV.num_actions) for s in log.steps)
    first = log.steps[0]
    assert first.cells.tolist() == [list(ENV.start)] * 12
    # a policy without network output: no state or logits; max_steps cuts the loop (those episodes: length 0)
    core = TrojanGridCore(EnvConfig(size=7, holes=0), 4, phase="eval")
    log = _Log()
    batch = run_episodes(core, lambda obs: torch.zeros(4, dtype=torch.int64), seed=0, recorders=[log], max_steps=2)
    assert len(log.steps) == 2 and log.steps[0].state is None and log.steps[0].logits is None
    assert batch.length.tolist() == [0, 0, 0, 0] and batch.outcome.tolist() == [0, 0, 0, 0]
    assert [s.cells[0].tolist() for s in log.steps] == [[6, 3], [5, 3]]  # moving up from the start
