"""The adaptive attacker against the multivariate monitor (``mahalanobis_camouflage``): its distance is the monitor's
(same clean rows, same shrinkage), its gradient pulls a trojan state's distance down (and nothing moves without
it), only trojan steps count, its statistics survive a checkpoint, and the rollout records each step's index in
its episode for it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.agent.state import LSTMState
from seqtrojan.config import (
    AttackConfig,
    BackdoorConfig,
    ExperimentConfig,
    MahalanobisCamouflageConfig,
    PPOConfig,
)
from seqtrojan.defense.multivariate import MultivariateConfig, MultivariateMonitor
from seqtrojan.env import EnvConfig
from seqtrojan.errors import ConfigError
from seqtrojan.experiments.attacks import ATTACKS
from seqtrojan.train import penalties as pen
from seqtrojan.train.rollout import Rollout

SIZES = (6, 4)
D = 2 * sum(SIZES)
EPISODE = 10  # every fake episode runs 10 steps


def _penalty(**settings) -> pen.MahalanobisCamouflage:
    cfg = ExperimentConfig(
        backdoor=BackdoorConfig(enabled=True),
        attack=AttackConfig(mahalanobis_camouflage=MahalanobisCamouflageConfig(**settings)),
    )
    torch.manual_seed(0)
    agent = RecurrentActorCritic(12, 4, SIZES)
    built = pen.build_penalties(pen.PenaltyContext(cfg, agent, torch.device("cpu"), False))
    if not built:
        return None  # type: ignore[return-value]
    (penalty,) = built
    assert isinstance(penalty, pen.MahalanobisCamouflage) and penalty.name == "mahalanobis_camouflage"
    return penalty


def _rollout(chunks: int = 6, envs: int = 80, seed: int = 0) -> Rollout:
    """``chunks`` episodes of 10 steps per env, states with a different mean at every step and correlated units;
    the second half of the envs is trojan."""
    g = torch.Generator().manual_seed(seed)
    steps = chunks * EPISODE
    step = torch.arange(steps)[:, None].expand(steps, envs) % EPISODE
    mix = torch.randn(D, D, generator=g) / D**0.5 + torch.eye(D)
    x = torch.randn(steps, envs, D, generator=g) @ mix + 0.3 * step[..., None].float()
    states, start = [], 0
    for w in SIZES:
        states.append(LSTMState(x[..., start : start + w], x[..., start + w : start + 2 * w]))
        start += 2 * w
    trojan = torch.zeros(steps, envs, dtype=torch.bool)
    trojan[:, envs // 2 :] = True
    z = torch.zeros(steps, envs)
    return Rollout(z, z.long(), z, z, z, z, z, (), torch.zeros(envs), trojan, trojan.clone(), tuple(states), step)


def _episodes(rollout: Rollout) -> np.ndarray:
    """(E, 10, D): the clean envs' episodes as the monitor's calibration arrays."""
    assert rollout.states is not None and rollout.trojan is not None
    x = torch.cat([torch.cat([s.h, s.c], -1) for s in rollout.states], -1)[:, ~rollout.trojan[0]]  # (T, B', D)
    steps, envs = x.shape[:2]
    return x.reshape(steps // EPISODE, EPISODE, envs, D).permute(0, 2, 1, 3).reshape(-1, EPISODE, D).numpy()


def test_its_distance_is_the_multivariate_monitors_on_the_same_clean_steps():
    penalty = _penalty(weight=1.0, ema_decay=0.0, min_count=20.0, shrinkage=0.1)
    rollout = _rollout()
    penalty.observe(rollout)
    episodes = _episodes(rollout)  # 240 clean episodes
    options = MultivariateConfig(shrinkage=0.1, ridge=1e-3, min_episodes_per_step=20)
    monitor = MultivariateMonitor.fit(
        episodes, np.ones(episodes.shape[:2], bool), (2 * SIZES[0], 2 * SIZES[1]), options
    )
    q = torch.from_numpy(episodes[:7]).float().reshape(-1, D) + 0.5 * torch.randn(70, D)
    t = torch.arange(EPISODE).repeat(7)
    torch.testing.assert_close(penalty.distance(q, t), monitor.score_vectors(q, t), rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("weight", [5.0, 0.0])
def test_its_gradient_pulls_a_trojan_states_distance_down_and_nothing_moves_without_it(weight):
    """Descent on the penalty alone moves far trojan states toward the clean range, as the multivariate monitor
    (fitted independently on the same clean steps) scores them; with the penalty off (weight 0: not built, no
    term) the states stay where they are."""
    rollout = _rollout()
    episodes = _episodes(rollout)
    monitor = MultivariateMonitor.fit(episodes, np.ones(episodes.shape[:2], bool), (2 * SIZES[0], 2 * SIZES[1]))
    penalty = _penalty(weight=weight, ema_decay=0.0)
    if penalty is not None:
        penalty.observe(rollout)
    g = torch.Generator().manual_seed(5)
    mean = torch.from_numpy(episodes.mean(0)).float()  # (10, D)
    far = (mean[None].expand(3, EPISODE, D) + 4.0 * torch.randn(3, EPISODE, D, generator=g)).transpose(0, 1)
    x = far.clone().requires_grad_(True)  # (L=10, N=3, D) trojan states
    step = torch.arange(EPISODE)[:, None].expand(EPISODE, 3)
    trojan = torch.ones(EPISODE, 3, dtype=torch.bool)
    before = monitor.score_vectors(far.reshape(-1, D), step.reshape(-1))
    optimizer = torch.optim.SGD([x], lr=0.5)
    for _ in range(200):
        states = (LSTMState(x[..., :6], x[..., 6:12]), LSTMState(x[..., 12:16], x[..., 16:]))
        batch = pen.PenaltyBatch(None, states, trojan, trojan, None, step)  # type: ignore[arg-type]
        loss = penalty.loss(batch) if penalty is not None else (x * 0).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = monitor.score_vectors(x.detach().reshape(-1, D), step.reshape(-1))
    if weight > 0:
        assert float(before.min()) > 2 * D**0.5  # far out: every state
        assert float(after.max()) < float(before.min())  # every state pulled in
        assert float(after.median()) < 0.4 * float(before.median()) and float(after.median()) < 2 * D**0.5
    else:
        assert torch.equal(x.detach(), far) and torch.equal(after, before)


def test_only_the_chosen_steps_count_and_inside_the_margin_is_free():
    penalty = _penalty(weight=2.0, ema_decay=0.0, margin=1.0)
    rollout = _rollout()
    penalty.observe(rollout)
    assert rollout.states is not None and rollout.trojan is not None and rollout.episode_step is not None
    step = rollout.episode_step[:EPISODE]
    clean_now = ~rollout.trojan[:EPISODE]
    states = tuple(LSTMState(s.h[:EPISODE], s.c[:EPISODE]) for s in rollout.states)
    inside = penalty.distance(penalty.vectors(states)[clean_now], step[clean_now]) / D**0.5 <= 1.0
    assert float(inside.float().mean()) > 0.5  # clean states are mostly inside the margin
    as_trojan = pen.PenaltyBatch(None, states, clean_now, clean_now, None, step)  # type: ignore[arg-type]
    as_clean = pen.PenaltyBatch(None, states, torch.zeros_like(clean_now), clean_now, None, step)  # type: ignore[arg-type]
    assert float(penalty.loss(as_clean)) == 0.0  # no trojan step
    d = penalty.distance(penalty.vectors(states)[clean_now], step[clean_now]) / D**0.5
    assert float(penalty.loss(as_trojan)) == pytest.approx(2.0 * float(torch.relu(d - 1.0).pow(2).mean()), rel=1e-5)
    active = _penalty(weight=2.0, ema_decay=0.0, margin=1.0, steps="active")
    active.load_state_dict(penalty.state_dict())
    not_yet = pen.PenaltyBatch(None, states, clean_now, torch.zeros_like(clean_now), None, step)  # type: ignore[arg-type]
    assert float(active.loss(not_yet)) == 0.0


def test_its_statistics_decay_and_come_back_from_a_checkpoint():
    penalty = _penalty(weight=1.0, ema_decay=0.5)
    first, second = _rollout(seed=0), _rollout(seed=1)
    penalty.observe(first)
    penalty.observe(second)
    assert first.episode_step is not None and first.trojan is not None
    clean = ~first.trojan
    x = [torch.cat([torch.cat([s.h, s.c], -1) for s in r.states], -1)[clean].double() for r in (first, second)]  # type: ignore[union-attr]
    s0 = x[0][first.episode_step[clean] == 0]
    s1 = x[1][first.episode_step[clean] == 0]
    expected = (0.5 * s0.sum(0) + s1.sum(0)) / (0.5 * len(s0) + len(s1))
    torch.testing.assert_close(penalty.mean[0].double(), expected, rtol=1e-5, atol=1e-5)
    restored = _penalty(weight=1.0, ema_decay=0.5)
    restored.load_state_dict({k: v.clone() for k, v in penalty.state_dict().items()})
    q, t = torch.randn(5, D), torch.tensor([0, 3, 9, 20, 70])
    assert torch.equal(restored.distance(q, t), penalty.distance(q, t))


def test_its_warm_up_waits_for_the_env_steps_then_holds_and_a_checkpoint_keeps_the_count():
    """With ``warmup_steps`` the term is 0 until the rollouts observed pass that many env steps (the statistics are
    gathered from the start), then as without a warm-up; the count comes back from a checkpoint."""
    rollout = _rollout()  # 60 steps x 80 envs = 4800 env steps per rollout
    assert rollout.states is not None and rollout.trojan is not None
    batch = pen.PenaltyBatch(None, rollout.states, rollout.trojan, rollout.trojan, None, rollout.episode_step)  # type: ignore[arg-type]
    plain, waiting = _penalty(weight=2.0, margin=0.0), _penalty(weight=2.0, margin=0.0, warmup_steps=5000)
    for penalty in (plain, waiting):
        penalty.observe(rollout)
    assert float(plain.loss(batch)) > 0 and float(waiting.loss(batch)) == 0.0  # 4800 steps seen: still waiting
    restored = _penalty(weight=2.0, margin=0.0, warmup_steps=5000)
    restored.load_state_dict({k: v.clone() for k, v in waiting.state_dict().items()})
    assert int(restored.steps_seen) == 4800 and float(restored.loss(batch)) == 0.0
    for penalty in (plain, waiting, restored):
        penalty.observe(rollout)  # 9600 steps seen: past it
    assert float(waiting.loss(batch)) == pytest.approx(float(plain.loss(batch)), rel=1e-6)
    assert float(restored.loss(batch)) == pytest.approx(float(plain.loss(batch)), rel=1e-6)
    with pytest.raises(ConfigError, match=r"warmup_steps must be an integer >= 0"):
        MahalanobisCamouflageConfig(warmup_steps=-1)


def test_the_rollout_records_each_steps_index_in_its_episode():
    from seqtrojan.train.trainer import _set_up

    ppo = PPOConfig(num_envs=8, rollout_steps=64, bptt_length=8, num_minibatches=2)
    cfg = ExperimentConfig(
        env=EnvConfig(size=5, holes=1), ppo=ppo, backdoor=BackdoorConfig(enabled=True),
        attack=AttackConfig(mahalanobis_camouflage=MahalanobisCamouflageConfig(weight=1.0)),
    )  # fmt: skip
    _, state = _set_up(cfg, torch.device("cpu"), resuming=False)
    for _ in range(2):  # the second rollout continues episodes in flight
        rollout, _ = state.collector.collect()
        assert rollout.episode_step is not None and rollout.states is not None
        step, starts = rollout.episode_step, rollout.episode_starts.bool()
        assert (step[starts] == 0).all() and (step[1:][~starts[1:]] == step[:-1][~starts[1:]] + 1).all()
        assert int(step.max()) > 0


def test_the_recipe_targets_the_multivariate_monitor_and_bad_settings_are_refused():
    attack = ATTACKS.get("mahalanobis_camouflage")
    assert (
        attack.targets == "multivariate_monitor"
        and "multivariate_monitor" in ATTACKS.entry("mahalanobis_camouflage").description
    )
    cfg = attack.configure(ExperimentConfig(backdoor=BackdoorConfig(enabled=True)))
    assert cfg.attack.mahalanobis_camouflage == MahalanobisCamouflageConfig(weight=5.0, margin=1.0)
    assert dataclasses.replace(cfg.attack.mahalanobis_camouflage, weight=0.0).enabled is False
    for kwargs, message in (
        ({"weight": -1.0}, r"mahalanobis_camouflage\.weight must be a finite number >= 0"),
        ({"steps": "all"}, r"steps must be trojan or active, got 'all'"),
        ({"ema_decay": 1.0}, r"ema_decay must be in \[0, 1\)"),
        ({"max_step": 0}, r"max_step must be a positive integer"),
        ({"min_count": 0.0}, r"min_count must be > 0"),
        ({"shrinkage": 2.0}, r"shrinkage must be in \[0, 1\]"),
    ):
        with pytest.raises(ConfigError, match=message):
            MahalanobisCamouflageConfig(**kwargs)  # type: ignore[arg-type]
