"""The ``state_bounds`` mitigation: bounds fitted on clean states, the clipping intervention, its registration, and
its effect on a tiny backdoored agent trained here in about 6 s (5x5/1, LSTM 32-16, the whole-view trigger code at
step 1 or 2, 131k env steps).

Measured on that agent (bounds from 200 clean episodes, 200 fresh episodes per arm, one training run): attack success
0.91 undefended, 0.37 with the clean min/max bounds, 0.19 with the [0.01, 0.99] quantiles; clean success 0.985 in
every arm.
"""

from __future__ import annotations

import dataclasses
import tempfile

import numpy as np
import pytest
import torch

from seqtrojan.agent.checkpoint import build_agent, load_agent
from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState
from seqtrojan.analysis.traces import record_traces
from seqtrojan.config import AgentConfig, BackdoorConfig, ExperimentConfig, PPOConfig, RunConfig
from seqtrojan.defense.mitigation import MITIGATIONS, MitigationConfig, MitigationContext
from seqtrojan.defense.state_bounds import (
    ClipToBounds,
    StateBoundsConfig,
    calibrate_bounds,
    clean_trace,
    fit_bounds,
    fit_trace,
)
from seqtrojan.env import EnvConfig, GridSpec, TriggerConfig
from seqtrojan.errors import ConfigError
from seqtrojan.evaluation.episodes import evaluate_agent, outcome_rate
from seqtrojan.serde import from_dict

CFG = ExperimentConfig(env=EnvConfig(size=7, holes=3), agent=AgentConfig(lstm_sizes=(16, 8)))
GRID = GridSpec(7, 3)


@pytest.fixture(scope="module")
def untrained() -> RecurrentActorCritic:
    torch.manual_seed(0)
    return build_agent(CFG).eval()


@pytest.fixture(scope="module")
def trace(untrained):
    return clean_trace(untrained, CFG.env, GRID, episodes=40, seed=0)


def test_the_bounds_contain_every_clean_state_and_are_its_range(trace):
    bounds = fit_trace(trace, StateBoundsConfig(quantile=0.0))
    assert [(b.layer, b.part) for b in bounds.bounds] == [(0, "h"), (0, "c"), (1, "h"), (1, "c")]
    assert bounds.steps == int(trace.mask.sum()) > 0
    for b in bounds.bounds:
        rows = trace.states(b.part, b.layer)[trace.mask]  # (steps, units): every running step
        np.testing.assert_allclose(b.low, rows.min(0), rtol=1e-6)  # quantile 0: exactly the clean min and max
        np.testing.assert_allclose(b.high, rows.max(0), rtol=1e-6)
        assert (rows >= b.low).all() and (rows <= b.high).all()
        assert (b.high > b.low).any()  # not collapsed to a point


