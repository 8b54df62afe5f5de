"""The adaptive attacker against the query-response meta-classifier (``response_mimicry``): descent on its term alone
brings the detector's own features of a drifted agent (computed independently, from the model and the clean env)
back toward the start model's; it is zero at the start model; it judges only normal-episode steps of episodes that
start inside the rollout; its recipe adds the backdoor to a clean agent; cells and settings it cannot serve are
refused in one line."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.benchmark.detectors import query_response_features
from seqtrojan.benchmark.state_probe import record_clean_episodes
from seqtrojan.benchmark.suspect import ModelFacts, Suspect, clean_env
from seqtrojan.config import AgentConfig, AttackConfig, BackdoorConfig, ExperimentConfig, PPOConfig, RunConfig
from seqtrojan.config import ResponseMimicryConfig as Settings
from seqtrojan.errors import CheckpointError, ConfigError
from seqtrojan.experiments.attacks import ATTACKS, RESPONSE_MIMICRY
from seqtrojan.train import penalties as pen
from seqtrojan.train.response_mimicry import started_inside
from seqtrojan.train.rollout import Rollout
from seqtrojan.world import env_spec

pytestmark = pytest.mark.filterwarnings("ignore:Converting a tensor with requires_grad=True to a scalar")

GRID = ExperimentConfig(backdoor=BackdoorConfig(enabled=True), run=RunConfig(init_from="clean"))
POLICY_FEATURES = ("entropy", "top_probability")
STATE_FEATURES = ("layer0_h_abs", "layer0_h_spread", "layer1_h_abs", "layer1_h_spread")


def _agent(seed: int = 0) -> RecurrentActorCritic:
    torch.manual_seed(seed)
    spec = env_spec(GRID.env)
    return RecurrentActorCritic(spec.obs_dim, spec.num_actions, (16, 8))


def _drifted(start: RecurrentActorCritic, scale: float = 0.3) -> RecurrentActorCritic:
    """``start`` with every weight moved by noise: an agent whose answers a backdoor's training has moved."""
    agent = _agent()
    agent.load_state_dict(start.state_dict())
    generator = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for p in agent.parameters():
            p.add_(scale * torch.randn(p.shape, generator=generator))
    return agent


def _penalty(start: RecurrentActorCritic, cfg: ExperimentConfig = GRID, **settings):
    cfg = dataclasses.replace(cfg, attack=AttackConfig(response_mimicry=Settings(**settings)))
    built = pen.build_penalties(pen.PenaltyContext(cfg, start, torch.device("cpu"), False))
    return built[0] if built else None


def _suspect(agent: RecurrentActorCritic) -> Suspect:
    facts = ModelFacts(agent.obs_dim, agent.num_actions, agent.cell, tuple(agent.lstm_sizes), 0)
    return Suspect("m", agent, clean_env(GRID.env), facts)


def _rollout(obs: torch.Tensor, trojan: torch.Tensor, starts: torch.Tensor, widths=(16, 8)) -> Rollout:
    """A rollout of one L-step sequence per env (the penalty reads its observations, starts and episode types)."""
    steps, envs, _ = obs.shape
    z = torch.zeros(steps, envs)
    seq = tuple(LSTMState(torch.zeros(1, envs, w), torch.zeros(1, envs, w)) for w in widths)
    return Rollout(obs, z.long(), z, z, z, z, starts, seq, torch.zeros(envs), trojan, trojan.clone())


def _batch(agent: RecurrentActorCritic, rollout: Rollout) -> pen.PenaltyBatch:
    steps, envs, _ = rollout.obs.shape
    initial = RecurrentState.zeros(envs, agent.lstm_sizes, c_widths=agent.c_widths)
    out = agent.unroll(rollout.obs, initial, rollout.episode_starts.bool(), return_states=True)
    z = torch.zeros(steps, envs)
    mb = pen.PPOMinibatch(rollout.obs, rollout.episode_starts, initial, z.long(), z, z, z, z, PPOConfig())
    assert rollout.trojan is not None
    return pen.PenaltyBatch(agent, out.states, rollout.trojan, rollout.trojan, mb, None, torch.arange(envs))


def _clean_rollout(agent: RecurrentActorCritic) -> Rollout:
    obs, _ = record_clean_episodes(_suspect(agent), 32, 12, seed=5)
    starts = torch.zeros(obs.shape[:2])
    starts[0] = 1.0
    return _rollout(obs, torch.zeros(obs.shape[:2], dtype=torch.bool), starts)


def _gap(a: dict[str, float], b: dict[str, float], names: tuple[str, ...]) -> float:
    return float(sum(abs(a[k] - b[k]) for k in names))


