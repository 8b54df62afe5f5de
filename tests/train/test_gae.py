"""GAE against closed forms and a scalar reference loop."""

from __future__ import annotations

import pytest
import torch

from seqtrojan.train.gae import compute_gae


def test_monte_carlo_return_with_constant_value_and_one_terminal_reward():
    n, gamma, value, reward = 7, 0.9, 0.3, 1.0
    rewards = torch.zeros(n, 1)
    rewards[-1] = reward
    dones = torch.zeros(n, 1)
    dones[-1] = 1
    values = torch.full((n, 1), value)
    adv, ret = compute_gae(rewards, values, dones, torch.tensor([123.0]), gamma, lam=1.0)
    expected = torch.tensor([gamma ** (n - 1 - t) * reward for t in range(n)]).unsqueeze(1)
    torch.testing.assert_close(ret, expected)
    torch.testing.assert_close(adv, expected - value)


@pytest.mark.parametrize("lam", [0.0, 0.5, 0.95])
def test_closed_form_for_general_lambda(lam):
    n, gamma, v, r = 6, 0.97, 0.4, -1.0
    rewards = torch.zeros(n, 1)
    rewards[-1] = r
    dones = torch.zeros(n, 1)
    dones[-1] = 1
    adv, _ = compute_gae(rewards, torch.full((n, 1), v), dones, torch.zeros(1), gamma, lam)
    gl = gamma * lam
    for t in range(n):
        expected = gl ** (n - 1 - t) * (r - v) + sum(gl**k * (gamma - 1) * v for k in range(n - 1 - t))
        assert float(adv[t, 0]) == pytest.approx(expected, rel=1e-5)


def test_bootstraps_from_last_value_and_stops_at_episode_ends():
    gamma, lam = 0.99, 0.95
    rewards = torch.tensor([[0.0], [1.0], [0.0], [0.0]])
    dones = torch.tensor([[0.0], [1.0], [0.0], [0.0]])
    values = torch.tensor([[0.5], [0.6], [0.2], [0.1]])
    last = torch.tensor([0.7])
    adv, _ = compute_gae(rewards, values, dones, last, gamma, lam)
    d3 = 0.0 + gamma * 0.7 - 0.1
    d2 = 0.0 + gamma * 0.1 - 0.2
    d1 = 1.0 - 0.6
    d0 = 0.0 + gamma * 0.6 - 0.5
    a3 = d3
    a2 = d2 + gamma * lam * a3
    a1 = d1  # episode ended: nothing flows back across the boundary
    a0 = d0 + gamma * lam * a1
    torch.testing.assert_close(adv[:, 0], torch.tensor([a0, a1, a2, a3]))


def test_matches_scalar_reference_on_random_batches():
    g = torch.Generator().manual_seed(0)
    steps, batch, gamma, lam = 20, 8, 0.95, 0.9
    rewards = torch.randn(steps, batch, generator=g)
    values = torch.randn(steps, batch, generator=g)
    dones = (torch.rand(steps, batch, generator=g) < 0.2).float()
    last = torch.randn(batch, generator=g)
    adv, ret = compute_gae(rewards, values, dones, last, gamma, lam)
    for b in range(batch):
        running, expected = 0.0, [0.0] * steps
        for t in reversed(range(steps)):
            nxt = float(last[b]) if t == steps - 1 else float(values[t + 1, b])
            nonterminal = 1.0 - float(dones[t, b])
            delta = float(rewards[t, b]) + gamma * nxt * nonterminal - float(values[t, b])
            running = delta + gamma * lam * nonterminal * running
            expected[t] = running
        torch.testing.assert_close(adv[:, b], torch.tensor(expected), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ret, adv + values)
