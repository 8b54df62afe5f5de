"""Generalized advantage estimation (Schulman et al. 2016) over a batched rollout."""

from __future__ import annotations

import torch


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    dones: torch.Tensor,
    last_value: torch.Tensor,
    gamma: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Advantages and returns.

    Args:
        rewards: (T, B) reward after action t.
        values: (T, B) value estimate of observation t.
        dones: (T, B) 1 where the episode ended with action t (the next observation starts a new episode).
            Time-outs count as ends: the time limit is part of the task, a failure, so it is not bootstrapped.
        last_value: (B,) value of the observation after the rollout.
    Returns:
        advantages (T, B) and returns = advantages + values (T, B).
    """
    steps = rewards.shape[0]
    advantages = torch.zeros_like(rewards)
    not_done = 1.0 - dones.to(rewards.dtype)
    next_value = last_value
    running = torch.zeros_like(last_value)
    for t in range(steps - 1, -1, -1):
        delta = rewards[t] + gamma * next_value * not_done[t] - values[t]
        running = delta + gamma * lam * not_done[t] * running
        advantages[t] = running
        next_value = values[t]
    return advantages, advantages + values