def test_quantile_and_margin_tighten_and_widen_the_range(trace):
    q = fit_trace(trace, StateBoundsConfig(quantile=0.05))
    m = fit_trace(trace, StateBoundsConfig(quantile=0.05, margin=1.0))
    for tight, wide in zip(q.bounds, m.bounds, strict=True):
        rows = trace.states(tight.part, tight.layer)[trace.mask]
        np.testing.assert_allclose(tight.low, np.quantile(rows, 0.05, axis=0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(tight.high, np.quantile(rows, 0.95, axis=0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(wide.high - tight.high, rows.std(0), rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(tight.low - wide.low, rows.std(0), rtol=1e-4, atol=1e-6)
    only_c = fit_trace(trace, StateBoundsConfig(parts=("c",), layers=(1,)))
    assert [(b.layer, b.part) for b in only_c.bounds] == [(1, "c")]


def test_the_intervention_clips_exactly_to_the_bounds_and_leaves_states_inside_alone(trace):
    bounds = fit_trace(trace, StateBoundsConfig(quantile=0.0))
    clip = ClipToBounds(bounds)
    for layer in (0, 1):
        lo = {b.part: torch.from_numpy(b.low) for b in bounds.bounds if b.layer == layer}
        hi = {b.part: torch.from_numpy(b.high) for b in bounds.bounds if b.layer == layer}
        inside = LSTMState((lo["h"] + hi["h"])[None] / 2, (lo["c"] + hi["c"])[None] / 2)
        out = clip(layer, None, inside)
        assert torch.equal(out.h, inside.h) and torch.equal(out.c, inside.c)
        beyond = LSTMState(torch.stack([hi["h"] + 5.0, lo["h"] - 5.0]), torch.stack([hi["c"] + 0.1, lo["c"] - 0.1]))
        out = clip(layer, torch.tensor([3, 3]), beyond)
        assert torch.equal(out.h, torch.stack([hi["h"], lo["h"]])) and torch.equal(
            out.c, torch.stack([hi["c"], lo["c"]])
        )
    h_only = ClipToBounds(fit_trace(trace, StateBoundsConfig(parts=("h",))))
    far = LSTMState(torch.full((1, 16), 99.0), torch.full((1, 16), 99.0))
    out = h_only(0, None, far)
    assert float(out.h.max()) < 99.0 and torch.equal(out.c, far.c)  # c is not a clipped part


def test_an_agent_run_with_the_clip_never_leaves_the_bounds(untrained, trace):
    bounds = fit_trace(trace, StateBoundsConfig(quantile=0.2))  # tight: most steps are clipped somewhere
    clipped = clean_trace(untrained, CFG.env, GRID, episodes=20, seed=1)
    assert any(((clipped.states(b.part, b.layer)[clipped.mask] > b.high).any()) for b in bounds.bounds)
    held = record_traces(untrained, CFG.env, [GRID], episodes=20, trojan=False, seed=1, intervention=bounds.clipper())
    for b in bounds.bounds:
        rows = held.states(b.part, b.layer)[held.mask]
        assert (rows >= b.low).all() and (rows <= b.high).all(), (b.layer, b.part)


def test_the_config_is_validated_and_read_from_a_mitigation_section():
    for bad, match in (({"quantile": 0.5}, "quantile"), ({"quantile": -0.1}, "quantile"), ({"margin": -1.0}, "margin"),
                       ({"parts": ()}, "parts"), ({"parts": ("h", "x")}, "parts"), ({"parts": ("c", "c")}, "parts"),
                       ({"layers": (-1,)}, "layers")):  # fmt: skip
        with pytest.raises(ConfigError, match=match):
            StateBoundsConfig(**bad)  # type: ignore[arg-type]
    mcfg = from_dict(MitigationConfig, {"state_bounds": {"quantile": 0.01, "margin": 0.5, "parts": ["c"]}})
    assert mcfg.state_bounds == StateBoundsConfig(quantile=0.01, margin=0.5, parts=("c",))
    with pytest.raises(ConfigError, match="layers"):
        fit_bounds([np.zeros((1, 2, 3), np.float32)], [np.zeros((1, 2, 3), np.float32)], np.ones((1, 2), bool),
                   StateBoundsConfig(layers=(1,)))  # fmt: skip


def test_registered_as_a_mitigation_that_measures_one_row(tmp_path, untrained):
    assert "state_bounds" in MITIGATIONS.names()
    mcfg = MitigationConfig(finetune_steps=0, calibration_episodes=20, eval_episodes=16)
    rows = MITIGATIONS.get("state_bounds")(MitigationContext(untrained, CFG, GRID, mcfg, tmp_path))
    assert list(rows) == ["state_bounds"]
    arm = rows["state_bounds"]
    assert arm.clean_success.n == arm.attack_success.n == 16 and "clipped" in arm.title


# --- effect on a tiny backdoored agent

TINY_ENV = EnvConfig(size=5, holes=1, trigger=TriggerConfig(train_steps=(1, 2), eval_steps=(1, 2)))
TINY_GRID = GridSpec(5, 1)


@pytest.fixture(scope="module")
def backdoored() -> RecurrentActorCritic:
    from seqtrojan.train.trainer import train

    with tempfile.TemporaryDirectory() as out:
        cfg = ExperimentConfig(
            env=TINY_ENV,
            agent=AgentConfig(lstm_sizes=(32, 16)),
            ppo=PPOConfig(
                total_steps=131_072,
                num_envs=128,
                rollout_steps=32,
                num_minibatches=2,
                update_epochs=4,
                learning_rate=3e-3,
            ),
            backdoor=BackdoorConfig(enabled=True, mixing="fixed"),
            run=RunConfig(out_dir=out, progress=False, eval_episodes=0, seed=0, checkpoint_every=10**9, threads=1),
        )
        agent, _, _ = load_agent(train(cfg).model_dir)
    return agent.eval()


def _rates(agent, intervention) -> tuple[float, float]:
    out = []
    for trojan, goal in ((False, "user_goal"), (True, "adversary_goal")):
        batch = evaluate_agent(agent, TINY_ENV, TINY_GRID, trojan=trojan, episodes=200, seed=5,
                               intervention=intervention)  # fmt: skip
        out.append(outcome_rate(batch, goal).value)
    return out[0], out[1]


def test_the_bounds_lower_attack_success_of_a_backdoored_agent_and_keep_clean_success(backdoored):
    agent = backdoored
    clean, attack = _rates(agent, None)
    assert attack >= 0.8 and clean >= 0.9  # the backdoor works, and so does the task
    bounds = calibrate_bounds(agent, TINY_ENV, TINY_GRID, StateBoundsConfig(quantile=0.01), episodes=200, seed=0)
    clean_b, attack_b = _rates(agent, bounds.clipper())
    assert attack_b <= attack - 0.4  # measured: 0.91 -> 0.19
    assert clean_b >= clean - 0.05
    loose = dataclasses.replace(bounds, bounds=tuple(dataclasses.replace(b, low=b.low - 1e3, high=b.high + 1e3)
                                                     for b in bounds.bounds))  # fmt: skip
    identity = _rates(agent, lambda layer, t, state: state)  # the same (unfused) step path, nothing edited
    assert _rates(agent, loose.clipper()) == identity  # bounds that never bind change nothing
