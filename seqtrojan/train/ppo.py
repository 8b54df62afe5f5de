"""The PPO objective and the recurrent update: sequences replayed from their stored start states."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import nn

from seqtrojan.agent.network import RecurrentActorCritic
from seqtrojan.config import PPOConfig
from seqtrojan.train.penalties import Penalty, PenaltyBatch
from seqtrojan.train.rollout import Rollout, initial_state_from


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
) -> LossParts:
    """Clipped surrogate + (clipped) value loss - entropy bonus, averaged over all elements.

    ``logits`` (..., A); every other tensor has the leading shape of ``logits`` without A.
    """
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


def to_sequences(x: torch.Tensor, length: int) -> torch.Tensor:
    """(T, B, ...) -> (L, T / L * B, ...): cut each env's rollout into T / L sequences of length L.

    Sequence ``k * B + b`` is env ``b``'s steps ``k * L .. (k + 1) * L - 1``, matching ``Rollout.seq_states``.
    """
    steps, batch = x.shape[:2]
    chunks = steps // length
    return x.reshape(chunks, length, batch, *x.shape[2:]).transpose(0, 1).reshape(length, chunks * batch, *x.shape[2:])


def ppo_update(
    agent: RecurrentActorCritic,
    optimizer: torch.optim.Optimizer,
    rollout: Rollout,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    cfg: PPOConfig,
    generator: torch.Generator,
    penalties: Sequence[Penalty] = (),
) -> dict[str, float]:
    """``update_epochs`` passes over the rollout's sequences in ``num_minibatches`` minibatches.

    Each of ``penalties`` (the attack's extra loss terms, :mod:`seqtrojan.train.penalties`) adds its weighted value
    to every minibatch's loss; the unroll returns every step's (h, c) only when one of them asks for it. Their means
    over the minibatches come back as ``penalty/<name>``."""
    length = cfg.sequence_length
    needs_states = any(p.needs_states for p in penalties)
    masks = {}
    if penalties and rollout.trojan is not None and rollout.adversary_active is not None:
        masks = {"trojan": rollout.trojan, "active": rollout.adversary_active}
        masks = {name: to_sequences(mask, length) for name, mask in masks.items()}
    seq = {
        name: to_sequences(tensor, length)
        for name, tensor in (
            ("obs", rollout.obs),
            ("starts", rollout.episode_starts),
            ("actions", rollout.actions),
            ("logprobs", rollout.logprobs),
            ("values", rollout.values),
            ("advantages", advantages),
            ("returns", returns),
        )
    }
    n = seq["actions"].shape[1]
    per_batch = n // cfg.num_minibatches
    totals = {k: 0.0 for k in LossParts._fields}
    penalty_totals = {p.name: 0.0 for p in penalties}
    count = 0
    for _ in range(cfg.update_epochs):
        order = torch.randperm(n, generator=generator).to(rollout.obs.device)
        epoch_kl = []
        for mb in order.split(per_batch):
            out = agent.unroll(
                seq["obs"][:, mb], initial_state_from(rollout.seq_states, mb), seq["starts"][:, mb],
                return_states=needs_states,
            )  # fmt: skip
            parts = ppo_loss(
                out.logits,
                out.values,
                seq["actions"][:, mb],
                seq["logprobs"][:, mb],
                seq["values"][:, mb],
                seq["advantages"][:, mb],
                seq["returns"][:, mb],
                cfg,
            )
            loss = parts.loss
            if penalties:
                batch = PenaltyBatch(
                    agent, out.states, masks["trojan"][:, mb] if masks else None,
                    masks["active"][:, mb] if masks else None,
                )  # fmt: skip
                for penalty in penalties:
                    value = penalty.loss(batch)
                    loss = loss + value
                    penalty_totals[penalty.name] += float(value.detach())
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), cfg.max_grad_norm)
            optimizer.step()
            for k, v in parts._asdict().items():
                totals[k] += float(v.detach())
            count += 1
            epoch_kl.append(float(parts.approx_kl))
        if cfg.target_kl is not None and sum(epoch_kl) / len(epoch_kl) > cfg.target_kl:
            break
    stats = {k: v / count for k, v in totals.items()}
    stats.update({f"penalty/{k}": v / count for k, v in penalty_totals.items()})
    var_returns = float(returns.var())
    stats["explained_variance"] = (
        1.0 - float((returns - rollout.values).var()) / var_returns if var_returns > 0 else 0.0
    )
    return stats
