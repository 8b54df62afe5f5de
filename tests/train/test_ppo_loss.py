"""The PPO objective: ratio 1, clipping, the value loss and the entropy bonus."""

from __future__ import annotations

import math

import torch

from seqtrojan.config import PPOConfig
from seqtrojan.train.ppo import ppo_loss
from seqtrojan.train.rollout import to_sequences

CFG = PPOConfig(norm_adv=False, clip_value_loss=False, ent_coef=0.0, vf_coef=0.5)


def parts(logits, actions, old_logprobs, adv, values=None, returns=None, old_values=None, cfg=CFG):
    n = actions.shape[0]
    values = torch.zeros(n) if values is None else values
    returns = torch.zeros(n) if returns is None else returns
    old_values = values.detach() if old_values is None else old_values
    return ppo_loss(logits, values, actions, old_logprobs, old_values, adv, returns, cfg)


def test_ratio_one_gives_minus_mean_advantage_and_zero_kl():
    logits = torch.randn(6, 4)
    actions = torch.randint(0, 4, (6,))
    old = torch.log_softmax(logits, -1).gather(-1, actions[:, None]).squeeze(-1)
    adv = torch.randn(6)
    p = parts(logits, actions, old, adv)
    assert torch.isclose(p.policy_loss, -adv.mean())
    assert float(p.approx_kl) == 0.0 and float(p.clip_fraction) == 0.0


def test_clipped_ratio_gives_no_policy_gradient():
    logits = torch.zeros(1, 4, requires_grad=True)
    actions = torch.tensor([2])
    old = torch.tensor([math.log(0.25) - 0.5])  # ratio = e^0.5 > 1.2
    p = parts(logits, actions, old, torch.tensor([1.0]))
    p.policy_loss.backward()
    assert torch.count_nonzero(logits.grad) == 0
    assert float(p.clip_fraction) == 1.0
    # With a negative advantage the unclipped term is the max: the gradient flows.
    logits.grad = None
    parts(logits, actions, old, torch.tensor([-1.0])).policy_loss.backward()
    # loss = ratio = exp(logp(2) - old): its gradient is ratio * (onehot(2) - softmax), softmax = 1/4 everywhere
    expected = math.exp(0.5) * torch.tensor([[-0.25, -0.25, 0.75, -0.25]])
    torch.testing.assert_close(logits.grad, expected)


def test_value_loss_plain_and_clipped():
    logits = torch.zeros(2, 4)
    actions = torch.zeros(2, dtype=torch.long)
    old = torch.full((2,), math.log(0.25))
    values = torch.tensor([1.0, 0.0])
    returns = torch.tensor([0.0, 2.0])
    p = parts(logits, actions, old, torch.zeros(2), values, returns)
    assert torch.isclose(p.value_loss, torch.tensor(0.5 * (1.0 + 4.0) / 2))
    cfg = PPOConfig(norm_adv=False, clip_value_loss=True, clip_coef=0.2)
    old_values = torch.tensor([0.0, 0.0])
    p = parts(logits, actions, old, torch.zeros(2), values, returns, old_values, cfg)
    # env 0: unclipped (1-0)^2 = 1, clipped 0.2^2 -> max 1; env 1: (0-2)^2 = 4 both ways.
    assert torch.isclose(p.value_loss, torch.tensor(0.5 * (1.0 + 4.0) / 2))


def test_entropy_of_uniform_policy_and_bonus_sign():
    logits = torch.zeros(3, 4)
    actions = torch.zeros(3, dtype=torch.long)
    old = torch.full((3,), math.log(0.25))
    cfg = PPOConfig(norm_adv=False, ent_coef=0.1, clip_value_loss=False)
    p = parts(logits, actions, old, torch.zeros(3), cfg=cfg)
    assert torch.isclose(p.entropy, torch.tensor(math.log(4.0)))
    assert torch.isclose(p.loss, p.policy_loss - 0.1 * p.entropy + cfg.vf_coef * p.value_loss)


def test_to_sequences_cuts_each_env_rollout_in_order():
    x = torch.arange(8 * 3).view(8, 3)  # (T=8, B=3), value = t * 3 + b
    seq = to_sequences(x, 4)  # (L=4, 2 * 3)
    assert seq.shape == (4, 6)
    assert seq[:, 0].tolist() == [0, 3, 6, 9]  # env 0, steps 0..3
    assert seq[:, 3 + 2].tolist() == [14, 17, 20, 23]  # chunk 1, env 2: steps 4..7


def test_a_mask_picks_steps_as_if_only_they_were_given():
    torch.manual_seed(0)
    cfg = PPOConfig(norm_adv=True, clip_value_loss=True, ent_coef=0.01, vf_coef=0.5)
    n = 40
    logits, values = torch.randn(n, 3), torch.randn(n)
    actions = torch.randint(0, 3, (n,))
    old_logprobs = torch.log_softmax(logits + 0.3 * torch.randn(n, 3), -1).gather(-1, actions[:, None]).squeeze(-1)
    old_values, adv, returns = values + 0.1 * torch.randn(n), torch.randn(n), torch.randn(n)
    args = (logits, values, actions, old_logprobs, old_values, adv, returns, cfg)
    everything = ppo_loss(*args)
    for a, b in zip(ppo_loss(*args, mask=torch.ones(n, dtype=torch.bool)), everything):
        torch.testing.assert_close(a, b)
    mask = torch.rand(n) < 0.4
    picked = ppo_loss(*(x[mask] for x in args[:-1]), cfg)
    for a, b in zip(ppo_loss(*args, mask=mask), picked):
        torch.testing.assert_close(a, b)
    assert float(ppo_loss(*args, mask=torch.zeros(n, dtype=torch.bool)).loss) == 0.0
