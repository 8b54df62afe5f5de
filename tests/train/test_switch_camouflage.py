"""The adaptive attacker against the goal-switch monitor (``switch_camouflage``): its distance is the monitor's (same
clean transitions, same shrinkage), its gradient makes an abrupt output transition predictable (and nothing moves
without it), and an episode's first step is never judged."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState, RecurrentState
from seqtrojan.config import AttackConfig, BackdoorConfig, ExperimentConfig, PPOConfig, SwitchCamouflageConfig
from seqtrojan.defense.goal_switch import GoalSwitchConfig, GoalSwitchMonitor, output_features
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.attacks import ATTACKS
from seqtrojan.train import penalties as pen
from seqtrojan.train.rollout import Rollout

SIZES = (6, 4)
EPISODE = 10


def _agent() -> RecurrentActorCritic:
    torch.manual_seed(0)
    return RecurrentActorCritic(12, 4, SIZES)


def _penalty(agent: RecurrentActorCritic, **settings) -> pen.SwitchCamouflage | None:
    cfg = ExperimentConfig(
        backdoor=BackdoorConfig(enabled=True),
        attack=AttackConfig(switch_camouflage=SwitchCamouflageConfig(**settings)),
    )
    built = pen.build_penalties(pen.PenaltyContext(cfg, agent, torch.device("cpu"), False))
    if not built:
        return None
    (penalty,) = built
    assert isinstance(penalty, pen.SwitchCamouflage) and penalty.name == "switch_camouflage"
    return penalty


def _rollout(chunks: int = 6, envs: int = 80, seed: int = 0) -> Rollout:
    """``chunks`` episodes of 10 steps per env; the last layer's h follows a noisy AR(1) around a per-step drift;
    the second half of the envs is trojan."""
    g = torch.Generator().manual_seed(seed)
    steps = chunks * EPISODE
    step = torch.arange(steps)[:, None].expand(steps, envs) % EPISODE
    h = torch.zeros(steps, envs, SIZES[-1])
    for t in range(steps):
        noise = torch.randn(envs, SIZES[-1], generator=g)
        h[t] = noise if t % EPISODE == 0 else 0.7 * h[t - 1] + 0.5 * noise
    h = h + 0.2 * step[..., None].float()
    first = torch.randn(steps, envs, SIZES[0], generator=g)
    states = (LSTMState(first, first), LSTMState(h, h))
    trojan = torch.zeros(steps, envs, dtype=torch.bool)
    trojan[:, envs // 2 :] = True
    z = torch.zeros(steps, envs)
    return Rollout(z, z.long(), z, z, z, z, z, (), torch.zeros(envs), trojan, trojan.clone(), states, step)


def _minibatch() -> pen.PPOMinibatch:
    """Three sequences of 10 steps starting episodes (zero start states); only ``initial`` is read."""
    initial = RecurrentState(tuple(LSTMState(torch.zeros(3, w), torch.zeros(3, w)) for w in SIZES))
    z = torch.zeros(EPISODE, 3)
    return pen.PPOMinibatch(z, z, initial, z.long(), z, z, z, z, PPOConfig())


def _clean_outputs(agent: RecurrentActorCritic, rollout: Rollout) -> np.ndarray:
    """(E, 10, F): the clean envs' episodes of outputs, as the monitor's calibration arrays."""
    assert rollout.states is not None and rollout.trojan is not None
    with torch.no_grad():
        x = output_features(agent, rollout.states[-1].h[:, ~rollout.trojan[0]], GoalSwitchConfig())  # (T, B', F)
    steps, envs, f = x.shape
    return x.reshape(steps // EPISODE, EPISODE, envs, f).permute(0, 2, 1, 3).reshape(-1, EPISODE, f).numpy()


def test_its_distance_is_the_goal_switch_monitors_on_the_same_clean_transitions():
    agent = _agent()
    penalty = _penalty(agent, weight=1.0, ema_decay=0.0, shrinkage=0.1)
    assert penalty is not None
    rollout = _rollout()
    penalty.observe(rollout)
    x = _clean_outputs(agent, rollout)  # 240 clean episodes
    options = GoalSwitchConfig(shrinkage=0.1, ridge=1e-3, min_episodes_per_step=20)
    monitor = GoalSwitchMonitor.fit(agent, x, np.ones(x.shape[:2], bool), options)
    assert rollout.states is not None
    with torch.no_grad():
        assert torch.allclose(penalty.outputs(rollout.states[-1].h), output_features(agent, rollout.states[-1].h,
                                                                                     options))  # fmt: skip
    q = torch.from_numpy(x[:7]).float()
    now, before = q[:, 1:].reshape(-1, q.shape[-1]), q[:, :-1].reshape(-1, q.shape[-1])
    now = now + 0.3 * torch.randn_like(now)
    t = torch.arange(1, EPISODE).repeat(7)
    torch.testing.assert_close(penalty.distance(now, before, t), monitor.distance(now, before, t), rtol=2e-3,
                               atol=2e-3)  # fmt: skip


@pytest.mark.parametrize("weight", [5.0, 0.0])
def test_its_gradient_makes_an_abrupt_switch_predictable_and_nothing_moves_without_it(weight):
    """Trojan sequences whose last-layer h jumps at one step (an abrupt change of policy and value): descent on the
    penalty alone lowers that transition's distance as the goal-switch monitor (fitted independently) scores it;
    with the penalty off nothing moves."""
    agent = _agent()
    rollout = _rollout()
    x = _clean_outputs(agent, rollout)
    monitor = GoalSwitchMonitor.fit(agent, x, np.ones(x.shape[:2], bool))
    penalty = _penalty(agent, weight=weight, ema_decay=0.0)
    if penalty is not None:
        penalty.observe(rollout)
    assert rollout.states is not None
    h0 = rollout.states[-1].h[:EPISODE, -3:].clone()  # (L, N=3, H): three trojan sequences from episode starts
    h0[5:] += 3.0 * torch.tensor([1.0, -1.0, 1.0, -1.0])  # the switch at step 5
    h = h0.clone().requires_grad_(True)
    step = rollout.episode_step[:EPISODE, -3:] if rollout.episode_step is not None else None
    assert step is not None
    trojan = torch.ones(EPISODE, 3, dtype=torch.bool)
    mb = _minibatch()

    def switch_distance(hh: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            out = output_features(agent, hh, GoalSwitchConfig())
        return monitor.distance(out[5], out[4], torch.full((3,), 5))

    before = switch_distance(h0)
    optimizer = torch.optim.SGD([h], lr=0.2)
    for _ in range(150):
        states = (LSTMState(torch.zeros(EPISODE, 3, 6), torch.zeros(EPISODE, 3, 6)), LSTMState(h, h))
        batch = pen.PenaltyBatch(agent, states, trojan, trojan, mb, step)
        loss = penalty.loss(batch) if penalty is not None else (h * 0).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = switch_distance(h.detach())
    if weight > 0:
        assert float(before.min()) > 3 * 5**0.5  # abrupt: far beyond a clean transition (about sqrt(F), F = 5)
        assert float(after.max()) < 0.6 * float(before.min()), (before, after)
    else:
        assert torch.equal(h.detach(), h0) and torch.equal(after, before)


def test_an_episodes_first_step_is_never_judged():
    agent = _agent()
    penalty = _penalty(agent, weight=3.0, ema_decay=0.0, margin=0.0)
    assert penalty is not None
    rollout = _rollout()
    penalty.observe(rollout)
    assert rollout.states is not None and rollout.episode_step is not None
    h = rollout.states[-1].h[:EPISODE, -3:] + 5.0  # far out at every step
    states = (LSTMState(torch.zeros(EPISODE, 3, 6), torch.zeros(EPISODE, 3, 6)), LSTMState(h, h))
    mb = _minibatch()
    only_first = torch.zeros(EPISODE, 3, dtype=torch.bool)
    only_first[0] = True
    step = rollout.episode_step[:EPISODE, -3:]
    assert float(penalty.loss(pen.PenaltyBatch(agent, states, only_first, only_first, mb, step)).detach()) == 0.0
    later = torch.zeros_like(only_first)
    later[3] = True
    assert float(penalty.loss(pen.PenaltyBatch(agent, states, later, later, mb, step)).detach()) > 0.0
    restored = _penalty(agent, weight=3.0, ema_decay=0.0, margin=0.0)
    assert restored is not None
    restored.load_state_dict({k: v.clone() for k, v in penalty.state_dict().items()})
    q, t = torch.randn(4, 5), torch.tensor([1, 3, 9, 30])
    assert torch.equal(restored.distance(q, q.flip(0), t), penalty.distance(q, q.flip(0), t))


def test_the_recipe_targets_the_goal_switch_monitor_and_bad_settings_are_refused():
    attack = ATTACKS.get("switch_camouflage")
    assert attack.targets == "goal_switch" and attack.from_clean  # added to a trained clean agent
    cfg = attack.configure(ExperimentConfig(backdoor=BackdoorConfig(enabled=True)))
    assert cfg.attack.switch_camouflage == SwitchCamouflageConfig(weight=5.0, margin=1.0)
    for kwargs, message in (
        ({"weight": -1.0}, r"switch_camouflage\.weight must be a finite number >= 0"),
        ({"steps": "all"}, r"steps must be trojan or active, got 'all'"),
        ({"ema_decay": 1.0}, r"ema_decay must be in \[0, 1\)"),
        ({"max_step": 1}, r"max_step must be an integer >= 2"),
        ({"min_count": 0.0}, r"min_count must be > 0"),
        ({"shrinkage": 2.0}, r"shrinkage must be in \[0, 1\]"),
        ({"prob_floor": 0.0}, r"prob_floor must be > 0"),
    ):
        with pytest.raises(ConfigError, match=message):
            SwitchCamouflageConfig(**kwargs)  # type: ignore[arg-type]
