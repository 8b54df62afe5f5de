"""The PPO objective: clipped surrogate, (clipped) value loss and entropy bonus, over all steps of a minibatch or
over the steps a mask picks."""

from __future__ import annotations

from typing import NamedTuple

import torch

from seqtrojan.config import PPOConfig


class LossParts(NamedTuple):
    loss: torch.Tensor
    policy_loss: torch.Tensor
    value_loss: torch.Tensor
    entropy: torch.Tensor
    approx_kl: torch.Tensor
    clip_fraction: torch.Tensor


def ppo_loss(
    logits: torch.Tensor,
    values: torch.Tensor,
    actions: torch.Tensor,
    old_logprobs: torch.Tensor,
    old_values: torch.Tensor,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    cfg: PPOConfig,
    mask: torch.Tensor | None = None,
) -> LossParts:
    """Clipped surrogate + (clipped) value loss - entropy bonus, averaged over all elements, or over the elements
    where the bool ``mask`` is true (advantages then normalised over those; no element: every part is 0).

    ``logits`` (..., A); every other tensor has the leading shape of ``logits`` without A.
    """
    if mask is not None:
        return _masked_ppo_loss(logits, values, actions, old_logprobs, old_values, advantages, returns, cfg, mask)
    log_probs = torch.log_softmax(logits, -1)
    new_logprobs = log_probs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    log_ratio = new_logprobs - old_logprobs
    ratio = log_ratio.exp()
    if cfg.norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    pg1 = -advantages * ratio
    pg2 = -advantages * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef)
    policy_loss = torch.maximum(pg1, pg2).mean()
    if cfg.clip_value_loss:
        clipped = old_values + (values - old_values).clamp(-cfg.clip_coef, cfg.clip_coef)
        value_loss = 0.5 * torch.maximum((values - returns) ** 2, (clipped - returns) ** 2).mean()
    else:
        value_loss = 0.5 * ((values - returns) ** 2).mean()
    entropy = -(log_probs.exp() * log_probs).sum(-1).mean()
    loss = policy_loss - cfg.ent_coef * entropy + cfg.vf_coef * value_loss
    with torch.no_grad():
        approx_kl = ((ratio - 1) - log_ratio).mean()
        clip_fraction = ((ratio - 1).abs() > cfg.clip_coef).float().mean()
    return LossParts(loss, policy_loss, value_loss, entropy, approx_kl, clip_fraction)


def _masked_ppo_loss(
    logits: torch.Tensor,
    values: torch.Tensor,
    actions: torch.Tensor,
    old_logprobs: torch.Tensor,
    old_values: torch.Tensor,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    cfg: PPOConfig,
    mask: torch.Tensor,
) -> LossParts:
    """:func:`ppo_loss` over the elements ``mask`` picks (means are sums over them divided by their count)."""
    weight = mask.to(logits.dtype)
    count = weight.sum().clamp_min(1.0)

    def mean(x: torch.Tensor) -> torch.Tensor:
        return (x * weight).sum() / count

    log_probs = torch.log_softmax(logits, -1)
    new_logprobs = log_probs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    log_ratio = new_logprobs - old_logprobs
    ratio = log_ratio.exp()
    if cfg.norm_adv:
        centre = mean(advantages)
        spread = (mean((advantages - centre) ** 2) * count / (count - 1).clamp_min(1.0)).sqrt()
        advantages = (advantages - centre) / (spread + 1e-8)
    policy_loss = mean(
        torch.maximum(-advantages * ratio, -advantages * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef))
    )
    if cfg.clip_value_loss:
        clipped = old_values + (values - old_values).clamp(-cfg.clip_coef, cfg.clip_coef)
        value_loss = 0.5 * mean(torch.maximum((values - returns) ** 2, (clipped - returns) ** 2))
    else:
        value_loss = 0.5 * mean((values - returns) ** 2)
    entropy = mean(-(log_probs.exp() * log_probs).sum(-1))
    loss = policy_loss - cfg.ent_coef * entropy + cfg.vf_coef * value_loss
    with torch.no_grad():
        approx_kl = mean((ratio - 1) - log_ratio)
        clip_fraction = mean(((ratio - 1).abs() > cfg.clip_coef).to(logits.dtype))
    return LossParts(loss, policy_loss, value_loss, entropy, approx_kl, clip_fraction)
