"""The adaptive attacker against the recurrent-state probe (``probe_camouflage``): descent on its term alone makes
the probe itself (computed independently, from the model and the clean env) see less, and with a margin
(``probe_mimicry``) stops near it; it judges only normal-episode
steps; its candidates leave out exactly those that draw the trigger, which it reads as the env draws it; its recipe
moves the trigger where no candidate reaches; envs and cells it cannot serve are refused in one line."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import RecurrentState
from seqtrojan.benchmark.state_probe import (
    ProbeSettings,
    env_candidates,
    probe_features,
    shows_trigger,
    trigger_view,
)
from seqtrojan.benchmark.suspect import ModelFacts, Suspect, clean_env
from seqtrojan.config import AgentConfig, AttackConfig, BackdoorConfig, ExperimentConfig, PPOConfig
from seqtrojan.config import ProbeCamouflageConfig as Settings
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.attacks import (
    ATTACKS,
    IN_DISTRIBUTION_VIEW,
    PROBE_MIMICRY_MARGIN,
    PROBE_SAFE_MINIGRID_CELLS,
)
from seqtrojan.presets import resolve_preset
from seqtrojan.serde import from_dict, load_yaml
from seqtrojan.train import penalties as pen
from seqtrojan.world import env_spec

GRID = ExperimentConfig(backdoor=BackdoorConfig(enabled=True))


def _memory() -> ExperimentConfig:
    return from_dict(ExperimentConfig, load_yaml(resolve_preset("minigrid_memory_backdoor")), "")


def _agent(cfg: ExperimentConfig, sizes=(16, 8)) -> RecurrentActorCritic:
    torch.manual_seed(0)
    spec = env_spec(cfg.env)
    return RecurrentActorCritic(spec.obs_dim, spec.num_actions, sizes)


def _penalty(cfg: ExperimentConfig, agent: RecurrentActorCritic, **settings):
    cfg = dataclasses.replace(cfg, attack=AttackConfig(probe_camouflage=Settings(**settings)))
    built = pen.build_penalties(pen.PenaltyContext(cfg, agent, torch.device("cpu"), False))
    return built[0] if built else None


def _suspect(agent: RecurrentActorCritic, cfg: ExperimentConfig) -> Suspect:
    facts = ModelFacts(agent.obs_dim, agent.num_actions, agent.cell, tuple(agent.lstm_sizes), 0)
    return Suspect("m", agent, clean_env(cfg.env), facts)


def _batch(agent: RecurrentActorCritic, obs: torch.Tensor, trojan: torch.Tensor) -> pen.PenaltyBatch:
    """Sequences that start episodes (zero start states), unrolled with gradients as the update does."""
    steps, n, _ = obs.shape
    starts = torch.zeros(steps, n)
    starts[0] = 1.0
    initial = RecurrentState.zeros(n, agent.lstm_sizes, c_widths=agent.c_widths)
    out = agent.unroll(obs, initial, starts.bool(), return_states=True)
    z = torch.zeros(steps, n)
    mb = pen.PPOMinibatch(obs, starts, initial, z.long(), z, z, z, z, PPOConfig())
    return pen.PenaltyBatch(agent, out.states, trojan, trojan.clone(), mb)


def _clean_views(cfg: ExperimentConfig, agent: RecurrentActorCritic, steps: int = 12, episodes: int = 32):
    from seqtrojan.benchmark.state_probe import record_clean_episodes

    obs, _ = record_clean_episodes(_suspect(agent, cfg), episodes, steps, seed=5)
    return obs


@pytest.mark.parametrize("weight", [3.0, 0.0])
def test_descent_on_its_term_makes_the_probe_see_less(weight):
    """A random grid-world agent remembers one-step view patches; Adam steps on the penalty alone (on clean-env
    sequences of that agent) lower the state probe's largest divergence -- the detector's own feature, computed
    afresh -- to well under half; with the penalty off nothing is built and nothing moves."""
    agent = _agent(GRID)
    before = probe_features(_suspect(agent, GRID), ProbeSettings())["divergence_max"]
    penalty = _penalty(GRID, agent, weight=weight)
    if weight == 0:
        assert penalty is None
        return
    obs = _clean_views(GRID, agent)
    normal = torch.zeros(obs.shape[:2], dtype=torch.bool)
    optimizer = torch.optim.Adam(agent.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss = penalty.loss(_batch(agent, obs, normal))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    after = probe_features(_suspect(agent, GRID), ProbeSettings())["divergence_max"]
    assert before > 0.02 and after < 0.5 * before, (before, after)
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:10])
    assert int(penalty.state_dict()["minibatches"]) == 60  # the draws' count, kept in the checkpoint


def _descended(margin_of_before: float) -> tuple[float, dict[str, float]]:
    """The probe's features of a random grid agent before, and after 60 Adam steps on the penalty (weight 3) with
    its margin at ``margin_of_before`` times the agent's largest divergence before."""
    agent = _agent(GRID)
    before = probe_features(_suspect(agent, GRID), ProbeSettings())["divergence_max"]
    penalty = _penalty(GRID, agent, weight=3.0, margin=margin_of_before * before)
    obs = _clean_views(GRID, agent)
    normal = torch.zeros(obs.shape[:2], dtype=torch.bool)
    optimizer = torch.optim.Adam(agent.parameters(), lr=3e-3)
    for _ in range(60):
        loss = penalty.loss(_batch(agent, obs, normal))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return before, probe_features(_suspect(agent, GRID), ProbeSettings())


