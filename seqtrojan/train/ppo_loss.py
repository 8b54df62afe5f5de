"""The PPO objective: clipped surrogate, (clipped) value loss and entropy bonus, over all steps of a minibatch or
over the steps a mask picks."""

from __future__ import annotations

from collections.abc import Callable
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
    mean, std = _moments(mask, logits.dtype)
    log_probs = torch.log_softmax(logits, -1)
    new_logprobs = log_probs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    log_ratio = new_logprobs - old_logprobs
    ratio = log_ratio.exp()
    if cfg.norm_adv:
        advantages = (advantages - mean(advantages)) / (std(advantages) + 1e-8)
    pg1 = -advantages * ratio
    pg2 = -advantages * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef)
    policy_loss = mean(torch.maximum(pg1, pg2))
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


Reduce = Callable[[torch.Tensor], torch.Tensor]


def _moments(mask: torch.Tensor | None, dtype: torch.dtype) -> tuple[Reduce, Reduce]:
    """The mean and the (unbiased) standard deviation over all elements, or over those ``mask`` picks."""
    if mask is None:
        return torch.mean, torch.std
    weight = mask.to(dtype)
    count = weight.sum().clamp_min(1.0)

    def mean(x: torch.Tensor) -> torch.Tensor:
        return (x * weight).sum() / count

    def std(x: torch.Tensor) -> torch.Tensor:
        return (mean((x - mean(x)) ** 2) * count / (count - 1).clamp_min(1.0)).sqrt()

    return mean, std