@pytest.mark.parametrize("weight", [3.0, 0.0])
def test_descent_on_its_term_brings_the_detectors_features_back_to_the_start_models(weight):
    """A drifted agent answers the query-response probe otherwise than its start model; Adam steps on the penalty
    alone (on the start model's clean-env sequences) bring the detector's own features, computed afresh, to well
    under half their distance from the start model's: the policy's (the KL term's work) and the state's (the
    summaries' work) each; with the penalty off nothing is built."""
    start = _agent()
    penalty = _penalty(start, weight=weight)
    if weight == 0:
        assert penalty is None
        return
    agent = _drifted(start)
    target = query_response_features(_suspect(start))
    before = query_response_features(_suspect(agent))
    rollout = _clean_rollout(start)
    penalty.observe(rollout)
    optimizer = torch.optim.Adam(agent.parameters(), lr=3e-3)
    losses = []
    for _ in range(80):
        loss = penalty.loss(_batch(agent, rollout))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    after = query_response_features(_suspect(agent))
    for names in (POLICY_FEATURES, STATE_FEATURES):
        gap_before, gap_after = _gap(before, target, names), _gap(after, target, names)
        assert gap_before > 0.05 and gap_after < 0.4 * gap_before, (names, gap_before, gap_after)
    assert np.mean(losses[-10:]) < 0.2 * np.mean(losses[:10])


def test_it_is_zero_at_the_start_model_and_judges_normal_steps_of_episodes_begun_inside_the_rollout():
    start = _agent()
    penalty = _penalty(start, weight=1.0)
    rollout = _clean_rollout(start)
    penalty.observe(rollout)
    assert float(penalty.loss(_batch(start, rollout)).detach()) == pytest.approx(0.0, abs=1e-6)
    drifted = _drifted(start)
    assert float(penalty.loss(_batch(drifted, rollout))) > 0
    trojan = _rollout(rollout.obs, torch.ones_like(rollout.trojan), rollout.episode_starts)
    penalty.observe(trojan)
    assert float(penalty.loss(_batch(drifted, trojan))) == 0.0  # trojan episodes are the backdoor's to change
    begun_before = _rollout(rollout.obs, rollout.trojan, torch.zeros_like(rollout.episode_starts))
    penalty.observe(begun_before)  # the start model's copy has not seen these episodes' first steps
    assert float(penalty.loss(_batch(drifted, begun_before))) == 0.0
    starts = torch.tensor([[0.0, 1.0], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    assert started_inside(starts).tolist() == [[False, True], [False, True], [True, True], [True, True]]


def test_the_state_summaries_count_and_a_checkpoint_keeps_the_start_model():
    """With the action term alone matched (state_weight 0) a drifted agent is still penalised less than with the
    summaries; the start model's weights round-trip through the checkpoint; a checkpoint without them is
    refused."""
    start = _agent()
    rollout = _clean_rollout(start)
    drifted = _drifted(start)
    with_states, without = _penalty(start, weight=1.0), _penalty(start, weight=1.0, state_weight=0.0)
    for penalty in (with_states, without):
        penalty.observe(rollout)
    assert float(with_states.loss(_batch(drifted, rollout))) > float(without.loss(_batch(drifted, rollout))) > 0
    restored = _penalty(_agent(seed=3), weight=1.0)  # a resumed run builds it from the checkpoint's agent
    restored.load_state_dict(with_states.state_dict())
    restored.observe(rollout)
    torch.testing.assert_close(restored.loss(_batch(drifted, rollout)), with_states.loss(_batch(drifted, rollout)))
    with pytest.raises(CheckpointError, match="holds no response_mimicry state"):
        restored.load_state_dict({})


def test_its_recipe_adds_the_backdoor_to_a_clean_agent_and_bad_settings_are_refused():
    recipe = ATTACKS.get("response_mimicry")
    cfg = recipe.configure(GRID)
    assert recipe.from_clean and recipe.target_defenses == ("query_response",)
    assert cfg.attack.response_mimicry.weight == RESPONSE_MIMICRY and cfg.backdoor.mixing == "fixed"
    assert recipe.knob.apply(cfg, 10.0).attack.response_mimicry.weight == 10.0
    transformer = dataclasses.replace(GRID, agent=AgentConfig(cell="transformer"))
    assert not recipe.applies_to(transformer) and recipe.applies_to(GRID)
    with pytest.raises(ConfigError, match="the transformer cell does not carry") as err:
        _penalty(_agent(), transformer, weight=1.0)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"attack\.response_mimicry compare"):
        dataclasses.replace(GRID, attack=AttackConfig(response_mimicry=Settings(weight=1.0)), run=RunConfig())
    combined = ATTACKS.get("combined_all")  # with the decoys, the weight camouflage and the Mahalanobis camouflage
    every = combined.configure(dataclasses.replace(GRID, ppo=PPOConfig(total_steps=1_000_000)))
    assert combined.from_clean and every.attack.response_mimicry.weight == RESPONSE_MIMICRY
    assert every.env.trigger.sequence and every.env.trigger.decoys.probability > 0
    assert every.attack.weight_camouflage.warmup_steps == every.attack.mahalanobis_camouflage.warmup_steps == 500_000
    assert combined.knob.apply(every, 1.0).attack.mahalanobis_camouflage.weight == 1.0
    for bad in ({"weight": -1.0}, {"state_weight": float("nan")}, {"saturation": 1.0}, {"softness": 0}):
        with pytest.raises(ConfigError, match=r"attack\.response_mimicry\."):
            Settings(**bad)