def test_its_margin_holds_the_mark_at_the_margin_instead_of_erasing_it():
    """``probe_mimicry``'s mechanism: with the margin at half the agent's largest divergence, descent stops near the
    margin (the probe still reads a mark, far more of one than without a margin), where a margin of 0 erases it."""
    before, erased = _descended(0.0)
    _, held = _descended(0.5)
    assert held["divergence_max"] < before
    assert held["divergence_max"] > 1.4 * erased["divergence_max"], (held, erased)
    assert held["divergence_mean"] > 2.0 * erased["divergence_mean"], (held, erased)
    agent = _agent(GRID)  # a margin above every distance costs nothing
    free = _penalty(GRID, agent, weight=3.0, margin=10.0)
    obs = _clean_views(GRID, agent)
    assert free.loss(_batch(agent, obs, torch.zeros(obs.shape[:2], dtype=torch.bool))).item() == 0.0


def test_it_judges_normal_episode_sequences_only_and_resumes_its_draws():
    agent = _agent(GRID)
    penalty = _penalty(GRID, agent, weight=1.0)
    obs = _clean_views(GRID, agent)
    trojan = torch.ones(obs.shape[:2], dtype=torch.bool)
    assert float(penalty.loss(_batch(agent, obs, trojan))) == 0.0
    first = penalty.loss(_batch(agent, obs, ~trojan))
    assert float(first) > 0 and torch.isfinite(first)
    again = _penalty(GRID, agent, weight=1.0)
    again.load_state_dict(penalty.state_dict())  # a resumed run draws what the straight one draws next
    torch.testing.assert_close(again.loss(_batch(agent, obs, ~trojan)), penalty.loss(_batch(agent, obs, ~trojan)))
    short = obs[:5]  # too short for a replaced step with 4 steps after it
    assert float(_penalty(GRID, agent, weight=1.0).loss(_batch(agent, short, ~trojan[:5]))) == 0.0


def test_the_trigger_is_read_as_the_env_draws_it_and_only_candidates_that_draw_it_are_left_out():
    import gymnasium as gym
    from minigrid.core.constants import COLOR_TO_IDX

    from seqtrojan.wrappers.observations import MiniGridOneHot
    from seqtrojan.wrappers.patches import MiniGridPatch

    memory = _memory()
    obs_dim = env_spec(memory.env).obs_dim
    trigger = memory.env.trigger
    wrapper = MiniGridOneHot(gym.make(memory.env.id))
    drawn = wrapper.observation({"image": MiniGridPatch(trigger.cells, trigger.object, trigger.color, key=None)(
        np.zeros((7, 7, 3), np.uint8), 0)})  # fmt: skip
    view = trigger_view(memory.env, obs_dim)
    on = view[1] > 0
    assert int(on.sum()) == 20 * len(trigger.cells)
    assert torch.equal(torch.from_numpy(drawn)[on], view[0][on])
    candidates = env_candidates(memory.env, obs_dim, ProbeSettings())
    shown = [c for c in candidates if shows_trigger(c, view)]
    assert len(shown) == 1  # the preset's two purple keys at the far row's left: one candidate draws exactly that
    assert shown[0][0].reshape(-1, 20)[0, 11 + COLOR_TO_IDX["purple"]] == 1.0
    moved = ATTACKS.get("probe_camouflage").configure(memory)
    assert moved.env.trigger.cells == PROBE_SAFE_MINIGRID_CELLS and moved.attack.probe_camouflage.weight > 0
    assert not any(shows_trigger(c, trigger_view(moved.env, obs_dim)) for c in candidates)

    grid = GRID.env
    whole = [c for c in env_candidates(grid, 54, ProbeSettings()) if shows_trigger(c, trigger_view(grid, 54))]
    assert len(whole) == 1 and whole[0][1].all()  # the dedicated code over the whole view
    recipe = ATTACKS.get("probe_camouflage").configure(GRID)
    assert recipe.env.trigger.values == tuple(code for row in IN_DISTRIBUTION_VIEW for code in row)
    assert not any(shows_trigger(c, trigger_view(recipe.env, 54)) for c in env_candidates(grid, 54, ProbeSettings()))
    mimicry = ATTACKS.get("probe_mimicry").configure(GRID)  # the same trigger and weight, with a margin
    assert mimicry.env == recipe.env and mimicry.attack.probe_camouflage == dataclasses.replace(
        recipe.attack.probe_camouflage, margin=PROBE_MIMICRY_MARGIN
    )
    assert ATTACKS.get("probe_mimicry").knob.apply(mimicry, 0.3).attack.probe_camouflage.margin == 0.3


def test_envs_and_cells_it_cannot_serve_are_refused_in_one_line():
    transformer = dataclasses.replace(GRID, agent=AgentConfig(cell="transformer"))
    with pytest.raises(ConfigError, match="the transformer cell does not carry") as err:
        _penalty(transformer, _agent(GRID), weight=1.0)
    assert "\n" not in str(err.value)
    assert not ATTACKS.get("probe_camouflage").applies_to(transformer)  # so a zoo never draws it for one
    pong = from_dict(ExperimentConfig, load_yaml(resolve_preset("minatar_breakout")), "")
    assert not ATTACKS.get("probe_camouflage").applies_to(pong)  # no candidates on MinAtar's channels
    assert ATTACKS.get("probe_camouflage").applies_to(_memory()) and ATTACKS.get("probe_camouflage").applies_to(GRID)
    with pytest.raises(ConfigError, match="no candidate inputs on MinAtar"):
        _penalty(dataclasses.replace(pong, backdoor=BackdoorConfig(enabled=True)), _agent(pong), weight=1.0)
    for bad in ({"weight": -1.0}, {"after": 0}, {"after": 1.5}, {"seed": -1}):
        with pytest.raises(ConfigError, match=r"attack\.probe_camouflage\."):
            Settings(**bad)
